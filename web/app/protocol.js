// The viewer side of protocol v1 (protocol/README.md): binary vector batches read straight into
// typed arrays, no per-vector objects.

export const BATCH_HEADER_BYTES = 40;
export const BATCH_RECORD_BYTES = 40;
/** With header flag bit 1 (asked for with `uncertainty: true`): u, v, w sigmas per vector. */
export const BATCH_SIGMA_BYTES = 12;
/** Floats per record: the record is 40 bytes = 10 float32 slots. */
export const RECORD_FLOATS = 10;
export const KIND_CAUSAL = 1;
export const KIND_REFINED = 2;
export const CONVENTIONS = ['opencv', 'unity', 'webxr'];

export class BatchError extends Error {}

/**
 * Decodes one `MRPV` batch. Positions of record i are floats [10i+2, 10i+5) of `floats`,
 * velocities [10i+5, 10i+8), the fit residual 10i+8; `trackId(i)` gives the track id;
 * `sigmas` (or null) holds the 1-sigma velocity errors, floats [3i, 3i+3).
 * @param {ArrayBuffer} buffer a whole WebSocket binary message
 */
export function decodeBatch(buffer) {
  if (!(buffer instanceof ArrayBuffer) || buffer.byteLength < BATCH_HEADER_BYTES) {
    throw new BatchError(`batch of ${buffer?.byteLength ?? '?'} bytes, shorter than its 40-byte header`);
  }
  const view = new DataView(buffer);
  const magic = String.fromCharCode(view.getUint8(0), view.getUint8(1), view.getUint8(2), view.getUint8(3));
  if (magic !== 'MRPV') throw new BatchError(`not a vector batch (magic ${JSON.stringify(magic)})`);
  const version = view.getUint8(4);
  if (version !== 1) throw new BatchError(`protocol version ${version}, this page speaks 1`);
  const kind = view.getUint8(5);
  const convention = CONVENTIONS[view.getUint8(6)];
  const count = view.getUint32(12, true);
  const withSigmas = (view.getUint8(7) & 2) === 2;
  const recordsEnd = BATCH_HEADER_BYTES + BATCH_RECORD_BYTES * count;
  const expected = recordsEnd + (withSigmas ? BATCH_SIGMA_BYTES * count : 0);
  if (buffer.byteLength !== expected) {
    throw new BatchError(`batch of ${buffer.byteLength} bytes, ${count} records need ${expected}`);
  }
  const words = new Uint32Array(buffer, BATCH_HEADER_BYTES, count * RECORD_FLOATS);
  return {
    kind,
    refined: kind === KIND_REFINED,
    convention,
    world: (view.getUint8(7) & 1) === 1,
    session: view.getUint32(8, true),
    count,
    // Frame indices and track ids are u64; they stay exact as Numbers below 2^53.
    frameIndex: Number(view.getBigUint64(16, true)),
    tS: view.getFloat64(24, true),
    processingUs: view.getUint32(32, true),
    ageUs: view.getUint32(36, true),
    floats: new Float32Array(buffer, BATCH_HEADER_BYTES, count * RECORD_FLOATS),
    sigmas: withSigmas ? new Float32Array(buffer, recordsEnd, count * 3) : null,
    trackId: (i) => words[i * RECORD_FLOATS] + words[i * RECORD_FLOATS + 1] * 2 ** 32,
  };
}

/** Columns of a `field` message's cell rows (`FIELD_COLUMNS` in protocol/README.md). */
export const FIELD_COLUMNS = ['x', 'y', 'z', 'n', 'u', 'v', 'w', 'std_u', 'std_v', 'std_w', 'sem_u', 'sem_v', 'sem_w', 'tracks'];

/**
 * Reads a `field` message's cells as { x, y, z, n, u, v, w } objects, by the column names it
 * declares (so columns added later do not move these).
 */
export function fieldCells(message) {
  const columns = Array.isArray(message?.columns) ? message.columns : [];
  const at = Object.fromEntries(columns.map((name, i) => [name, i]));
  if (['x', 'y', 'z', 'n', 'u', 'v', 'w'].some((c) => at[c] === undefined)) return [];
  return (Array.isArray(message.cells) ? message.cells : []).map((row) => ({
    x: row[at.x], y: row[at.y], z: row[at.z], n: row[at.n], u: row[at.u], v: row[at.v], w: row[at.w],
  }));
}
