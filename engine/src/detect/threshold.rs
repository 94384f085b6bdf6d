//! The method's adaptive threshold (eq. 1): a pixel is foreground where the blurred image is at
//! least the mean of the box around it minus the contrast constant C (borders replicated), with
//! C made stricter where the image's noise would pass it.

use super::DetectConfig;
use crate::ImageView;

/// Side of the tiles screened before the exact threshold test, pixels.
const TILE: usize = 16;

/// Each tile's range of blurred values, recorded by the blur: most of an image is background
/// that provably fails the test, and a tile's range says which tiles need the exact test.
#[derive(Debug, Default)]
pub(super) struct Tiles {
    tiles_x: usize,
    tiles_y: usize,
    min: Vec<u16>,
    max: Vec<u16>,
    /// Tiles that may hold foreground pixels.
    candidate: Vec<bool>,
}

impl Tiles {
    /// Empty ranges for an image of `w` x `h` pixels.
    pub(super) fn reset(&mut self, w: usize, h: usize) {
        (self.tiles_x, self.tiles_y) = (w.div_ceil(TILE), h.div_ceil(TILE));
        let n = self.tiles_x * self.tiles_y;
        self.min.clear();
        self.min.resize(n, u16::MAX);
        self.max.clear();
        self.max.resize(n, 0);
    }

    /// Takes the blurred row `y` into its tiles' ranges.
    pub(super) fn record_row(&mut self, y: usize, row: &[u16]) {
        let tiles = (y / TILE) * self.tiles_x..(y / TILE + 1) * self.tiles_x;
        let (mins, maxs) = (&mut self.min[tiles.clone()], &mut self.max[tiles]);
        for ((lo, hi), chunk) in mins.iter_mut().zip(maxs.iter_mut()).zip(row.chunks(TILE)) {
            let (cmin, cmax) = chunk
                .iter()
                .fold((u16::MAX, 0u16), |(a, b), &v| (a.min(v), b.max(v)));
            *lo = (*lo).min(cmin);
            *hi = (*hi).max(cmax);
        }
    }

    /// Marks the tiles that may hold a foreground pixel: the box mean is at least the smallest
    /// blurred value around the pixel, so a pixel below `that minimum - C` cannot pass. `half`
    /// is the box's half side, `c_scaled` the contrast constant times 256.
    fn screen(&mut self, half: usize, c_scaled: i64) {
        let (tiles_x, tiles_y) = (self.tiles_x, self.tiles_y);
        // The box around any pixel of a tile lies within `reach` tiles of it.
        let reach = half.div_ceil(TILE).max(1);
        self.candidate.clear();
        self.candidate.resize(tiles_x * tiles_y, false);
        for ty in 0..tiles_y {
            for tx in 0..tiles_x {
                let mut floor = u16::MAX;
                for ny in ty.saturating_sub(reach)..=(ty + reach).min(tiles_y - 1) {
                    for nx in tx.saturating_sub(reach)..=(tx + reach).min(tiles_x - 1) {
                        floor = floor.min(self.min[ny * tiles_x + nx]);
                    }
                }
                self.candidate[ty * tiles_x + tx] =
                    self.max[ty * tiles_x + tx] as i64 + c_scaled >= floor as i64;
            }
        }
    }
}

/// Running column sums of the blurred image, reused from image to image.
#[derive(Debug, Default)]
pub(super) struct Threshold {
    column_sums: Vec<i32>,
}

impl Threshold {
    /// Eq. 1 against the box mean (replicated borders), into `mask` (1 foreground, 0 not). Tiles
    /// are screened first ([`Tiles::screen`]); only surviving tiles get exact box sums, from
    /// running column sums (vertical) and a prefix sum along each tile row (horizontal).
    #[allow(clippy::too_many_arguments)]
    pub(super) fn run(
        &mut self,
        blurred: &[u16],
        (w, h): (usize, usize),
        tiles: &mut Tiles,
        box_size_px: usize,
        contrast_c: f64,
        mask: &mut Vec<u8>,
    ) {
        let half = box_size_px.max(1) / 2;
        let area = ((2 * half + 1) * (2 * half + 1)) as i64;
        // blurred >= sum/area - C  <=>  blurred * area + C * area * 256 >= sum (all scaled by 256)
        let offset = (contrast_c * area as f64 * 256.0).round() as i64;
        let c_scaled = (contrast_c * 256.0).round() as i64;
        mask.clear();
        mask.resize(w * h, 0);
        tiles.screen(half, c_scaled);
        let row = |y: isize| y.clamp(0, h as isize - 1) as usize * w;
        // Column sums over rows y-half..=y+half (replicated) for the current row y, padded by
        // `half` replicated columns each side so a tile's window needs no clamping. With the box
        // capped at 101 and |C| at 255 every sum and product below stays inside i32.
        let (area, offset) = (area as i32, offset as i32);
        self.column_sums.clear();
        self.column_sums.resize(w + 2 * half, 0);
        for k in -(half as isize)..=half as isize {
            let r = row(k);
            for (s, &b) in self.column_sums[half..half + w]
                .iter_mut()
                .zip(&blurred[r..r + w])
            {
                *s += b as i32;
            }
        }
        let side = 2 * half + 1;
        let mut prefix: Vec<i32> = vec![0; TILE + 2 * half + 1];
        let mut sums: Vec<i32> = vec![0; TILE];
        for y in 0..h {
            if y > 0 {
                let (add, sub) = (
                    row((y + half) as isize),
                    row(y as isize - half as isize - 1),
                );
                for ((s, &a), &b) in self.column_sums[half..half + w]
                    .iter_mut()
                    .zip(&blurred[add..add + w])
                    .zip(&blurred[sub..sub + w])
                {
                    *s += a as i32 - b as i32;
                }
            }
            let (first, last) = (self.column_sums[half], self.column_sums[half + w - 1]);
            self.column_sums[..half].fill(first);
            self.column_sums[half + w..].fill(last);
            let ty = y / TILE;
            for tx in 0..tiles.tiles_x {
                if !tiles.candidate[ty * tiles.tiles_x + tx] {
                    continue;
                }
                let (x0, x1) = (tx * TILE, ((tx + 1) * TILE).min(w));
                let n = x1 - x0;
                // Padded column x0 is image column x0 - half.
                let mut running = 0;
                for (p, &c) in prefix[1..]
                    .iter_mut()
                    .zip(&self.column_sums[x0..x1 + 2 * half])
                {
                    running += c;
                    *p = running;
                }
                for (i, s) in sums[..n].iter_mut().enumerate() {
                    *s = prefix[i + side] - prefix[i];
                }
                let blurred = &blurred[y * w + x0..y * w + x1];
                let mask = &mut mask[y * w + x0..y * w + x1];
                for ((m, &b), &sum) in mask.iter_mut().zip(blurred).zip(&sums[..n]) {
                    *m = (b as i32 * area + offset >= sum) as u8;
                }
            }
        }
    }
}

/// `contrast_c`, lowered (made stricter) where the image's noise would pass it: the noise is
/// estimated from the differences of horizontally adjacent pixels on every fourth row (their
/// median absolute value, robust to the few pixels on particles), and the 5x5 binomial blur
/// keeps 0.273 of it.
pub(super) fn effective_contrast(config: &DetectConfig, image: ImageView<'_>) -> f64 {
    if config.noise_sigmas <= 0.0 || image.width < 2 {
        return config.contrast_c;
    }
    let mut histogram = [0usize; 256];
    let mut n = 0usize;
    for row in image.pixels.chunks_exact(image.width).step_by(4) {
        for pair in row.windows(2) {
            histogram[pair[0].abs_diff(pair[1]) as usize] += 1;
            n += 1;
        }
    }
    let mut seen = 0;
    let median = histogram
        .iter()
        .position(|&count| {
            seen += count;
            2 * seen > n
        })
        .unwrap_or(0) as f64;
    // A difference of two pixels has sqrt(2) times their noise; MAD to sigma is 1.4826.
    let sigma = 1.4826 * median / std::f64::consts::SQRT_2;
    const BLUR_NOISE_GAIN: f64 = 0.273;
    config
        .contrast_c
        .min(-config.noise_sigmas * BLUR_NOISE_GAIN * sigma)
}
