// Unit tests of the page's pure modules: node --test web/tests/
import assert from 'node:assert/strict';
import { readFileSync } from 'node:fs';
import { test } from 'node:test';
import { decodeBatch, BatchError, fieldCells, KIND_CAUSAL, KIND_REFINED } from '../app/protocol.js';
import { speedColor, niceCeiling } from '../app/colormap.js';
import { Placement } from '../app/placement.js';

const golden = (name) => {
  const bytes = readFileSync(new URL(`../../protocol/golden/${name}`, import.meta.url));
  return bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.byteLength);
};

test('golden batches decode as protocol/README.md says', () => {
  const b = decodeBatch(golden('batch-causal-unity.bin'));
  assert.equal(b.kind, KIND_CAUSAL);
  assert.equal(b.convention, 'unity');
  assert.equal(b.world, true);
  assert.equal(b.session, 1);
  assert.equal(b.count, 2);
  assert.equal(b.frameIndex, 42);
  assert.equal(b.tS, 1.4);
  assert.equal(b.processingUs, 2100);
  assert.equal(b.ageUs, 3400);
  assert.equal(b.trackId(0), 7);
  // Unity flips y: the OpenCV position (0.5, 0.25, 1.5) travels as (0.5, -0.25, 1.5).
  assert.deepEqual(Array.from(b.floats.subarray(2, 8)), [0.5, -0.25, 1.5, 0.125, 0.0625, 0.03125]);
  const r = decodeBatch(golden('batch-refined-opencv.bin'));
  assert.equal(r.kind, KIND_REFINED);
  assert.equal(r.refined, true);
  assert.equal(r.world, false);
  const e = decodeBatch(golden('batch-causal-empty-webxr.bin'));
  assert.equal(e.count, 0);
  assert.equal(e.convention, 'webxr');
});

test('malformed batches are refused with a reason', () => {
  const good = golden('batch-causal-unity.bin');
  assert.throws(() => decodeBatch(good.slice(0, good.byteLength - 1)), BatchError);
  assert.throws(() => decodeBatch(good.slice(0, 39)), /shorter than its 40-byte header/);
  const wrongMagic = good.slice(0);
  new Uint8Array(wrongMagic)[0] = 0x58;
  assert.throws(() => decodeBatch(wrongMagic), /magic/);
  const wrongVersion = good.slice(0);
  new Uint8Array(wrongVersion)[4] = 2;
  assert.throws(() => decodeBatch(wrongVersion), /version 2/);
  assert.throws(() => decodeBatch(golden('frame-raw8-4x2.bin')), /not a vector batch/);
});

test('speed colours match the Rerun log (src/rerun_log.rs)', () => {
  const byte = (c) => c.map((v) => Math.round(v * 255));
  assert.deepEqual(byte(speedColor(0, 1)), [68, 1, 84]);
  assert.deepEqual(byte(speedColor(1, 1)), [253, 231, 37]);
  assert.deepEqual(byte(speedColor(5, 1)), [253, 231, 37]);
  assert.deepEqual(byte(speedColor(0.5, 1)), [33, 145, 140]);
  assert.equal(niceCeiling(0.13), 0.2);
  assert.equal(niceCeiling(3), 5);
  assert.equal(niceCeiling(1), 1);
  assert.equal(niceCeiling(0.4), 0.5);
});

test('the volume is centred on the anchor and fitted to the view, or drawn at true scale', () => {
  const p = new Placement({ anchor: [0, 1.3, -1.2], fitSize: 0.6, settleBatches: 3 });
  // Particles filling x in [-1, 1], y in [0, 2], z in [-3, -1]: 200 per batch, stride 10 floats.
  let seed = 1;
  const random = () => ((seed = (seed * 16807) % 2147483647) / 2147483647);
  for (let batch = 0; batch < 5; batch++) {
    const floats = new Float32Array(200 * 10);
    for (let i = 0; i < 200; i++) {
      floats.set([random() * 2 - 1, random() * 2, -1 - random() * 2, 0.1, 0, 0], i * 10 + 2);
    }
    p.observe(floats, 200);
  }
  assert.ok(p.fixed);
  assert.equal(p.batchesSeen, 3, 'the mapping stops moving once fixed');
  p.centre.forEach((c, k) => assert.ok(Math.abs(c - [0, 1, -2][k]) < 0.1, `centre ${p.centre}`));
  assert.ok(Math.abs(p.extent - 2) < 0.15, `extent ${p.extent}`);
  assert.ok(Math.abs(p.scale - 0.6 / p.extent) < 1e-12);
  p.map(p.centre).forEach((v, k) => assert.ok(Math.abs(v - p.anchor[k]) < 1e-9));
  assert.ok(Math.abs(p.medianSpeed - 0.1) < 1e-6);
  p.trueScale = true;
  assert.equal(p.scale, 1);
  const corner = p.map([p.centre[0] + 1, p.centre[1], p.centre[2]]);
  assert.ok(Math.abs(corner[0] - 1) < 1e-9, 'one metre stays one metre');
  p.reset();
  assert.equal(p.fixed, false);
});

test('a batch with uncertainties carries them after the records', () => {
  const b = decodeBatch(golden('batch-refined-sigmas-webxr.bin'));
  assert.equal(b.count, 2);
  assert.equal(b.sigmas.length, 6);
  assert.deepEqual(Array.from(b.sigmas), [0.0010000000474974513, 0.0020000000949949026, 0.0078125, 0.0005000000237487257, 0.0005000000237487257, 0.00390625]);
  assert.equal(decodeBatch(golden('batch-causal-unity.bin')).sigmas, null);
});

test('field messages are read by their column names', () => {
  const message = JSON.parse(readFileSync(new URL('../../protocol/golden/server-field.json', import.meta.url), 'utf8'));
  const cells = fieldCells(message);
  assert.equal(cells.length, 2);
  assert.deepEqual(cells[0], { x: 0.025, y: -0.125, z: -0.47500000000000003, n: 42, u: 0.25, v: 0.03125, w: -0.125 });
  // Columns added later, or reordered, do not move what the page reads.
  const reordered = { ...message, columns: ['n', ...message.columns.filter((c) => c !== 'n')], cells: message.cells.map((r) => [r[3], ...r.filter((_, i) => i !== 3)]) };
  assert.deepEqual(fieldCells(reordered)[1], fieldCells(message)[1]);
  assert.deepEqual(fieldCells({ columns: ['x'], cells: [[1]] }), []);
});
