// Where the measured volume goes in the observer's space (docs/live-service.md: "Where the flow appears").
// A point p of the session's world (WebXR convention: x right, y up, -z forward, metres) is drawn
// at  anchor + scale * (p - centre):  no rotation, so "up" and "forward" stay the wearer's.
// centre and the robust extent come from the first batches and then stay fixed (press Recentre
// to measure again), so the picture does not breathe as particles come and go.

const SAMPLE_CAP = 4096;

function percentile(sorted, q) {
  if (sorted.length === 0) return 0;
  const at = Math.min(sorted.length - 1, Math.max(0, Math.round(q * (sorted.length - 1))));
  return sorted[at];
}

export class Placement {
  /**
   * @param {object} o
   * @param {number[]} o.anchor where the volume's centre goes, metres in the XR reference space
   * @param {number} o.fitSize the volume's largest extent is scaled to this many metres
   * @param {boolean} o.trueScale draw at 1:1 instead
   * @param {number} o.settleBatches non-empty batches observed before the mapping is fixed
   */
  constructor({ anchor = [0, 1.3, -1.2], fitSize = 0.6, trueScale = false, settleBatches = 15 } = {}) {
    this.anchor = anchor;
    this.fitSize = fitSize;
    this.trueScale = trueScale;
    this.settleBatches = settleBatches;
    this.reset();
  }

  reset() {
    this.samples = [[], [], []];
    this.speeds = [];
    this.batchesSeen = 0;
    this.fixed = false;
    this.centre = [0, 0, 0];
    this.lo = [0, 0, 0];
    this.hi = [0, 0, 0];
    this.extent = 1;
    this.medianSpeed = 0;
  }

  /** Feeds one batch's positions (stride 10 floats, position at +2, velocity at +5). */
  observe(floats, count) {
    if (this.fixed || count === 0) return;
    const step = Math.max(1, Math.ceil(count / 256));
    for (let i = 0; i < count; i += step) {
      const o = i * 10;
      if (this.samples[0].length >= SAMPLE_CAP) break;
      for (let k = 0; k < 3; k++) this.samples[k].push(floats[o + 2 + k]);
      this.speeds.push(Math.hypot(floats[o + 5], floats[o + 6], floats[o + 7]));
    }
    this.batchesSeen++;
    this.#estimate();
    if (this.batchesSeen >= this.settleBatches) this.fixed = true;
  }

  #estimate() {
    let extent = 0;
    for (let k = 0; k < 3; k++) {
      const s = Float64Array.from(this.samples[k]).sort();
      const lo = percentile(s, 0.02);
      const hi = percentile(s, 0.98);
      this.centre[k] = (lo + hi) / 2;
      this.lo[k] = lo;
      this.hi[k] = hi;
      extent = Math.max(extent, hi - lo);
    }
    // One particle or a flat sheet still needs a finite scale.
    this.extent = Math.max(extent, 0.05);
    const sp = Float64Array.from(this.speeds).sort();
    this.medianSpeed = percentile(sp, 0.5);
  }

  get scale() {
    return this.trueScale ? 1 : this.fitSize / this.extent;
  }

  /** p (session world) -> XR reference space. */
  map(p) {
    const s = this.scale;
    return p.map((v, k) => this.anchor[k] + s * (v - this.centre[k]));
  }
}
