// Speed colours: the same ramp and scale rule as mrptv's Rerun log (src/rerun_log.rs), so a
// colour means the same speed in both viewers.

const STOPS = [
  [68, 1, 84],
  [59, 82, 139],
  [33, 145, 140],
  [94, 201, 98],
  [253, 231, 37],
];

/** Writes the colour of `speed` on a 0..`max` scale (saturating) into out[0..3], 0..1 sRGB. */
export function speedColor(speed, max, out = [0, 0, 0]) {
  const x = (max > 0 ? Math.min(Math.max(speed / max, 0), 1) : 0) * 4;
  const i = Math.min(Math.floor(x), 3);
  const f = x - i;
  for (let k = 0; k < 3; k++) out[k] = (STOPS[i][k] * (1 - f) + STOPS[i + 1][k] * f) / 255;
  return out;
}

/** A "nice" upper bound (1, 2 or 5 x 10^k) at or above x. */
export function niceCeiling(x) {
  if (!(x > 0 && Number.isFinite(x))) return 1;
  const decade = 10 ** Math.floor(Math.log10(x));
  for (const m of [1, 2, 5, 10]) if (m * decade >= x * (1 - 1e-12)) return m * decade;
  return 10 * decade;
}

/** CSS gradient of the ramp, left = 0. */
export function rampCss() {
  const stops = STOPS.map((c, i) => `rgb(${c.join(',')}) ${(i * 25).toFixed(0)}%`);
  return `linear-gradient(to right, ${stops.join(', ')})`;
}
