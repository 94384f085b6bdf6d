//! Stage 1: particle detection in one grayscale image (method section 3.1).
//!
//! 5x5 Gaussian blur (OpenCV's fixed binomial kernel for `ksize = 5, sigma = 0`), adaptive
//! threshold against the mean of a 15x15 box minus a contrast constant C (Sauvola-style local
//! binarisation), then 8-connected regions of the binary image. The regions are exactly the areas
//! enclosed by the outer borders that Suzuki & Abe (1985) border following returns, so labelling
//! them directly gives the same particles without tracing contours. Per region: intensity-weighted
//! moment centroid (eqs. 2-3), brightness at the centroid, equivalent diameter.
//!
//! Beyond the method: regions holding several separated intensity peaks (touching particles) can be
//! split between their peaks ([`DetectConfig::split_touching`]).

use serde::{Deserialize, Serialize};

use super::ImageView;
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
    /// Side of the box whose mean is the local threshold base, pixels (method: 15).
    pub box_size_px: usize,
    /// Contrast constant C, grey levels: a pixel is a particle if `blurred >= box_mean - C`
    /// (method eq. 1). Bright particles on a darker background need C < 0; the method leaves the
    /// value to the user, -6 keeps sensor noise of a few grey levels out.
    pub contrast_c: f64,
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
    /// Split regions that hold several peaks separated by a dip (touching particles).
    pub split_touching: bool,
    /// A dip between two peaks must fall below `(1 - split_dip_fraction)` of the lower peak's
    /// height above the region's edge for the peaks to count as separate particles.
    pub split_dip_fraction: f64,
}

impl Default for DetectConfig {
    fn default() -> Self {
        Self {
            box_size_px: 15,
            contrast_c: -6.0,
            min_area_px: 3,
            max_area_px: 5000,
            centroid_weight: CentroidWeight::Intensity,
            reject_border: true,
            max_axis_ratio: 1.5,
            split_touching: true,
            split_dip_fraction: 0.25,
        }
    }
}

/// One detected particle image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Detection {
    pub centroid: PixelPoint,
    /// Equivalent diameter: the circle with the region's area, pixels.
    pub diameter_px: f64,
    /// Raw intensity at the centroid (bilinear), grey levels.
    pub brightness: f64,
    pub area_px: u32,
    /// Cut out of an elongated region of overlapping particles: found, but its centroid is
    /// pulled towards its neighbour, so good for tracking and not for measuring.
    pub from_overlap: bool,
}

/// Reusable buffers, so the hot path allocates nothing once warmed up.
#[derive(Debug, Default)]
pub struct Detector {
    row_pass: Vec<u16>,
    /// Blurred image scaled by 256 (the binomial kernel's sum), kept unrounded.
    blurred: Vec<u16>,
    column_sums: Vec<u32>,
    /// 0 background, 1 foreground not yet labelled, 2 labelled.
    mask: Vec<u8>,
    stack: Vec<u32>,
    region: Vec<u32>,
}

impl Detector {
    pub fn new() -> Self {
        Self::default()
    }

    /// Detects particles; appends to `out` (cleared first) in raster order of their first pixel.
    pub fn detect(&mut self, image: ImageView<'_>, config: &DetectConfig, out: &mut Vec<Detection>) {
        out.clear();
        let (w, h) = (image.width, image.height);
        if w == 0 || h == 0 {
            return;
        }
        self.blur(image);
        self.threshold(w, h, config);
        self.label(image, config, out);
    }

    fn blur(&mut self, image: ImageView<'_>) {
        let (w, h) = (image.width, image.height);
        let px = image.pixels;
        self.row_pass.resize(w * h, 0);
        self.blurred.resize(w * h, 0);
        let clamp_x = |x: isize| x.clamp(0, w as isize - 1) as usize;
        for (src, dst) in px.chunks_exact(w).zip(self.row_pass.chunks_exact_mut(w)) {
            // Slice zips instead of indexing, so the compiler drops bounds checks and vectorises.
            if w >= 5 {
                for (d, s) in dst[2..w - 2].iter_mut().zip(src.windows(5)) {
                    *d = s[0] as u16 + 4 * s[1] as u16 + 6 * s[2] as u16 + 4 * s[3] as u16 + s[4] as u16;
                }
            }
            for x in (0..w.min(2)).chain(w.saturating_sub(2).max(w.min(2))..w) {
                dst[x] = kernel(|k| src[clamp_x(x as isize + k)] as u16);
            }
        }
        let row = |y: isize| y.clamp(0, h as isize - 1) as usize * w;
        for y in 0..h as isize {
            let tmp = &self.row_pass;
            let rows = [row(y - 2), row(y - 1), row(y), row(y + 1), row(y + 2)].map(|r| &tmp[r..r + w]);
            let dst = &mut self.blurred[y as usize * w..(y as usize + 1) * w];
            for ((((d, a), b), c), (e, f)) in dst
                .iter_mut()
                .zip(rows[0])
                .zip(rows[1])
                .zip(rows[2])
                .zip(rows[3].iter().zip(rows[4]))
            {
                *d = a + 4 * b + 6 * c + 4 * e + f;
            }
        }
    }

    /// Box mean with replicated borders by running column sums, then eq. 1.
    fn threshold(&mut self, w: usize, h: usize, config: &DetectConfig) {
        let half = config.box_size_px.max(1) / 2;
        let area = ((2 * half + 1) * (2 * half + 1)) as i64;
        // blurred >= sum/area - C  <=>  blurred * area + C * area * 256 >= sum (all scaled by 256);
        // the largest sum, 225 * 65280, fits an i32 easily.
        let offset = (config.contrast_c * area as f64 * 256.0).round().clamp(i32::MIN as f64, i32::MAX as f64) as i32;
        let area = area as i32;
        let row = |y: isize| y.clamp(0, h as isize - 1) as usize * w;
        self.mask.resize(w * h, 0);
        self.column_sums.clear();
        self.column_sums.resize(w, 0);
        for k in -(half as isize)..=half as isize {
            let r = row(k);
            for (s, &b) in self.column_sums.iter_mut().zip(&self.blurred[r..r + w]) {
                *s += b as u32;
            }
        }
        // Column sums padded by `half` replicated columns each side, so the sliding window needs
        // no clamping.
        let mut padded = vec![0i32; w + 2 * half + 1];
        for y in 0..h {
            if y > 0 {
                let (add, sub) = (row((y + half) as isize), row(y as isize - half as isize - 1));
                for ((s, &a), &b) in self
                    .column_sums
                    .iter_mut()
                    .zip(&self.blurred[add..add + w])
                    .zip(&self.blurred[sub..sub + w])
                {
                    *s = *s + a as u32 - b as u32;
                }
            }
            let sums = &self.column_sums;
            for (i, p) in padded.iter_mut().enumerate() {
                *p = sums[(i as isize - half as isize).clamp(0, w as isize - 1) as usize] as i32;
            }
            let mut window: i32 = padded[..2 * half + 1].iter().sum();
            let base = y * w;
            let blurred = &self.blurred[base..base + w];
            let mask = &mut self.mask[base..base + w];
            for x in 0..w {
                if x > 0 {
                    window += padded[x + 2 * half] - padded[x - 1];
                }
                mask[x] = (blurred[x] as i32 * area + offset >= window) as u8;
            }
        }
    }

    /// Mean of the blurred image over the threshold box around pixel `i` (grey levels).
    fn local_mean(&self, w: usize, h: usize, half: usize, i: usize) -> f64 {
        let (x, y) = ((i % w) as isize, (i / w) as isize);
        let half = half as isize;
        let mut sum = 0u64;
        for yy in y - half..=y + half {
            let r = yy.clamp(0, h as isize - 1) as usize * w;
            for xx in x - half..=x + half {
                sum += self.blurred[r + xx.clamp(0, w as isize - 1) as usize] as u64;
            }
        }
        sum as f64 / ((2 * half + 1) * (2 * half + 1)) as f64 / 256.0
    }

    fn label(&mut self, image: ImageView<'_>, config: &DetectConfig, out: &mut Vec<Detection>) {
        let (w, h) = (image.width, image.height);
        for start in 0..w * h {
            if self.mask[start] != 1 {
                continue;
            }
            self.region.clear();
            self.stack.clear();
            self.stack.push(start as u32);
            self.mask[start] = 2;
            let mut touches_border = false;
            while let Some(i) = self.stack.pop() {
                let i = i as usize;
                self.region.push(i as u32);
                let (x, y) = (i % w, i / w);
                touches_border |= x == 0 || y == 0 || x + 1 == w || y + 1 == h;
                for ny in y.saturating_sub(1)..=(y + 1).min(h - 1) {
                    for nx in x.saturating_sub(1)..=(x + 1).min(w - 1) {
                        let j = ny * w + nx;
                        if self.mask[j] == 1 {
                            self.mask[j] = 2;
                            self.stack.push(j as u32);
                        }
                    }
                }
            }
            if self.region.len() < config.min_area_px
                || self.region.len() > config.max_area_px
                || (touches_border && config.reject_border)
            {
                continue;
            }
            self.region.sort_unstable();
            if config.split_touching && self.region.len() >= 12 {
                self.split_region(image, config, out);
            } else {
                self.emit(image, config, &self.region, out);
            }
        }
    }

    fn weight(&self, image: ImageView<'_>, config: &DetectConfig, i: usize) -> f64 {
        let v = image.pixels[i] as f64;
        match config.centroid_weight {
            CentroidWeight::Intensity => v,
            CentroidWeight::AboveLocalMean => {
                (v - self.local_mean(image.width, image.height, config.box_size_px / 2, i)).max(0.0)
            }
        }
    }

    /// Measures a region, unless it is elongated (overlapping particles): then it is cut in two
    /// by intensity-weighted 2-means along its long axis when splitting is on and both halves come
    /// out round, and dropped otherwise.
    fn emit(&self, image: ImageView<'_>, config: &DetectConfig, pixels: &[u32], out: &mut Vec<Detection>) {
        let w = image.width;
        let elongated = |p: &[u32]| config.max_axis_ratio > 0.0 && p.len() >= 12 && axis_ratio(p, w) > config.max_axis_ratio;
        if !elongated(pixels) {
            out.extend(self.measure(image, config, pixels));
            return;
        }
        if !config.split_touching {
            return;
        }
        let halves = self.two_means(image, config, pixels);
        if halves.iter().all(|h| h.len() >= config.min_area_px && !elongated(h)) {
            for h in &halves {
                out.extend(self.measure(image, config, h).map(|d| Detection {
                    from_overlap: true,
                    ..d
                }));
            }
        }
    }

    /// Splits a region in two along its long axis.
    fn two_means(&self, image: ImageView<'_>, config: &DetectConfig, pixels: &[u32]) -> Vec<Vec<u32>> {
        let w = image.width;
        let at = |i: u32| ((i as usize % w) as f64, (i as usize / w) as f64);
        let (mx, my) = pixels.iter().fold((0.0, 0.0), |(x, y), &i| (x + at(i).0, y + at(i).1));
        let (mx, my) = (mx / pixels.len() as f64, my / pixels.len() as f64);
        // Seed the two centres on the long axis, one standard deviation out.
        let (mut xx, mut yy, mut xy) = (0.0, 0.0, 0.0);
        for &i in pixels {
            let (dx, dy) = (at(i).0 - mx, at(i).1 - my);
            xx += dx * dx;
            yy += dy * dy;
            xy += dx * dy;
        }
        let angle = 0.5 * (2.0 * xy).atan2(xx - yy);
        let spread = ((xx + yy) / pixels.len() as f64).sqrt();
        let (ux, uy) = (angle.cos() * spread, angle.sin() * spread);
        self.k_means(image, config, pixels, vec![(mx - ux, my - uy), (mx + ux, my + uy)])
    }

    /// Intensity-weighted k-means of a region's pixels from the given seeds (a few rounds suffice
    /// for the handful of pixels in a particle image).
    fn k_means(&self, image: ImageView<'_>, config: &DetectConfig, pixels: &[u32], mut centres: Vec<(f64, f64)>) -> Vec<Vec<u32>> {
        let w = image.width;
        let at = |i: u32| ((i as usize % w) as f64, (i as usize / w) as f64);
        let mut parts: Vec<Vec<u32>> = vec![Vec::new(); centres.len()];
        for _ in 0..8 {
            parts.iter_mut().for_each(Vec::clear);
            for &i in pixels {
                let (x, y) = at(i);
                let nearest = centres
                    .iter()
                    .enumerate()
                    .map(|(n, c)| (n, (x - c.0).powi(2) + (y - c.1).powi(2)))
                    .min_by(|a, b| a.1.total_cmp(&b.1))
                    .map_or(0, |(n, _)| n);
                parts[nearest].push(i);
            }
            for (c, part) in centres.iter_mut().zip(&parts) {
                let (mut sw, mut sx, mut sy) = (0.0, 0.0, 0.0);
                for &i in part {
                    let v = self.weight(image, config, i as usize).max(1e-9);
                    sw += v;
                    sx += v * at(i).0;
                    sy += v * at(i).1;
                }
                if sw > 0.0 {
                    *c = (sx / sw, sy / sw);
                }
            }
        }
        parts
    }

    fn measure(&self, image: ImageView<'_>, config: &DetectConfig, pixels: &[u32]) -> Option<Detection> {
        let w = image.width;
        let (mut m00, mut m10, mut m01) = (0.0, 0.0, 0.0);
        for &i in pixels {
            let i = i as usize;
            let v = self.weight(image, config, i);
            m00 += v;
            m10 += v * (i % w) as f64;
            m01 += v * (i / w) as f64;
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
            brightness: image.bilinear(centroid),
            area_px: pixels.len() as u32,
            from_overlap: false,
        })
    }

    /// Splits a region between its separated peaks of the blurred image; a region with one peak
    /// (or peaks joined without a real dip, e.g. a flat-topped disc with noise) stays whole.
    fn split_region(&self, image: ImageView<'_>, config: &DetectConfig, out: &mut Vec<Detection>) {
        let w = image.width;
        let h = image.height;
        let b = &self.blurred;
        let region = &self.region;
        let in_region = |j: usize| region.binary_search(&(j as u32)).is_ok();
        // Peak pixels: not lower than any 8-neighbour inside the region.
        let mut peaks: Vec<usize> = Vec::new();
        let mut floor = u16::MAX;
        for &i in region {
            let i = i as usize;
            floor = floor.min(b[i]);
            let (x, y) = (i % w, i / w);
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
                peaks.push(i);
            }
        }
        // Keep the highest peak of every group whose members are joined without a real dip.
        peaks.sort_by(|&a, &c| b[c].cmp(&b[a]).then(a.cmp(&c)));
        let mut kept: Vec<usize> = Vec::new();
        for &p in &peaks {
            let separate = kept.iter().all(|&k| {
                let lower = (b[p].min(b[k]) - floor) as f64;
                let dip = lowest_on_segment(b, w, p, k) - floor as f64;
                dip < (1.0 - config.split_dip_fraction) * lower
            });
            if separate {
                kept.push(p);
            }
        }
        if kept.len() < 2 {
            self.emit(image, config, region, out);
            return;
        }
        let seeds = kept.iter().map(|&k| ((k % w) as f64, (k / w) as f64)).collect();
        let parts = self.k_means(image, config, region, seeds);
        for part in &parts {
            if part.len() >= config.min_area_px {
                self.emit(image, config, part, out);
            }
        }
    }
}

/// Long over short axis of a region's pixel distribution (from its second central moments).
fn axis_ratio(pixels: &[u32], w: usize) -> f64 {
    let n = pixels.len() as f64;
    let (mut sx, mut sy) = (0.0, 0.0);
    for &i in pixels {
        sx += (i as usize % w) as f64;
        sy += (i as usize / w) as f64;
    }
    let (mx, my) = (sx / n, sy / n);
    let (mut xx, mut yy, mut xy) = (0.0, 0.0, 0.0);
    for &i in pixels {
        let (dx, dy) = ((i as usize % w) as f64 - mx, (i as usize / w) as f64 - my);
        xx += dx * dx;
        yy += dy * dy;
        xy += dx * dy;
    }
    let (mean, diff) = ((xx + yy) / 2.0, ((xx - yy) / 2.0).hypot(xy));
    let (major, minor) = (mean + diff, (mean - diff).max(1e-12));
    (major / minor).sqrt()
}

fn kernel(sample: impl Fn(isize) -> u16) -> u16 {
    sample(-2) + 4 * sample(-1) + 6 * sample(0) + 4 * sample(1) + sample(2)
}

fn lowest_on_segment(b: &[u16], w: usize, from: usize, to: usize) -> f64 {
    let (x0, y0) = ((from % w) as f64, (from / w) as f64);
    let (x1, y1) = ((to % w) as f64, (to / w) as f64);
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
        assert!((d[0].centroid.x - 2500.0 / 700.0).abs() < 1e-9, "{:?}", d[0]);
        assert!((d[0].centroid.y - 1800.0 / 700.0).abs() < 1e-9, "{:?}", d[0]);
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
        // Each part keeps its half of the bridge (the middle column goes to one side), which pulls
        // its centroid inwards by at most 600 * 3.5 / 4120 = 0.51 px.
        assert!((split[0].centroid.x - 5.5).abs() < 0.52 && (split[1].centroid.x - 14.5).abs() < 0.52, "{split:?}");
        assert!((split[0].centroid.y - 5.5).abs() < 1e-9 && (split[1].centroid.y - 5.5).abs() < 1e-9);
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
        assert!(detect(w, &img, &elongated).is_empty(), "merged pair is elongated");
    }

    #[test]
    fn overlapping_discs_are_cut_in_two() {
        let w = 30;
        let mut img = vec![0u8; w * 20];
        for y in 0..20usize {
            for x in 0..w {
                let r1 = ((x as f64 - 11.0).powi(2) + (y as f64 - 10.0).powi(2)).sqrt();
                let r2 = ((x as f64 - 17.0).powi(2) + (y as f64 - 10.0).powi(2)).sqrt();
                img[y * w + x] = (u8::from(r1 < 4.0) + u8::from(r2 < 4.0)) * 100;
            }
        }
        let d = detect(w, &img, &DetectConfig::default());
        assert_eq!(d.len(), 2, "{d:?}");
        assert!(d.iter().all(|d| d.from_overlap));
        let mut xs: Vec<f64> = d.iter().map(|d| d.centroid.x).collect();
        xs.sort_by(f64::total_cmp);
        assert!((xs[0] - 11.0).abs() < 0.8 && (xs[1] - 17.0).abs() < 0.8, "{xs:?}");
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
        assert!(detect(10, &img, &DetectConfig::default()).is_empty(), "clipped particle dropped by default");
    }
}
