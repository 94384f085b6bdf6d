//! Stage 1: particle detection in one grayscale image (method section 3.1).
//!
//! 5x5 Gaussian blur (OpenCV's fixed binomial kernel for `ksize = 5, sigma = 0`), adaptive
//! threshold against the mean of a 15x15 box minus a contrast constant C (Sauvola-style local
//! binarisation), then 8-connected regions of the binary image. The regions are exactly the areas
//! enclosed by the outer borders that Suzuki & Abe (1985) border following returns, so labelling
//! them directly gives the same particles without tracing contours. Per region: intensity-weighted
//! moment centroid (eqs. 2-3), brightness at the centroid, equivalent diameter.
//!
//! Beyond the method: regions holding several particles can be split between their intensity
//! peaks or cut (again, until each part is round) ([`DetectConfig::split_touching`]), and the
//! parts refined by fitting them together as spots ([`DetectConfig::fit_overlaps`]); a region
//! holding more particles than its shape shows is fitted again where the tracks expect them
//! ([`Detector::separate_expected`]); a causal per-camera background model takes what stands
//! still out of the blurred image before the threshold
//! ([`DetectConfig::background_rise_per_frame`]).

use serde::{Deserialize, Serialize};

pub mod spots;

use spots::{fit_spots, Spot, SpotFit};
use crate::ImageView;
use crate::geometry::PixelPoint;

/// How each pixel of a region weighs in its centroid.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CentroidWeight {
    /// The raw pixel intensity, as the method's moments (eq. 2).
    Intensity,
    /// Intensity above the local 15x15 mean: removes the pull of a sloping background.
    AboveLocalMean,
}

/// Detection parameters. Defaults follow the method unless noted.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DetectConfig {
    /// Side of the box whose mean is the local threshold base, odd, pixels (method: 15; at most
    /// 101).
    pub box_size_px: usize,
    /// Contrast constant C, grey levels (-255..=255): a pixel is a particle if `blurred >= box_mean - C`
    /// (method eq. 1). Bright particles on a darker background need C < 0; the method leaves the
    /// value to the user, -6 keeps sensor noise of a few grey levels out.
    pub contrast_c: f64,
    /// Raise the threshold in noisy images: a pixel must exceed its local mean by at least this
    /// many standard deviations of the blurred image's noise, measured in each image (robustly,
    /// from neighbouring pixels' differences), when that is more than -C. 0: C alone (the
    /// method).
    pub noise_sigmas: f64,
    /// Causal background model, per camera: each pixel's background follows its darkest recent
    /// value in the blurred image (where sensor noise is a quarter of the raw image's) and,
    /// where the pixel has stayed brighter for 10 frames, rises by at most this many grey levels
    /// per frame; it is subtracted before thresholding, and from the intensities that weigh
    /// centroids. What stays still in the image (posters, lamps, LEDs, hot pixels, vignetting)
    /// fades out within 10 + contrast / rate frames; a particle that crosses a pixel within 10
    /// frames leaves the model untouched. It starts at zero, so the first frames are detected as
    /// they are. 0: off (the method).
    pub background_rise_per_frame: f64,
    /// Regions smaller than this many pixels are noise, not particles.
    pub min_area_px: usize,
    /// Regions larger than this are reflections or background structure, not particles.
    pub max_area_px: usize,
    pub centroid_weight: CentroidWeight,
    /// Drop regions touching the image border: part of the particle is outside the image, so
    /// its centroid, diameter and brightness are all biased.
    pub reject_border: bool,
    /// Drop regions (of 12 pixels or more) whose long axis exceeds this multiple of their short
    /// axis: a single particle images as a disc, an elongated region is two or more particles
    /// overlapping, whose merged centroid lies on neither. 0 keeps every region (the method).
    pub max_axis_ratio: f64,
    /// Split elongated regions (touching or overlapping particles, see `max_axis_ratio`) into
    /// round parts instead of dropping them. The parts keep tracks alive through an overlap but
    /// are flagged, and left out of velocity fits.
    pub split_touching: bool,
    /// A dip between two peaks must fall below `(1 - split_dip_fraction)` of the lower peak's
    /// height above the region's edge for the peaks to count as separate particles.
    pub split_dip_fraction: f64,
    /// Refine the parts of a split region by fitting them together as spots (Gaussian to
    /// flat-topped) to the blurred image, so a particle's image may run under its neighbour's
    /// instead of being cut at the boundary between them. Where the fit is trustworthy the
    /// parts take its centres, and overlapping ones are then measured too (see
    /// [`Separation::Fitted`]); false: parts keep the cut's centroids and overlapping ones are
    /// only tracked.
    pub fit_overlaps: bool,
    /// Fit a region again where the tracks expect more particles in it than its shape gave
    /// ([`Detector::separate_expected`]): particles merged into one round blob keep their
    /// tracks.
    pub separate_expected: bool,
}

impl Default for DetectConfig {
    fn default() -> Self {
        Self {
            box_size_px: 15,
            contrast_c: -6.0,
            noise_sigmas: 5.0,
            background_rise_per_frame: 2.0,
            min_area_px: 3,
            max_area_px: 5000,
            centroid_weight: CentroidWeight::Intensity,
            reject_border: true,
            max_axis_ratio: 1.5,
            split_touching: true,
            split_dip_fraction: 0.25,
            fit_overlaps: true,
            separate_expected: true,
        }
    }
}

/// `contrast_c`, lowered (made stricter) where the image's noise would pass it: the noise is
/// estimated from the differences of horizontally adjacent pixels on every fourth row (their
/// median absolute value, robust to the few pixels on particles), and the 5x5 binomial blur
/// keeps 0.273 of it.
fn effective_contrast(config: &DetectConfig, image: ImageView<'_>) -> f64 {
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

/// One detected particle image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Detection {
    pub centroid: PixelPoint,
    /// Equivalent diameter: the circle with the region's area, pixels.
    pub diameter_px: f64,
    /// Intensity at the centroid (bilinear) above the background model, grey levels.
    pub brightness: f64,
    pub area_px: u32,
    /// How it was told apart from its neighbours, which decides what its centroid is good for.
    pub separation: Separation,
}

/// How a particle image was told apart from its neighbours. Ordered from the most to the least
/// exact centroid.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Separation {
    /// On its own, or parted from a touching neighbour at a dip between their peaks.
    Clear,
    /// Overlapping a neighbour, separated by fitting both as spots, and the fit is trustworthy
    /// ([`SpotFit::is_trustworthy`]), or, for a spot seeded where a track expected it, its
    /// centre is pinned down by the pixels ([`SpotFit::is_measured`]): centroids within about
    /// 0.1 px. Measured where a track's clear samples do not support a velocity fit on their
    /// own.
    Fitted,
    /// Overlapping, cut in two by 2-means, and no trustworthy spot fit: its centroid may be
    /// pulled towards its neighbour, so good for tracking and not for measuring.
    Cut,
}

/// A pixel of a region with its coordinates, so nothing downstream divides by the width.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Pixel {
    index: u32,
    x: u32,
    y: u32,
}

/// Reusable buffers, so the hot path allocates nothing once warmed up.
#[derive(Debug, Default)]
pub struct Detector {
    /// Ring of five horizontally blurred rows.
    row_pass: Vec<u16>,
    /// Blurred image scaled by 256 (the binomial kernel's sum), kept unrounded.
    blurred: Vec<u16>,
    column_sums: Vec<i32>,
    /// Tiles that may hold foreground pixels.
    candidate: Vec<bool>,
    tile_min: Vec<u16>,
    tile_max: Vec<u16>,
    /// 0 background, 1 foreground not yet labelled, 2 labelled.
    mask: Vec<u8>,
    /// Region label per labelled pixel; labels keep increasing across calls, so the buffer never
    /// needs clearing (a pixel's stale label from an earlier image never equals a current one).
    labels: Vec<u32>,
    next_label: u32,
    stack: Vec<Pixel>,
    region: Vec<Pixel>,
    /// The contrast constant in use for the current image.
    contrast_c: f64,
    /// Per pixel: the background model, in the blurred image's units (grey levels x 256); empty
    /// when the model is off.
    background: Vec<u16>,
    /// The model once the current image is in it.
    next_background: Vec<u16>,
    /// Per pixel: frames in a row it has been brighter than its model.
    bright_frames: Vec<u8>,
    /// The current image's measured regions, in label order, with the detections each gave.
    resolved: Vec<ResolvedRegion>,
}

/// A region that was measured, and the run of the output its detections fill.
#[derive(Debug, Clone, Copy)]
struct ResolvedRegion {
    label: u32,
    first: usize,
    count: usize,
    area_px: usize,
}

/// Frames a pixel must stay brighter than its background model before the model rises there.
const BACKGROUND_DELAY_FRAMES: u8 = 10;

impl Detector {
    pub fn new() -> Self {
        Self::default()
    }

    /// Detects particles; appends to `out` (cleared first) in raster order of their first pixel.
    pub fn detect(
        &mut self,
        image: ImageView<'_>,
        config: &DetectConfig,
        out: &mut Vec<Detection>,
    ) {
        out.clear();
        let (w, h) = (image.width, image.height);
        if w == 0 || h == 0 {
            return;
        }
        let rise = if config.background_rise_per_frame > 0.0 {
            if self.background.len() != w * h {
                self.background.clear();
                self.background.resize(w * h, 0);
                self.next_background.resize(w * h, 0);
                self.bright_frames.clear();
                self.bright_frames.resize(w * h, 0);
            }
            // In the blurred image's units (x 256); at least one unit so the model can rise.
            (config.background_rise_per_frame * 256.0)
                .round()
                .clamp(1.0, 65535.0) as u16
        } else {
            self.background.clear();
            0
        };
        self.blur(image, rise);
        self.contrast_c = effective_contrast(config, image);
        self.threshold(w, h, config);
        self.label(image, config, out);
        if rise > 0 {
            std::mem::swap(&mut self.background, &mut self.next_background);
        }
    }

    /// The contrast constant the last image was thresholded with: `contrast_c`, or lower where
    /// the image's noise called for it (`noise_sigmas`).
    pub fn last_contrast_c(&self) -> f64 {
        self.contrast_c
    }

    /// The 5x5 binomial blur, separable, through a ring of five row-pass rows so the
    /// intermediate image never leaves the cache; subtracts the background model (updating it
    /// with the blurred row first) when `rise` is not 0, and records each tile's range on the way.
    fn blur(&mut self, image: ImageView<'_>, rise: u16) {
        let (w, h) = (image.width, image.height);
        let px = image.pixels;
        self.row_pass.resize(5 * w, 0);
        self.blurred.resize(w * h, 0);
        let (tiles_x, tiles_y) = (w.div_ceil(TILE), h.div_ceil(TILE));
        self.tile_min.clear();
        self.tile_min.resize(tiles_x * tiles_y, u16::MAX);
        self.tile_max.clear();
        self.tile_max.resize(tiles_x * tiles_y, 0);
        let clamp_x = |x: isize| x.clamp(0, w as isize - 1) as usize;
        let row_pass = |src: &[u8], dst: &mut [u16]| {
            // Shifted slices instead of indexing, so the compiler drops bounds checks and vectorises.
            if w >= 5 {
                let n = w - 4;
                let taps = [
                    &src[0..n],
                    &src[1..n + 1],
                    &src[2..n + 2],
                    &src[3..n + 3],
                    &src[4..n + 4],
                ];
                for (((d, (a, b)), (c, e)), f) in dst[2..w - 2]
                    .iter_mut()
                    .zip(taps[0].iter().zip(taps[1]))
                    .zip(taps[2].iter().zip(taps[3]))
                    .zip(taps[4])
                {
                    *d = *a as u16 + 4 * *b as u16 + 6 * *c as u16 + 4 * *e as u16 + *f as u16;
                }
            }
            for x in (0..w.min(2)).chain(w.saturating_sub(2).max(w.min(2))..w) {
                dst[x] = kernel(|k| src[clamp_x(x as isize + k)] as u16);
            }
        };
        let ring_row = |y: usize| (y % 5) * w;
        let mut computed = 0;
        for y in 0..h {
            // Rows y-2..=y+2 (clamped) must be in the ring; they are the last five computed.
            while computed <= (y + 2).min(h - 1) {
                let r = ring_row(computed);
                row_pass(
                    &px[computed * w..(computed + 1) * w],
                    &mut self.row_pass[r..r + w],
                );
                computed += 1;
            }
            let tmp = &self.row_pass;
            let rows = [
                y as isize - 2,
                y as isize - 1,
                y as isize,
                y as isize + 1,
                y as isize + 2,
            ]
            .map(|r| ring_row(r.clamp(0, h as isize - 1) as usize))
            .map(|r| &tmp[r..r + w]);
            let dst = &mut self.blurred[y * w..(y + 1) * w];
            for ((((d, a), b), c), (e, f)) in dst
                .iter_mut()
                .zip(rows[0])
                .zip(rows[1])
                .zip(rows[2])
                .zip(rows[3].iter().zip(rows[4]))
            {
                *d = a + 4 * b + 6 * c + 4 * e + f;
            }
            if rise > 0 {
                // The image is compared with the model as it stood before this frame, so a
                // particle arriving at a pixel keeps its whole contrast; the updated model takes
                // its place once the image is measured. A pixel brighter than its model raises
                // it only after BACKGROUND_DELAY_FRAMES frames in a row, so a particle passing
                // over it leaves the model (and its own centroid) untouched.
                let row = y * w..(y + 1) * w;
                for (((d, &b), next), bright) in dst
                    .iter_mut()
                    .zip(&self.background[row.clone()])
                    .zip(&mut self.next_background[row.clone()])
                    .zip(&mut self.bright_frames[row])
                {
                    let above = *d > b.saturating_add(rise);
                    *bright = if above { bright.saturating_add(1) } else { 0 };
                    *next = if !above || *bright > BACKGROUND_DELAY_FRAMES {
                        b.saturating_add(rise).min(*d)
                    } else {
                        b
                    };
                    *d = d.saturating_sub(b);
                }
            }
            let tiles = (y / TILE) * tiles_x..(y / TILE + 1) * tiles_x;
            let (mins, maxs) = (&mut self.tile_min[tiles.clone()], &mut self.tile_max[tiles]);
            for ((lo, hi), chunk) in mins.iter_mut().zip(maxs.iter_mut()).zip(dst.chunks(TILE)) {
                let (cmin, cmax) = chunk
                    .iter()
                    .fold((u16::MAX, 0u16), |(a, b), &v| (a.min(v), b.max(v)));
                *lo = (*lo).min(cmin);
                *hi = (*hi).max(cmax);
            }
        }
    }

    /// Eq. 1 against the box mean (replicated borders). Most of an image is background that
    /// provably fails the test: the box mean is at least the smallest blurred value around the
    /// pixel, so a pixel below `that minimum - C` cannot pass. Tiles are screened with that bound;
    /// only surviving tiles get exact box sums, from running column sums (vertical) and a prefix
    /// sum along each tile row (horizontal).
    fn threshold(&mut self, w: usize, h: usize, config: &DetectConfig) {
        let half = config.box_size_px.max(1) / 2;
        let area = ((2 * half + 1) * (2 * half + 1)) as i64;
        // blurred >= sum/area - C  <=>  blurred * area + C * area * 256 >= sum (all scaled by 256)
        let offset = (self.contrast_c * area as f64 * 256.0).round() as i64;
        let c_scaled = (self.contrast_c * 256.0).round() as i64;
        self.mask.clear();
        self.mask.resize(w * h, 0);
        let (tiles_x, tiles_y) = (w.div_ceil(TILE), h.div_ceil(TILE));
        // The box around any pixel of a tile lies within `reach` tiles of it.
        let reach = half.div_ceil(TILE).max(1);
        self.candidate.clear();
        self.candidate.resize(tiles_x * tiles_y, false);
        for ty in 0..tiles_y {
            for tx in 0..tiles_x {
                let mut floor = u16::MAX;
                for ny in ty.saturating_sub(reach)..=(ty + reach).min(tiles_y - 1) {
                    for nx in tx.saturating_sub(reach)..=(tx + reach).min(tiles_x - 1) {
                        floor = floor.min(self.tile_min[ny * tiles_x + nx]);
                    }
                }
                self.candidate[ty * tiles_x + tx] =
                    self.tile_max[ty * tiles_x + tx] as i64 + c_scaled >= floor as i64;
            }
        }
        let row = |y: isize| y.clamp(0, h as isize - 1) as usize * w;
        // Column sums over rows y-half..=y+half (replicated) for the current row y, padded by
        // `half` replicated columns each side so a tile's window needs no clamping. With the box
        // capped at 101 and |C| at 255 every sum and product below stays inside i32.
        let area = area as i32;
        let offset = offset as i32;
        self.column_sums.clear();
        self.column_sums.resize(w + 2 * half, 0);
        for k in -(half as isize)..=half as isize {
            let r = row(k);
            for (s, &b) in self.column_sums[half..half + w]
                .iter_mut()
                .zip(&self.blurred[r..r + w])
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
                    .zip(&self.blurred[add..add + w])
                    .zip(&self.blurred[sub..sub + w])
                {
                    *s += a as i32 - b as i32;
                }
            }
            let (first, last) = (self.column_sums[half], self.column_sums[half + w - 1]);
            self.column_sums[..half].fill(first);
            self.column_sums[half + w..].fill(last);
            let ty = y / TILE;
            for tx in 0..tiles_x {
                if !self.candidate[ty * tiles_x + tx] {
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
                let blurred = &self.blurred[y * w + x0..y * w + x1];
                let mask = &mut self.mask[y * w + x0..y * w + x1];
                for ((m, &b), &sum) in mask.iter_mut().zip(blurred).zip(&sums[..n]) {
                    *m = (b as i32 * area + offset >= sum) as u8;
                }
            }
        }
    }

    /// Sum of the blurred image over the box around (x, y), borders replicated.
    fn box_sum(&self, w: usize, h: usize, half: usize, x: usize, y: usize) -> i64 {
        let half = half as isize;
        let mut sum = 0i64;
        for yy in y as isize - half..=y as isize + half {
            let r = yy.clamp(0, h as isize - 1) as usize * w;
            for xx in x as isize - half..=x as isize + half {
                sum += self.blurred[r + xx.clamp(0, w as isize - 1) as usize] as i64;
            }
        }
        sum
    }

    /// Mean of the blurred image over the threshold box around pixel `i` (grey levels).
    fn local_mean(&self, w: usize, h: usize, half: usize, i: usize) -> f64 {
        self.box_sum(w, h, half, i % w, i / w) as f64
            / ((2 * half + 1) * (2 * half + 1)) as f64
            / 256.0
    }

    fn label(&mut self, image: ImageView<'_>, config: &DetectConfig, out: &mut Vec<Detection>) {
        let (w, h) = (image.width, image.height);
        self.labels.resize(w * h, 0);
        // An image has at most one region per pixel, so starting it with room for that many
        // labels means none wraps within it.
        let most_regions = u32::try_from(w * h).unwrap_or(u32::MAX);
        if self.next_label > u32::MAX - most_regions {
            self.labels.fill(0);
            self.next_label = 0;
        }
        self.resolved.clear();
        let mut start = 0;
        while let Some(next) = next_unlabelled(&self.mask, start) {
            start = next;
            self.next_label += 1;
            let label = self.next_label;
            self.flood_region(w, h, start, |mask, labels, j| {
                let unlabelled = mask[j] == 1;
                if unlabelled {
                    mask[j] = 2;
                    labels[j] = label;
                }
                unlabelled
            });
            let touches_border = self.region.iter().any(|p| {
                let (x, y) = (p.x as usize, p.y as usize);
                x == 0 || y == 0 || x + 1 == w || y + 1 == h
            });
            if self.region.len() < config.min_area_px
                || self.region.len() > config.max_area_px
                || (touches_border && config.reject_border)
            {
                continue;
            }
            let first = out.len();
            self.resolve(image, config, label, out);
            self.resolved.push(ResolvedRegion {
                label,
                first,
                count: out.len() - first,
                area_px: self.region.len(),
            });
        }
    }

    /// Looks again where tracks expect particles (`expected`, raw pixels, e.g. from each track's
    /// motion): a region holding more expected particles than it gave detections is particles
    /// overlapping too closely to part by shape (a merged round blob, a cluster of three), and
    /// is fitted again with one spot seeded at each expected position. Where the fit explains
    /// the region's pixels, its spots replace the region's detections: [`Separation::Fitted`]
    /// where the fit is trustworthy, else [`Separation::Cut`] (good for keeping the tracks,
    /// not for measuring). Regions of more than four expected particles are left as they are.
    /// Called after [`Self::detect`] on the same image, where
    /// [`DetectConfig::separate_expected`] asks for it.
    pub fn separate_expected(
        &mut self,
        image: ImageView<'_>,
        expected: &[PixelPoint],
        out: &mut Vec<Detection>,
    ) {
        if expected.len() < 2 || self.resolved.is_empty() {
            return;
        }
        let (w, h) = (image.width as f64, image.height as f64);
        let mut claims: Vec<(usize, PixelPoint)> = expected
            .iter()
            .filter(|p| p.x >= 0.0 && p.y >= 0.0 && p.x <= w - 1.0 && p.y <= h - 1.0)
            .filter_map(|&p| {
                let j = nearest_pixel(image, p);
                if self.mask.get(j) != Some(&2) {
                    return None;
                }
                // Only the current image's measured regions are in `resolved`.
                let r = self
                    .resolved
                    .binary_search_by_key(&self.labels[j], |r| r.label)
                    .ok()?;
                Some((r, p))
            })
            .collect();
        claims.sort_by_key(|&(r, _)| r);
        let mut replaced: Vec<(usize, Vec<Detection>)> = Vec::new();
        for group in claims.chunk_by(|a, b| a.0 == b.0) {
            let region = self.resolved[group[0].0];
            let k = group.len();
            // A region only cut by shape, whose every part a track expects, is fitted again
            // from the expectations: the cut's parts are biased towards each other, the
            // expectations are not.
            let only_cut = k >= 2
                && k == region.count
                && out[region.first..region.first + region.count]
                    .iter()
                    .all(|d| d.separation == Separation::Cut);
            let more_expected_than_found = k > region.count.max(1);
            if !(more_expected_than_found || only_cut) || k > MAX_SPOTS_PER_REGION {
                continue;
            }
            // Two tracks expecting one spot are one particle followed twice, not two.
            let distinct = group.iter().enumerate().all(|(i, a)| {
                group[i + 1..]
                    .iter()
                    .all(|b| (a.1.x - b.1.x).hypot(a.1.y - b.1.y) >= MIN_EXPECTED_APART_PX)
            });
            if !distinct {
                continue;
            }
            self.gather_region(image, region.label, nearest_pixel(image, group[0].1));
            let share = region.area_px as f64 / k as f64;
            let diameter_px = (4.0 * share / std::f64::consts::PI).sqrt();
            let seeds: Vec<Spot> = group
                .iter()
                .map(|&(_, p)| self.spot_seed(image, p, diameter_px))
                .collect();
            let Some(fit) = self
                .fit_spots_to_region(image, region.label, &seeds)
                .filter(SpotFit::explains_the_pixels)
            else {
                continue;
            };
            let trusted = fit.is_trustworthy();
            let parts = fit
                .spots
                .iter()
                .enumerate()
                .map(|(k, spot)| {
                    let apart =
                        !only_cut || fit.is_apart(k, CUT_REFIT_MIN_SEPARATION_IN_HALF_WIDTHS);
                    let separation = if trusted || (fit.is_measured(k) && apart) {
                        Separation::Fitted
                    } else {
                        Separation::Cut
                    };
                    let centroid = PixelPoint {
                        x: spot.x,
                        y: spot.y,
                    };
                    Detection {
                        centroid,
                        diameter_px,
                        brightness: self.brightness_at(image, centroid),
                        area_px: share.round() as u32,
                        separation,
                    }
                })
                .collect();
            replaced.push((group[0].0, parts));
        }
        if replaced.is_empty() {
            return;
        }
        let before = std::mem::take(out);
        let mut replaced = replaced.into_iter().peekable();
        for (r, region) in self.resolved.iter_mut().enumerate() {
            let first = out.len();
            match replaced.next_if(|(at, _)| *at == r) {
                Some((_, parts)) => out.extend(parts),
                None => out.extend_from_slice(&before[region.first..region.first + region.count]),
            }
            region.first = first;
            region.count = out.len() - first;
        }
    }

    /// Collects the pixels of the current image's region `label` that holds pixel `from` into
    /// `self.region`.
    fn gather_region(&mut self, image: ImageView<'_>, label: u32, from: usize) {
        if self.labels.get(from) != Some(&label) {
            self.region.clear();
            return;
        }
        // Marked as visited by flipping the mask to 3 for the walk, and back after.
        self.flood_region(image.width, image.height, from, |mask, labels, j| {
            let unvisited = mask[j] == 2 && labels[j] == label;
            if unvisited {
                mask[j] = 3;
            }
            unvisited
        });
        for p in &self.region {
            self.mask[p.index as usize] = 2;
        }
    }

    /// Walks the 8-connected pixels from `from` that `claim` accepts (it marks each it accepts,
    /// so none is visited twice) into `self.region`.
    fn flood_region(
        &mut self,
        w: usize,
        h: usize,
        from: usize,
        mut claim: impl FnMut(&mut [u8], &mut [u32], usize) -> bool,
    ) {
        self.region.clear();
        self.stack.clear();
        if !claim(&mut self.mask, &mut self.labels, from) {
            return;
        }
        self.stack.push(Pixel {
            index: from as u32,
            x: (from % w) as u32,
            y: (from / w) as u32,
        });
        while let Some(p) = self.stack.pop() {
            self.region.push(p);
            let (x, y) = (p.x as usize, p.y as usize);
            for ny in y.saturating_sub(1)..=(y + 1).min(h - 1) {
                for nx in x.saturating_sub(1)..=(x + 1).min(w - 1) {
                    let j = ny * w + nx;
                    if claim(&mut self.mask, &mut self.labels, j) {
                        self.stack.push(Pixel {
                            index: j as u32,
                            x: nx as u32,
                            y: ny as u32,
                        });
                    }
                }
            }
        }
    }

    /// A spot to start a fit from: centred at `at`, as bright as the blurred image there, as
    /// wide as a disc of `diameter_px` blurred.
    fn spot_seed(&self, image: ImageView<'_>, at: PixelPoint, diameter_px: f64) -> Spot {
        Spot {
            x: at.x,
            y: at.y,
            amplitude: self.blurred[nearest_pixel(image, at)] as f64 / 256.0,
            sigma: (diameter_px / 3.5).max(0.8),
            flatness: 1.2,
        }
    }

    /// The background model at pixel `i`, grey levels (0 when the model is off).
    #[inline]
    fn background_at(&self, i: usize) -> f64 {
        self.background.get(i).map_or(0.0, |&b| b as f64 / 256.0)
    }

    #[inline]
    fn weight(&self, image: ImageView<'_>, config: &DetectConfig, i: usize) -> f64 {
        let v = (image.pixels[i] as f64 - self.background_at(i)).max(0.0);
        match config.centroid_weight {
            CentroidWeight::Intensity => v,
            CentroidWeight::AboveLocalMean => {
                (v - self.local_mean(image.width, image.height, config.box_size_px / 2, i)).max(0.0)
            }
        }
    }

    /// Measures a region. A round region is one particle. An elongated one is several touching or
    /// overlapping particles whose merged centroid lies on none of them: it is split between its
    /// separated intensity peaks, or failing that cut in two by intensity-weighted 2-means along its
    /// long axis, and kept only if every part comes out round. The parts are then refined by a
    /// spot fit ([`DetectConfig::fit_overlaps`]); see [`Separation`] for what each is good for.
    fn resolve(
        &self,
        image: ImageView<'_>,
        config: &DetectConfig,
        label: u32,
        out: &mut Vec<Detection>,
    ) {
        let region = &self.region;
        let elongated = |p: &[Pixel]| {
            config.max_axis_ratio > 0.0 && p.len() >= 12 && axis_ratio(p) > config.max_axis_ratio
        };
        if !elongated(region) {
            out.extend(self.measure(image, config, region));
            return;
        }
        if !config.split_touching {
            return;
        }
        // Parts separated by a dip are particles that touch; parts cut by 2-means overlap, and
        // their centroids are pulled towards each other.
        let (parts, separation) = match self.split_at_peaks(image, config, label) {
            Some(parts) => (parts, Separation::Clear),
            None => (self.two_means(image, config, region), Separation::Cut),
        };
        // A part still elongated is itself several particles (a chain of three, or a pair
        // inside a cluster): cut it again, up to the most spots a fit takes. Only what cannot
        // be made round is dropped, not the whole region: measured on the dense seeded scene,
        // dropping whole regions lost one particle image in ten among those 3-5 px from a
        // neighbour.
        let mut round: Vec<(Vec<Pixel>, Separation)> = Vec::new();
        // A stack, so parts come out in the order they were cut.
        let mut pending: Vec<(Vec<Pixel>, Separation)> =
            parts.into_iter().rev().map(|p| (p, separation)).collect();
        let mut complete = true;
        while let Some((part, separation)) = pending.pop() {
            if part.len() < config.min_area_px {
                complete = false;
            } else if !elongated(&part) {
                round.push((part, separation));
            } else if round.len() + pending.len() + 2 <= MAX_SPOTS_PER_REGION {
                pending.extend(
                    self.two_means(image, config, &part)
                        .into_iter()
                        .rev()
                        .map(|half| (half, Separation::Cut)),
                );
            } else {
                complete = false;
            }
        }
        let mut measured: Vec<Detection> = round
            .iter()
            .filter_map(|(part, separation)| {
                let d = self.measure(image, config, part)?;
                Some(Detection {
                    separation: *separation,
                    ..d
                })
            })
            .collect();
        // A fit needs every particle of the region, or the missing one's light pulls the rest.
        // Regions cut into three or four parts are only tracked: fitting them took a quarter
        // of a 0.005-particles-per-pixel frame's time for one point of yield (54.2 % vs
        // 53.2 %); the tracks that expect particles there still get them fitted
        // ([`Self::separate_expected`]).
        if config.fit_overlaps && complete && measured.len() == round.len() && round.len() <= 2 {
            // An untrusted fit changes nothing: measured on the synthetic scenes, even its
            // better-placed cut parts moved tracks enough to triple one rig's out-of-plane error.
            let seeds: Vec<Spot> = measured
                .iter()
                .map(|d| self.spot_seed(image, d.centroid, d.diameter_px))
                .collect();
            if let Some(fit) = self
                .fit_spots_to_region(image, label, &seeds)
                .filter(SpotFit::is_trustworthy)
            {
                for (d, spot) in measured.iter_mut().zip(&fit.spots) {
                    d.centroid = PixelPoint {
                        x: spot.x,
                        y: spot.y,
                    };
                    d.brightness = self.brightness_at(image, d.centroid);
                    d.separation = d.separation.min(Separation::Fitted);
                }
            }
        }
        out.extend(measured);
    }

    /// Fits spots from `seeds` to the current region in the blurred image (background model
    /// subtracted) over the region and a 2-pixel margin of background around it; pixels of
    /// other regions are left out.
    fn fit_spots_to_region(
        &self,
        image: ImageView<'_>,
        label: u32,
        seeds: &[Spot],
    ) -> Option<SpotFit> {
        let (w, h) = (image.width, image.height);
        let (mut x0, mut y0, mut x1, mut y1) = (u32::MAX, u32::MAX, 0, 0);
        for p in &self.region {
            x0 = x0.min(p.x);
            y0 = y0.min(p.y);
            x1 = x1.max(p.x);
            y1 = y1.max(p.y);
        }
        // Two pixels of background around the region pin down the floor and the spots' tails
        // (with one, in a trial under an earlier iteration limit, the cluttered room lost 1.6
        // points of yield).
        let margin = 2;
        let (x0, y0) = (
            (x0 as usize).saturating_sub(margin),
            (y0 as usize).saturating_sub(margin),
        );
        let (x1, y1) = (
            (x1 as usize + margin).min(w - 1),
            (y1 as usize + margin).min(h - 1),
        );
        // Only pixels within the margin of the region: an elongated region's bounding box is
        // mostly background far from either particle.
        let (bw, bh) = (x1 - x0 + 1, y1 - y0 + 1);
        let mut near = vec![false; bw * bh];
        for p in &self.region {
            let (px, py) = (p.x as usize - x0, p.y as usize - y0);
            for ny in py.saturating_sub(margin)..=(py + margin).min(bh - 1) {
                let row = ny * bw;
                near[row + px.saturating_sub(margin)..=row + (px + margin).min(bw - 1)].fill(true);
            }
        }
        let mut samples = Vec::with_capacity(bw * bh);
        for y in y0..=y1 {
            for x in x0..=x1 {
                let j = y * w + x;
                if near[(y - y0) * bw + (x - x0)]
                    && (self.mask[j] == 0 || (self.mask[j] == 2 && self.labels[j] == label))
                {
                    samples.push((x as f64, y as f64, self.blurred[j] as f64 / 256.0));
                }
            }
        }
        fit_spots(&samples, seeds)
    }

    /// Raw intensity above the background model at a centroid (bilinear, clamped to the image).
    fn brightness_at(&self, image: ImageView<'_>, centroid: PixelPoint) -> f64 {
        (image.bilinear(centroid) - self.background_at(nearest_pixel(image, centroid))).max(0.0)
    }

    /// Splits a region in two along its long axis.
    fn two_means(
        &self,
        image: ImageView<'_>,
        config: &DetectConfig,
        pixels: &[Pixel],
    ) -> Vec<Vec<Pixel>> {
        // Seed the two centres on the long axis, one standard deviation out.
        let m = Moments::of(pixels);
        let (mx, my) = (m.mean_x, m.mean_y);
        let angle = 0.5 * (2.0 * m.xy).atan2(m.xx - m.yy);
        let spread = ((m.xx + m.yy) / pixels.len() as f64).sqrt();
        let (ux, uy) = (angle.cos() * spread, angle.sin() * spread);
        self.k_means(
            image,
            config,
            pixels,
            vec![(mx - ux, my - uy), (mx + ux, my + uy)],
        )
    }

    /// Intensity-weighted k-means of a region's pixels from the given seeds (a few rounds suffice
    /// for the handful of pixels in a particle image).
    fn k_means(
        &self,
        image: ImageView<'_>,
        config: &DetectConfig,
        pixels: &[Pixel],
        mut centres: Vec<(f64, f64)>,
    ) -> Vec<Vec<Pixel>> {
        let points: Vec<(f64, f64, f64)> = pixels
            .iter()
            .map(|p| {
                (
                    p.x as f64,
                    p.y as f64,
                    self.weight(image, config, p.index as usize).max(1e-9),
                )
            })
            .collect();
        let mut nearest = vec![0usize; points.len()];
        let mut sums = vec![(0.0, 0.0, 0.0); centres.len()];
        for _ in 0..10 {
            sums.iter_mut().for_each(|s| *s = (0.0, 0.0, 0.0));
            for (&(x, y, v), n) in points.iter().zip(nearest.iter_mut()) {
                let mut best = f64::MAX;
                for (c, &(cx, cy)) in centres.iter().enumerate() {
                    let d = (x - cx) * (x - cx) + (y - cy) * (y - cy);
                    if d < best {
                        best = d;
                        *n = c;
                    }
                }
                let s = &mut sums[*n];
                *s = (s.0 + v, s.1 + v * x, s.2 + v * y);
            }
            let mut moved: f64 = 0.0;
            for (c, &(sw, sx, sy)) in centres.iter_mut().zip(&sums) {
                if sw > 0.0 {
                    let next = (sx / sw, sy / sw);
                    moved = moved.max((next.0 - c.0).abs() + (next.1 - c.1).abs());
                    *c = next;
                }
            }
            if moved < 1e-6 {
                break;
            }
        }
        let mut parts: Vec<Vec<Pixel>> = vec![Vec::new(); centres.len()];
        for (&p, &n) in pixels.iter().zip(&nearest) {
            parts[n].push(p);
        }
        parts
    }

    fn measure(
        &self,
        image: ImageView<'_>,
        config: &DetectConfig,
        pixels: &[Pixel],
    ) -> Option<Detection> {
        let (mut m00, mut m10, mut m01) = (0.0, 0.0, 0.0);
        for p in pixels {
            let v = self.weight(image, config, p.index as usize);
            m00 += v;
            m10 += v * p.x as f64;
            m01 += v * p.y as f64;
        }
        if m00 <= 0.0 {
            return None;
        }
        let centroid = PixelPoint {
            x: m10 / m00,
            y: m01 / m00,
        };
        Some(Detection {
            centroid,
            diameter_px: (4.0 * pixels.len() as f64 / std::f64::consts::PI).sqrt(),
            brightness: self.brightness_at(image, centroid),
            area_px: pixels.len() as u32,
            separation: Separation::Clear,
        })
    }

    /// Splits the current region between its separated peaks of the blurred image; `None` when
    /// it has one peak, or peaks joined without a real dip (a flat-topped disc with noise).
    fn split_at_peaks(
        &self,
        image: ImageView<'_>,
        config: &DetectConfig,
        label: u32,
    ) -> Option<Vec<Vec<Pixel>>> {
        let w = image.width;
        let h = image.height;
        let b = &self.blurred;
        let region = &self.region;
        let in_region = |j: usize| self.labels[j] == label;
        // Peak pixels: not lower than any 8-neighbour inside the region.
        let mut peaks: Vec<Pixel> = Vec::new();
        let mut floor = u16::MAX;
        for &p in region {
            let i = p.index as usize;
            floor = floor.min(b[i]);
            let (x, y) = (p.x as usize, p.y as usize);
            let mut is_peak = true;
            'n: for ny in y.saturating_sub(1)..=(y + 1).min(h - 1) {
                for nx in x.saturating_sub(1)..=(x + 1).min(w - 1) {
                    let j = ny * w + nx;
                    if j != i && b[j] > b[i] && in_region(j) {
                        is_peak = false;
                        break 'n;
                    }
                }
            }
            if is_peak {
                peaks.push(p);
            }
        }
        // Keep the highest peak of every group whose members are joined without a real dip.
        let at = |p: &Pixel| b[p.index as usize];
        peaks.sort_by(|a, c| at(c).cmp(&at(a)).then(a.index.cmp(&c.index)));
        let mut kept: Vec<Pixel> = Vec::new();
        for &p in &peaks {
            let separate = kept.iter().all(|k| {
                let lower = (at(&p).min(at(k)) - floor) as f64;
                let dip = lowest_on_segment(b, w, &p, k) - floor as f64;
                dip < (1.0 - config.split_dip_fraction) * lower
            });
            if separate {
                kept.push(p);
            }
        }
        if kept.len() < 2 {
            return None;
        }
        let seeds = kept.iter().map(|k| (k.x as f64, k.y as f64)).collect();
        Some(self.k_means(image, config, region, seeds))
    }
}

/// The most particles one region is split into: the spot fit takes at most four.
const MAX_SPOTS_PER_REGION: usize = 4;

/// Tracks expecting particles closer than this are taken to follow the same one.
const MIN_EXPECTED_APART_PX: f64 = 1.0;

/// A region only cut by shape and fitted again from its tracks' expectations: a spot counts as
/// measured only this far from the others (in sums of half widths; trustworthy fits need 1).
/// Closer ones, measured in turbulence, came out pinned by the fit's covariance but biased by
/// the spot model's mismatch: at 0 the turbulence scene's out-of-plane error rose from 2.15 %
/// to 3.09 % (yield 87.0 -> 95.4 %); at 0.85, 2.52 % (yield 91.1 %); at 1, 2.50 % (yield 87.1 %).
const CUT_REFIT_MIN_SEPARATION_IN_HALF_WIDTHS: f64 = 0.85;

/// Index of the pixel nearest a point of the image (clamped to the image).
fn nearest_pixel(image: ImageView<'_>, at: PixelPoint) -> usize {
    (at.y.round() as usize).min(image.height - 1) * image.width
        + (at.x.round() as usize).min(image.width - 1)
}

/// The next pixel at or after `from` marked 1 (foreground, unlabelled). Skips 16 pixels at a time
/// with a branch-free test the compiler vectorises: most of an image is background.
fn next_unlabelled(mask: &[u8], from: usize) -> Option<usize> {
    let mut at = from;
    while at < mask.len() {
        let end = (at + 16).min(mask.len());
        let chunk = &mask[at..end];
        if chunk.iter().fold(0u8, |acc, &m| acc | (m & 1)) != 0 {
            return chunk.iter().position(|&m| m == 1).map(|p| at + p);
        }
        at = end;
    }
    None
}

/// Centroid and second central moments of a region's pixel positions (unweighted: its shape).
struct Moments {
    mean_x: f64,
    mean_y: f64,
    xx: f64,
    yy: f64,
    xy: f64,
}

impl Moments {
    fn of(pixels: &[Pixel]) -> Self {
        let n = pixels.len().max(1) as f64;
        let (sx, sy) = pixels
            .iter()
            .fold((0.0, 0.0), |(x, y), p| (x + p.x as f64, y + p.y as f64));
        let (mean_x, mean_y) = (sx / n, sy / n);
        let (mut xx, mut yy, mut xy) = (0.0, 0.0, 0.0);
        for p in pixels {
            let (dx, dy) = (p.x as f64 - mean_x, p.y as f64 - mean_y);
            xx += dx * dx;
            yy += dy * dy;
            xy += dx * dy;
        }
        Self {
            mean_x,
            mean_y,
            xx,
            yy,
            xy,
        }
    }
}

/// Long over short axis of a region's pixel distribution (from its second central moments).
fn axis_ratio(pixels: &[Pixel]) -> f64 {
    let m = Moments::of(pixels);
    let (mean, diff) = ((m.xx + m.yy) / 2.0, ((m.xx - m.yy) / 2.0).hypot(m.xy));
    let (major, minor) = (mean + diff, (mean - diff).max(1e-12));
    (major / minor).sqrt()
}

/// Side of the tiles screened before the exact threshold test, pixels.
const TILE: usize = 16;

fn kernel(sample: impl Fn(isize) -> u16) -> u16 {
    sample(-2) + 4 * sample(-1) + 6 * sample(0) + 4 * sample(1) + sample(2)
}

fn lowest_on_segment(b: &[u16], w: usize, from: &Pixel, to: &Pixel) -> f64 {
    let (x0, y0) = (from.x as f64, from.y as f64);
    let (x1, y1) = (to.x as f64, to.y as f64);
    let steps = ((x1 - x0).abs().max((y1 - y0).abs()).ceil() as usize).max(1);
    (0..=steps)
        .map(|s| {
            let t = s as f64 / steps as f64;
            let (x, y) = ((x0 + t * (x1 - x0)).round(), (y0 + t * (y1 - y0)).round());
            b[y as usize * w + x as usize] as f64
        })
        .fold(f64::MAX, f64::min)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn detect(width: usize, pixels: &[u8], config: &DetectConfig) -> Vec<Detection> {
        let image = ImageView::new(width, pixels.len() / width, pixels).expect("valid");
        let mut out = Vec::new();
        Detector::new().detect(image, config, &mut out);
        out
    }

    #[test]
    fn finds_a_literal_particle_and_its_centroid() {
        #[rustfmt::skip]
        let img: Vec<u8> = vec![
            0, 0, 0, 0, 0, 0, 0, 0,
            0, 0, 0, 0, 0, 0, 0, 0,
            0, 0, 0, 100, 200, 0, 0, 0,
            0, 0, 0, 200, 200, 0, 0, 0,
            0, 0, 0, 0, 0, 0, 0, 0,
            0, 0, 0, 0, 0, 0, 0, 0,
        ];
        let d = detect(8, &img, &DetectConfig::default());
        assert_eq!(d.len(), 1);
        // Moments over the raw intensities: (3*100 + 4*200 + 3*200 + 4*200) / 700 etc.
        assert!(
            (d[0].centroid.x - 2500.0 / 700.0).abs() < 1e-9,
            "{:?}",
            d[0]
        );
        assert!(
            (d[0].centroid.y - 1800.0 / 700.0).abs() < 1e-9,
            "{:?}",
            d[0]
        );
        assert!(d[0].diameter_px > 2.0);
    }

    #[test]
    fn flat_and_empty_images_have_no_particles() {
        let config = DetectConfig::default();
        assert!(detect(16, &[0u8; 16 * 12], &config).is_empty());
        assert!(detect(16, &[255u8; 16 * 12], &config).is_empty());
        assert!(detect(16, &[77u8; 16 * 12], &config).is_empty());
    }

    #[test]
    fn two_separate_particles_in_raster_order() {
        let mut img = vec![10u8; 30 * 20];
        img[5 * 30 + 20] = 200;
        img[5 * 30 + 21] = 200;
        img[15 * 30 + 4] = 200;
        img[15 * 30 + 5] = 200;
        let d = detect(30, &img, &DetectConfig::default());
        assert_eq!(d.len(), 2);
        assert!((d[0].centroid.x - 20.5).abs() < 1e-9 && (d[0].centroid.y - 5.0).abs() < 1e-9);
        assert!((d[1].centroid.x - 4.5).abs() < 1e-9 && (d[1].centroid.y - 15.0).abs() < 1e-9);
    }

    #[test]
    fn touching_particles_are_split_only_when_asked() {
        // Two 4x4 bright squares joined by a dimmer bridge.
        let w = 24;
        let mut img = vec![0u8; w * 12];
        for y in 4..8 {
            for x in 4..8 {
                img[y * w + x] = 220;
                img[y * w + x + 9] = 220;
            }
        }
        for x in 8..13 {
            img[5 * w + x] = 100;
            img[6 * w + x] = 100;
        }
        let split = detect(w, &img, &DetectConfig::default());
        assert_eq!(split.len(), 2, "{split:?}");
        assert!(
            split.iter().all(|d| d.separation == Separation::Clear),
            "separated by a dip: touching, not overlapping"
        );
        // Each part keeps its half of the bridge (the middle column goes to one side), which pulls
        // its centroid inwards by at most 600 * 3.5 / 4120 = 0.51 px.
        assert!(
            (split[0].centroid.x - 5.5).abs() < 0.52 && (split[1].centroid.x - 14.5).abs() < 0.52,
            "{split:?}"
        );
        assert!(
            (split[0].centroid.y - 5.5).abs() < 1e-9 && (split[1].centroid.y - 5.5).abs() < 1e-9
        );
        let whole = DetectConfig {
            split_touching: false,
            max_axis_ratio: 0.0,
            ..Default::default()
        };
        assert_eq!(detect(w, &img, &whole).len(), 1);
        let elongated = DetectConfig {
            split_touching: false,
            ..Default::default()
        };
        assert!(
            detect(w, &img, &elongated).is_empty(),
            "merged pair is elongated"
        );
    }

    #[test]
    fn heavily_overlapping_discs_are_cut_in_two_and_only_tracked() {
        let w = 30;
        let mut img = vec![0u8; w * 20];
        for y in 0..20usize {
            for x in 0..w {
                let r1 = ((x as f64 - 11.0).powi(2) + (y as f64 - 10.0).powi(2)).sqrt();
                let r2 = ((x as f64 - 17.0).powi(2) + (y as f64 - 10.0).powi(2)).sqrt();
                img[y * w + x] = (u8::from(r1 < 4.0) + u8::from(r2 < 4.0)) * 100;
            }
        }
        let centres = |d: &[Detection]| {
            let mut xs: Vec<f64> = d.iter().map(|d| d.centroid.x).collect();
            xs.sort_by(f64::total_cmp);
            xs
        };
        let cut_only = DetectConfig {
            fit_overlaps: false,
            ..Default::default()
        };
        let cut = detect(w, &img, &cut_only);
        assert_eq!(cut.len(), 2, "{cut:?}");
        assert!(cut.iter().all(|d| d.separation == Separation::Cut));
        let xs = centres(&cut);
        assert!(
            (xs[0] - 11.0).abs() < 0.8 && (xs[1] - 17.0).abs() < 0.8,
            "{xs:?}"
        );
        // Centres 6 px apart with 4 px radii: too close for the fit to be trusted, so the cut
        // stands.
        let fitted = detect(w, &img, &DetectConfig::default());
        assert_eq!(fitted, cut);
    }

    /// Gaussian spots of amplitude 200 on a floor of 10, `w` x `h`.
    fn gaussian_spots(w: usize, h: usize, sigma: f64, centres: &[(f64, f64)]) -> Vec<u8> {
        (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f64, (i / w) as f64);
                let v: f64 = centres
                    .iter()
                    .map(|&(cx, cy)| {
                        200.0
                            * (-((x - cx).powi(2) + (y - cy).powi(2)) / (2.0 * sigma * sigma)).exp()
                    })
                    .sum();
                (10.0 + v).min(255.0).round() as u8
            })
            .collect()
    }

    /// The largest distance from a truth centre to the nearest detection, pixels.
    fn worst_error(truth: &[(f64, f64)], found: &[Detection]) -> f64 {
        truth
            .iter()
            .map(|&(tx, ty)| {
                found
                    .iter()
                    .map(|d| (d.centroid.x - tx).hypot(d.centroid.y - ty))
                    .fold(f64::MAX, f64::min)
            })
            .fold(0.0, f64::max)
    }

    #[test]
    fn overlapping_spots_without_a_dip_are_fitted_and_measured() {
        // Two Gaussian spots (sigma 1.5 px) 4.8 px apart: after the 5x5 blur there is no dip
        // between them, so they are cut, and the fit separates them.
        let w = 32;
        let truth = [(12.3, 10.4), (16.9, 11.8)];
        let img = gaussian_spots(w, 22, 1.5, &truth);
        let cut_only = DetectConfig {
            fit_overlaps: false,
            ..Default::default()
        };
        let error = |d: &[Detection]| worst_error(&truth, d);
        let cut = detect(w, &img, &cut_only);
        assert_eq!(cut.len(), 2, "{cut:?}");
        assert!(cut.iter().all(|d| d.separation == Separation::Cut));
        let fitted = detect(w, &img, &DetectConfig::default());
        assert_eq!(fitted.len(), 2, "{fitted:?}");
        assert!(
            fitted.iter().all(|d| d.separation == Separation::Fitted),
            "{fitted:?}"
        );
        // The cut is off by 0.1 px here, the fit by under 0.01 px.
        assert!(
            error(&fitted) < 0.02 && error(&fitted) < error(&cut) / 5.0,
            "fitted {fitted:?}, cut {cut:?}"
        );
    }

    #[test]
    fn a_part_still_elongated_is_cut_again_until_each_part_is_round() {
        // A dip parts the right spot from the other two, which overlap without one: the left
        // part is still two particles, so it is cut again (the whole region used to be
        // dropped).
        let w = 36;
        let truth = [(9.0, 12.0), (12.6, 12.5), (19.5, 12.2)];
        let found = detect(
            w,
            &gaussian_spots(w, 24, 1.3, &truth),
            &DetectConfig::default(),
        );
        let separations: Vec<Separation> = found.iter().map(|d| d.separation).collect();
        assert_eq!(
            separations,
            [Separation::Cut, Separation::Cut, Separation::Clear],
            "{found:?}"
        );
        // Cut centroids are pulled towards each other: good for tracking, not for measuring.
        assert!(worst_error(&truth, &found) < 0.3, "{found:?}");
    }

    /// Detects `img` and looks again where `expected` says particles are.
    fn detect_expecting(w: usize, img: &[u8], expected: &[(f64, f64)]) -> Vec<Detection> {
        let image = ImageView::new(w, img.len() / w, img).expect("valid");
        let config = DetectConfig::default();
        let mut detector = Detector::new();
        let mut out = Vec::new();
        detector.detect(image, &config, &mut out);
        let expected: Vec<PixelPoint> =
            expected.iter().map(|&(x, y)| PixelPoint { x, y }).collect();
        detector.separate_expected(image, &expected, &mut out);
        out
    }

    #[test]
    fn particles_merged_into_one_round_blob_are_found_where_tracks_expect_them() {
        // Two spots 2.9 px apart blur into one round blob: its shape gives one particle, with
        // its centroid between the two.
        let w = 30;
        let truth = [(13.4, 11.2), (16.1, 12.3)];
        let img = gaussian_spots(w, 24, 1.3, &truth);
        let alone = detect(w, &img, &DetectConfig::default());
        assert_eq!(alone.len(), 1, "{alone:?}");
        assert!(worst_error(&truth, &alone) > 1.0, "{alone:?}");
        // Tracks expecting them 0.3-0.4 px off (a prediction's usual miss) get both back.
        let expected = [(13.1, 11.5), (16.4, 12.0)];
        let found = detect_expecting(w, &img, &expected);
        assert_eq!(found.len(), 2, "{found:?}");
        assert!(worst_error(&truth, &found) < 0.05, "{found:?}");
        assert!(
            found.iter().all(|d| d.separation == Separation::Fitted),
            "well determined by the pixels: {found:?}"
        );
        // One expectation, or two on the same spot, leave the region as it was.
        assert_eq!(detect_expecting(w, &img, &expected[..1]), alone);
        assert_eq!(
            detect_expecting(w, &img, &[(14.7, 11.7), (14.9, 11.9)]),
            alone
        );
    }

    #[test]
    fn a_pair_only_cut_is_measured_where_its_tracks_expect_it() {
        // Two spots (sigma 1.5 px) 3.8 px apart: no dip, and the fit seeded from the shape's
        // cut is too close to trust, so both are only cut, 0.19 px off.
        let w = 32;
        let truth = [(13.0, 11.0), (16.572, 12.292)];
        let img = gaussian_spots(w, 24, 1.5, &truth);
        let alone = detect(w, &img, &DetectConfig::default());
        assert_eq!(alone.len(), 2, "{alone:?}");
        assert!(alone.iter().all(|d| d.separation == Separation::Cut));
        assert!(worst_error(&truth, &alone) > 0.15, "{alone:?}");
        // Both tracks expecting their particle, 0.3-0.4 px off: fitted from there, measured.
        let expected = [(12.7, 11.3), (16.9, 12.1)];
        let found = detect_expecting(w, &img, &expected);
        assert_eq!(found.len(), 2, "{found:?}");
        assert!(
            found.iter().all(|d| d.separation == Separation::Fitted),
            "{found:?}"
        );
        assert!(worst_error(&truth, &found) < 0.02, "{found:?}");
        // Only one of them expected (the other expectation falls on the background): the cut
        // stands.
        assert_eq!(
            detect_expecting(w, &img, &[expected[0], (28.0, 20.0)]),
            alone
        );
    }

    #[test]
    fn one_particle_expected_twice_stays_one() {
        // Two tracks on either side of a single spot (one of them following a ghost, or two
        // that swapped): the pixels hold one particle, and that is what comes out.
        let w = 30;
        let img = gaussian_spots(w, 24, 1.3, &[(14.6, 11.8)]);
        let alone = detect(w, &img, &DetectConfig::default());
        assert_eq!(alone.len(), 1);
        let found = detect_expecting(w, &img, &[(13.2, 11.5), (16.0, 12.1)]);
        assert_eq!(found, alone);
    }

    #[test]
    fn round_particles_pass_the_axis_ratio_test() {
        let w = 20;
        let mut img = vec![0u8; w * 20];
        for y in 0..20usize {
            for x in 0..w {
                let r = ((x as f64 - 9.3).powi(2) + (y as f64 - 10.2).powi(2)).sqrt();
                if r < 4.0 {
                    img[y * w + x] = 200;
                }
            }
        }
        let d = detect(w, &img, &DetectConfig::default());
        assert_eq!(d.len(), 1);
        assert!((d[0].diameter_px - 8.0).abs() < 1.5, "{:?}", d[0]);
    }

    #[test]
    fn particle_on_the_image_border_is_found_only_when_allowed() {
        let mut img = vec![0u8; 10 * 10];
        img[0] = 250;
        img[1] = 250;
        img[10] = 250;
        img[11] = 250;
        let keep = DetectConfig {
            reject_border: false,
            ..Default::default()
        };
        let d = detect(10, &img, &keep);
        assert_eq!(d.len(), 1);
        assert!((d[0].centroid.x - 0.5).abs() < 1e-9 && (d[0].centroid.y - 0.5).abs() < 1e-9);
        assert!(
            detect(10, &img, &DetectConfig::default()).is_empty(),
            "clipped particle dropped by default"
        );
    }

    /// A 96x64 frame: background 20, a static lamp (a bright spot) and a poster with print,
    /// and a Gaussian particle image at `particle`.
    fn room_with_particle(particle: (f64, f64)) -> Vec<u8> {
        let (w, h) = (96usize, 64usize);
        let mut img = vec![0f64; w * h];
        for y in 0..h {
            for x in 0..w {
                let mut v = 20.0;
                if (50..90).contains(&x) && (4..30).contains(&y) {
                    v += if (y / 3) % 2 == 1 && (x / 2) % 3 != 0 {
                        12.0
                    } else {
                        60.0
                    };
                }
                let lamp = ((x as f64 - 20.0).powi(2) + (y as f64 - 12.0).powi(2)) / 2.0;
                let spot = ((x as f64 - particle.0).powi(2) + (y as f64 - particle.1).powi(2))
                    / (2.0 * 1.3 * 1.3);
                img[y * w + x] = v + 160.0 * (-lamp).exp() + 150.0 * (-spot).exp();
            }
        }
        img.iter().map(|v| v.round().min(255.0) as u8).collect()
    }

    #[test]
    fn the_background_model_fades_what_stands_still_and_keeps_what_moves() {
        let config = DetectConfig::default();
        let method = DetectConfig {
            background_rise_per_frame: 0.0,
            ..DetectConfig::default()
        };
        let mut with_model = Detector::new();
        let mut without = Detector::new();
        let near = |d: &Detection, x: f64, y: f64| (d.centroid.x - x).hypot(d.centroid.y - y) < 2.0;
        let mut out = Vec::new();
        let mut squared_errors = [0.0f64; 2];
        for frame in 0..90 {
            // Across the view past the lamp and under the poster: 1 px per frame, slower than
            // its own diameter.
            let t = frame as f64;
            let particle = (8.0 + 0.9 * t, 18.0 + 0.4 * t);
            let pixels = room_with_particle(particle);
            let image = ImageView::new(96, 64, &pixels).expect("valid");
            with_model.detect(image, &config, &mut out);
            let Some(found) = out.iter().find(|d| near(d, particle.0, particle.1)) else {
                panic!("frame {frame}: moving particle at {particle:?} not found: {out:?}");
            };
            squared_errors[0] +=
                (found.centroid.x - particle.0).powi(2) + (found.centroid.y - particle.1).powi(2);
            let lamp_seen = out.iter().any(|d| near(d, 20.0, 12.0));
            if frame == 0 {
                assert!(
                    lamp_seen,
                    "the model starts empty: the first frame is as it is"
                );
            }
            // The lamp's blurred peak is ~80 grey levels: 10 + 80 / 2 frames.
            if frame >= 60 {
                assert!(!lamp_seen, "frame {frame}: the lamp should have faded");
                assert_eq!(out.len(), 1, "frame {frame}: {out:?}");
            }
            without.detect(image, &method, &mut out);
            assert!(
                out.iter().any(|d| near(d, 20.0, 12.0)),
                "no model: the lamp stays"
            );
            if let Some(found) = out.iter().find(|d| near(d, particle.0, particle.1)) {
                squared_errors[1] += (found.centroid.x - particle.0).powi(2)
                    + (found.centroid.y - particle.1).powi(2);
            }
        }
        let [with_model, without] = squared_errors.map(|e| (e / 90.0).sqrt());
        assert!(
            with_model < 0.1 && with_model < without,
            "RMS centroid error {with_model:.3} px with the model, {without:.3} px without"
        );
    }
}
