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
    /// The image's rows.
    rows: usize,
    /// Per column, the smallest and largest blurred value over the current tile row's rows
    /// so far.
    column_min: Vec<u16>,
    column_max: Vec<u16>,
}

impl Tiles {
    /// Empty ranges for an image of `w` x `h` pixels.
    pub(super) fn reset(&mut self, w: usize, h: usize) {
        (self.tiles_x, self.tiles_y) = (w.div_ceil(TILE), h.div_ceil(TILE));
        self.rows = h;
        let n = self.tiles_x * self.tiles_y;
        self.min.clear();
        self.min.resize(n, u16::MAX);
        self.max.clear();
        self.max.resize(n, 0);
    }

    /// Takes the blurred row `y` into its tiles' ranges: each column's range over the tile
    /// row's rows so far (a plain element-wise pass, vectorised), folded into the tiles once
    /// the tile row is complete (its last row or the image's).
    pub(super) fn record_row(&mut self, y: usize, row: &[u16]) {
        if y.is_multiple_of(TILE) {
            self.column_min.clear();
            self.column_min.extend_from_slice(row);
            self.column_max.clear();
            self.column_max.extend_from_slice(row);
        } else {
            for ((lo, hi), &v) in self
                .column_min
                .iter_mut()
                .zip(&mut self.column_max)
                .zip(row)
            {
                *lo = (*lo).min(v);
                *hi = (*hi).max(v);
            }
        }
        if y % TILE == TILE - 1 || y + 1 == self.rows {
            self.fold_tile_row(y / TILE);
        }
    }

    /// The tiles of tile row `ty` take their columns' ranges.
    fn fold_tile_row(&mut self, ty: usize) {
        let tiles = ty * self.tiles_x..(ty + 1) * self.tiles_x;
        let (mins, maxs) = (&mut self.min[tiles.clone()], &mut self.max[tiles]);
        let columns = self
            .column_min
            .chunks(TILE)
            .zip(self.column_max.chunks(TILE));
        for ((lo, hi), (cmin, cmax)) in mins.iter_mut().zip(maxs.iter_mut()).zip(columns) {
            *lo = cmin.iter().fold(*lo, |a, &v| a.min(v));
            *hi = cmax.iter().fold(*hi, |a, &v| a.max(v));
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

/// Running column sums of the blurred image and the box sums along a row, reused from image
/// to image.
#[derive(Debug, Default)]
pub(super) struct Threshold {
    column_sums: Vec<i32>,
    prefix: Vec<i32>,
}

impl Threshold {
    /// Eq. 1 against the box mean (replicated borders), into `mask` (1 foreground, 0 not). Tiles
    /// are screened first ([`Tiles::screen`]); only surviving tiles get exact box sums, from
    /// running column sums (vertical) and a prefix sum along the row (horizontal): over each
    /// surviving tile, or over the whole row where its tiles' overlapping margins would sum
    /// more columns than the row has.
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
        // With the box capped at 101 and |C| at 255 every box sum and product below stays
        // inside i32.
        let test = BoxTest {
            half,
            area: area as i32,
            offset: offset as i32,
        };
        self.start_column_sums(blurred, (w, h), half);
        self.prefix.resize(w + 2 * half + 1, 0);
        for y in 0..h {
            if y > 0 {
                self.advance_column_sums(blurred, (w, h), half, y);
            }
            let (blurred, mask) = (&blurred[y * w..(y + 1) * w], &mut mask[y * w..(y + 1) * w]);
            let row_tiles = (y / TILE) * tiles.tiles_x..(y / TILE + 1) * tiles.tiles_x;
            let candidates = &tiles.candidate[row_tiles];
            let surviving = candidates.iter().filter(|&&c| c).count();
            if surviving * (TILE + 2 * half) >= w + 2 * half {
                test.span(&self.column_sums, &mut self.prefix, blurred, mask, 0..w);
                continue;
            }
            for (tx, _) in candidates.iter().enumerate().filter(|(_, &c)| c) {
                let span = tx * TILE..((tx + 1) * TILE).min(w);
                test.span(&self.column_sums, &mut self.prefix, blurred, mask, span);
            }
        }
    }

    /// Column sums over rows -half..=half (replicated) for row 0, padded by `half` replicated
    /// columns each side so a span's box needs no clamping.
    fn start_column_sums(&mut self, blurred: &[u16], (w, h): (usize, usize), half: usize) {
        self.column_sums.clear();
        self.column_sums.resize(w + 2 * half, 0);
        for k in -(half as isize)..=half as isize {
            let r = clamped_row(k, h) * w;
            for (s, &b) in self.column_sums[half..half + w]
                .iter_mut()
                .zip(&blurred[r..r + w])
            {
                *s += b as i32;
            }
        }
        self.pad_column_sums(w, half);
    }

    /// Moves the column sums from row `y - 1`'s box to row `y`'s.
    fn advance_column_sums(
        &mut self,
        blurred: &[u16],
        (w, h): (usize, usize),
        half: usize,
        y: usize,
    ) {
        let add = clamped_row((y + half) as isize, h) * w;
        let sub = clamped_row(y as isize - half as isize - 1, h) * w;
        for ((s, &a), &b) in self.column_sums[half..half + w]
            .iter_mut()
            .zip(&blurred[add..add + w])
            .zip(&blurred[sub..sub + w])
        {
            *s += a as i32 - b as i32;
        }
        self.pad_column_sums(w, half);
    }

    /// Replicates the first and last column sums into the `half` padding columns each side.
    fn pad_column_sums(&mut self, w: usize, half: usize) {
        let (first, last) = (self.column_sums[half], self.column_sums[half + w - 1]);
        self.column_sums[..half].fill(first);
        self.column_sums[half + w..].fill(last);
    }
}

/// Row `y` clamped to an image of `h` rows (borders replicated).
fn clamped_row(y: isize, h: usize) -> usize {
    y.clamp(0, h as isize - 1) as usize
}

/// Eq. 1 on integers: a pixel passes where `blurred * area + offset >= box sum`.
struct BoxTest {
    half: usize,
    area: i32,
    offset: i32,
}

impl BoxTest {
    /// Tests the pixels `span` of a row (`blurred`, `mask`) against their box sums, from the
    /// row's padded `column_sums` (padded column x is image column x - half) through `prefix`.
    fn span(
        &self,
        column_sums: &[i32],
        prefix: &mut [i32],
        blurred: &[u16],
        mask: &mut [u8],
        span: std::ops::Range<usize>,
    ) {
        let (x0, x1) = (span.start, span.end);
        let side = 2 * self.half + 1;
        // A whole row's running sum may pass i32::MAX (a wide image, a large box); it wraps,
        // and each box sum, a difference of two of them, is still exact.
        let mut running = 0i32;
        prefix[0] = 0;
        for (p, &c) in prefix[1..=x1 - x0 + 2 * self.half]
            .iter_mut()
            .zip(&column_sums[x0..x1 + 2 * self.half])
        {
            running = running.wrapping_add(c);
            *p = running;
        }
        let (area, offset) = (self.area, self.offset);
        for (((m, &b), &hi), &lo) in mask[x0..x1]
            .iter_mut()
            .zip(&blurred[x0..x1])
            .zip(&prefix[side..])
            .zip(&prefix[..x1 - x0])
        {
            *m = (b as i32 * area + offset >= hi.wrapping_sub(lo)) as u8;
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
    let histogram = difference_histogram(image);
    let n: usize = histogram.iter().sum();
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

/// Counts of the absolute differences of horizontally adjacent pixels on every fourth row.
/// Four histograms take the pairs in turn: a smooth background's differences fall in a few
/// bins, and with one histogram each count would wait for the one before it.
fn difference_histogram(image: ImageView<'_>) -> [usize; 256] {
    let mut histograms = [[0u32; 256]; 4];
    for row in image.pixels.chunks_exact(image.width).step_by(4) {
        let (left, right) = (&row[..row.len() - 1], &row[1..]);
        let (mut lefts, mut rights) = (left.chunks_exact(4), right.chunks_exact(4));
        for (a, b) in lefts.by_ref().zip(rights.by_ref()) {
            for (k, histogram) in histograms.iter_mut().enumerate() {
                histogram[a[k].abs_diff(b[k]) as usize] += 1;
            }
        }
        for (a, b) in lefts.remainder().iter().zip(rights.remainder()) {
            histograms[0][a.abs_diff(*b) as usize] += 1;
        }
    }
    std::array::from_fn(|v| histograms.iter().map(|h| h[v] as usize).sum())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Eq. 1 pixel by pixel: the blurred value against its box's mean minus C, borders
    /// replicated, on the same integer scale.
    fn naive(blurred: &[u16], (w, h): (usize, usize), box_size_px: usize, c: f64) -> Vec<u8> {
        let half = (box_size_px / 2) as isize;
        let area = ((2 * half + 1) * (2 * half + 1)) as i64;
        let offset = (c * area as f64 * 256.0).round() as i64;
        let at = |x: isize, y: isize| {
            let (x, y) = (x.clamp(0, w as isize - 1), y.clamp(0, h as isize - 1));
            blurred[y as usize * w + x as usize] as i64
        };
        (0..h as isize)
            .flat_map(|y| (0..w as isize).map(move |x| (x, y)))
            .map(|(x, y)| {
                let sum: i64 = (-half..=half)
                    .flat_map(|dy| (-half..=half).map(move |dx| (dx, dy)))
                    .map(|(dx, dy)| at(x + dx, y + dy))
                    .sum();
                u8::from(at(x, y) * area + offset >= sum)
            })
            .collect()
    }

    #[test]
    fn the_difference_histogram_counts_every_fourth_rows_pairs() {
        // Rows of 2 to 11 pixels: pairs in fours and left over.
        for w in 2..12 {
            let pixels: Vec<u8> = (0..w * 9).map(|i| ((i * 37) % 251) as u8).collect();
            let image = ImageView::new(w, 9, &pixels).expect("sized");
            let mut expected = [0usize; 256];
            for row in pixels.chunks_exact(w).step_by(4) {
                for pair in row.windows(2) {
                    expected[pair[0].abs_diff(pair[1]) as usize] += 1;
                }
            }
            assert_eq!(difference_histogram(image), expected, "width {w}");
        }
    }

    #[test]
    fn each_tile_records_the_range_of_its_pixels() {
        // Edge tiles cut short on both axes.
        let (w, h) = (37, 35);
        let image: Vec<u16> = (0..w * h).map(|i| ((i * 7919) % 1013) as u16).collect();
        let mut tiles = Tiles::default();
        tiles.reset(w, h);
        for y in 0..h {
            tiles.record_row(y, &image[y * w..(y + 1) * w]);
        }
        for (t, (&lo, &hi)) in tiles.min.iter().zip(&tiles.max).enumerate() {
            let (tx, ty) = (t % tiles.tiles_x, t / tiles.tiles_x);
            let pixels = (ty * TILE..((ty + 1) * TILE).min(h))
                .flat_map(|y| (tx * TILE..((tx + 1) * TILE).min(w)).map(move |x| y * w + x));
            let values: Vec<u16> = pixels.map(|i| image[i]).collect();
            assert_eq!(
                lo,
                values.iter().copied().fold(u16::MAX, u16::min),
                "tile {t}"
            );
            assert_eq!(hi, values.iter().copied().fold(0, u16::max), "tile {t}");
        }
        assert_eq!(tiles.min.len(), 9);
    }

    #[test]
    fn the_screened_threshold_is_eq_1_at_every_pixel() {
        // Dim noise with bright spots: tile rows with one spot (a few surviving tiles, summed
        // tile by tile) and with spots everywhere (summed along the whole row), boxes from small
        // to wider than a tile, and a C that every tile survives.
        let (w, h) = (83, 61);
        let mut state = 11u64;
        let blurred: Vec<u16> = (0..w * h)
            .map(|i| {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                let noise = (state >> 62) as u16 * 256;
                let (x, y) = (i % w, i / w);
                let spot = ((30..34).contains(&x) && (5..9).contains(&y)) || (y > 40 && x % 5 == 0);
                noise + if spot { 60 * 256 } else { 0 }
            })
            .collect();
        for (box_size_px, c) in [(3, -6.0), (15, -6.0), (15, 2.0), (41, -3.0)] {
            let mut tiles = Tiles::default();
            tiles.reset(w, h);
            for y in 0..h {
                tiles.record_row(y, &blurred[y * w..(y + 1) * w]);
            }
            let mut mask = Vec::new();
            Threshold::default().run(&blurred, (w, h), &mut tiles, box_size_px, c, &mut mask);
            assert_eq!(
                mask,
                naive(&blurred, (w, h), box_size_px, c),
                "box {box_size_px}, C {c}"
            );
            assert!(mask.contains(&1) && mask.contains(&0));
        }
    }
}
