//! The 8-connected regions of the binary image and what a region's pixels measure.
//!
//! The regions are exactly the areas enclosed by the outer borders that Suzuki & Abe (1985)
//! border following returns (the method's `findContours`), so labelling them directly gives the
//! same particles without tracing contours. Per region: intensity-weighted moment centroid
//! (method eqs. 2-3), brightness at the centroid, equivalent diameter.

use super::background::Background;
use super::{split, CentroidWeight, DetectConfig, Detection, Separation};
use crate::geometry::PixelPoint;
use crate::ImageView;

/// A pixel of a region with its coordinates, so nothing downstream divides by the width.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Pixel {
    pub(super) index: u32,
    pub(super) x: u32,
    pub(super) y: u32,
}

/// A region that was measured, and the run of the output its detections fill.
#[derive(Debug, Clone, Copy)]
pub(super) struct ResolvedRegion {
    pub(super) label: u32,
    pub(super) first: usize,
    pub(super) count: usize,
    pub(super) area_px: usize,
}

/// The binary image and its labelling, reused from image to image.
#[derive(Debug, Default)]
pub(super) struct Regions {
    /// 0 background, 1 foreground not yet labelled, 2 labelled.
    pub(super) mask: Vec<u8>,
    /// Region label per labelled pixel; labels keep increasing across calls, so the buffer never
    /// needs clearing (a pixel's stale label from an earlier image never equals a current one).
    pub(super) labels: Vec<u32>,
    next_label: u32,
    stack: Vec<Pixel>,
    /// The pixels of the region walked last.
    pub(super) region: Vec<Pixel>,
    /// The current image's measured regions, in label order, with the detections each gave.
    pub(super) resolved: Vec<ResolvedRegion>,
    /// Per pixel, whether a track expects a particle there in the image being labelled (see
    /// [`Regions::mark_tracked`]); empty until a track has.
    tracked: Vec<bool>,
    /// The pixels marked in `tracked`, to clear them again.
    tracked_at: Vec<usize>,
}

/// What measuring a region reads: the image, the blurred image (scaled by 256), the background
/// model, and which pixels belong to which region.
#[derive(Clone, Copy)]
pub(super) struct Context<'a> {
    pub(super) image: ImageView<'a>,
    pub(super) config: &'a DetectConfig,
    pub(super) blurred: &'a [u16],
    pub(super) background: &'a Background,
    pub(super) mask: &'a [u8],
    pub(super) labels: &'a [u32],
    /// Per pixel, whether a track expects a particle there (empty: none does).
    pub(super) tracked: &'a [bool],
}

impl Context<'_> {
    /// Whether a track expects a particle on one of `region`'s pixels.
    pub(super) fn is_tracked(&self, region: &[Pixel]) -> bool {
        !self.tracked.is_empty()
            && region
                .iter()
                .any(|p| self.tracked.get(p.index as usize) == Some(&true))
    }
}

impl Regions {
    /// Labels the foreground of `mask` region by region and measures each region of an
    /// acceptable size (and off the border, where asked) into `out`.
    pub(super) fn label(
        &mut self,
        image: ImageView<'_>,
        config: &DetectConfig,
        blurred: &[u16],
        background: &Background,
        out: &mut Vec<Detection>,
    ) {
        let (w, h) = (image.width, image.height);
        self.start_labels(w * h);
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
            if !self.is_candidate(w, h, config) {
                continue;
            }
            let first = out.len();
            let context = Context {
                image,
                config,
                blurred,
                background,
                mask: &self.mask,
                labels: &self.labels,
                tracked: &self.tracked,
            };
            split::resolve(&context, &self.region, label, out);
            self.resolved.push(ResolvedRegion {
                label,
                first,
                count: out.len() - first,
                area_px: self.region.len(),
            });
        }
    }

    /// Marks the pixels nearest `tracked` (raw pixels; those off the image are left out) for
    /// this image's labelling.
    pub(super) fn mark_tracked(&mut self, image: ImageView<'_>, tracked: &[PixelPoint]) {
        if tracked.is_empty() {
            return;
        }
        self.tracked.resize(image.width * image.height, false);
        for j in tracked.iter().filter_map(|&p| pixel_on(image, p)) {
            self.tracked[j] = true;
            self.tracked_at.push(j);
        }
    }

    /// Clears what [`Regions::mark_tracked`] marked, leaving no track for the next image.
    pub(super) fn unmark_tracked(&mut self) {
        for j in self.tracked_at.drain(..) {
            self.tracked[j] = false;
        }
    }

    /// Readies the labels for an image of `pixels` pixels. An image has at most one region per
    /// pixel, so starting it with room for that many labels means none wraps within it.
    fn start_labels(&mut self, pixels: usize) {
        self.labels.resize(pixels, 0);
        let most_regions = u32::try_from(pixels).unwrap_or(u32::MAX);
        if self.next_label > u32::MAX - most_regions {
            self.labels.fill(0);
            self.next_label = 0;
        }
        self.resolved.clear();
    }

    /// Whether the region walked last may be a particle: its area in range, and off the image
    /// border where `reject_border` asks (part of such a particle is outside the image).
    fn is_candidate(&self, w: usize, h: usize, config: &DetectConfig) -> bool {
        let touches_border = self.region.iter().any(|p| {
            let (x, y) = (p.x as usize, p.y as usize);
            x == 0 || y == 0 || x + 1 == w || y + 1 == h
        });
        !(self.region.len() < config.min_area_px
            || self.region.len() > config.max_area_px
            || (touches_border && config.reject_border))
    }

    /// Collects the pixels of the current image's region `label` that holds pixel `from` into
    /// `self.region`.
    pub(super) fn gather_region(&mut self, image: ImageView<'_>, label: u32, from: usize) {
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
}

impl Context<'_> {
    /// How pixel `i` weighs in its region's centroid ([`CentroidWeight`]), above the background.
    #[inline]
    pub(super) fn weight(&self, i: usize) -> f64 {
        let v = (self.image.pixels[i] as f64 - self.background.at(i)).max(0.0);
        match self.config.centroid_weight {
            CentroidWeight::Intensity => v,
            CentroidWeight::AboveLocalMean => (v - self.local_mean(i)).max(0.0),
        }
    }

    /// Mean of the blurred image over the threshold box around pixel `i` (grey levels), borders
    /// replicated.
    fn local_mean(&self, i: usize) -> f64 {
        let (w, h) = (self.image.width, self.image.height);
        let half = (self.config.box_size_px / 2) as isize;
        let (x, y) = ((i % w) as isize, (i / w) as isize);
        let mut sum = 0i64;
        for yy in y - half..=y + half {
            let r = yy.clamp(0, h as isize - 1) as usize * w;
            for xx in x - half..=x + half {
                sum += self.blurred[r + xx.clamp(0, w as isize - 1) as usize] as i64;
            }
        }
        sum as f64 / ((2 * half + 1) * (2 * half + 1)) as f64 / 256.0
    }

    /// Raw intensity above the background model at a centroid (bilinear, clamped to the image).
    pub(super) fn brightness_at(&self, centroid: PixelPoint) -> f64 {
        let below = self.background.at(nearest_pixel(self.image, centroid));
        (self.image.bilinear(centroid) - below).max(0.0)
    }

    /// The detection a set of pixels makes: weighted moment centroid, equivalent diameter (the
    /// circle of the same area), brightness at the centroid. `None` when no pixel weighs.
    pub(super) fn measure(&self, pixels: &[Pixel]) -> Option<Detection> {
        let (mut m00, mut m10, mut m01) = (0.0, 0.0, 0.0);
        for p in pixels {
            let v = self.weight(p.index as usize);
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
            brightness: self.brightness_at(centroid),
            area_px: pixels.len() as u32,
            separation: Separation::Clear,
        })
    }
}

/// The index of the pixel nearest `at`, where `at` lies on the image (`None` off it).
pub(super) fn pixel_on(image: ImageView<'_>, at: PixelPoint) -> Option<usize> {
    let (w, h) = (image.width as f64, image.height as f64);
    (at.x >= 0.0 && at.y >= 0.0 && at.x <= w - 1.0 && at.y <= h - 1.0)
        .then(|| nearest_pixel(image, at))
}

/// Index of the pixel nearest a point of the image (clamped to the image).
pub(super) fn nearest_pixel(image: ImageView<'_>, at: PixelPoint) -> usize {
    (at.y.round() as usize).min(image.height - 1) * image.width
        + (at.x.round() as usize).min(image.width - 1)
}

/// The next pixel at or after `from` marked 1 (foreground, unlabelled). Skips eight pixels at a
/// time, read as one word: most of an image is background (0) or labelled (2), neither of which
/// has the low bit set.
fn next_unlabelled(mask: &[u8], from: usize) -> Option<usize> {
    const LOW_BITS: u64 = 0x0101_0101_0101_0101;
    let first_in = |pixels: &[u8], at: usize| pixels.iter().position(|&m| m == 1).map(|p| at + p);
    let mut words = mask.get(from..)?.chunks_exact(8);
    let mut at = from;
    for word in words.by_ref() {
        let bytes: [u8; 8] = word.try_into().unwrap_or_default();
        if u64::from_ne_bytes(bytes) & LOW_BITS != 0 {
            return first_in(word, at);
        }
        at += 8;
    }
    first_in(words.remainder(), at)
}

/// Centroid and second central moments of a region's pixel positions (unweighted: its shape).
pub(super) struct Moments {
    pub(super) mean_x: f64,
    pub(super) mean_y: f64,
    pub(super) xx: f64,
    pub(super) yy: f64,
    pub(super) xy: f64,
}

impl Moments {
    pub(super) fn of(pixels: &[Pixel]) -> Self {
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

    /// Long over short axis of the pixel distribution.
    pub(super) fn axis_ratio(&self) -> f64 {
        let (mean, diff) = (
            (self.xx + self.yy) / 2.0,
            ((self.xx - self.yy) / 2.0).hypot(self.xy),
        );
        let (major, minor) = (mean + diff, (mean - diff).max(1e-12));
        (major / minor).sqrt()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_next_unlabelled_pixel_is_found_from_any_start() {
        // Background, labelled pixels and unlabelled ones, in and across words and in the
        // tail shorter than a word.
        let mut mask = vec![0u8; 45];
        for i in [3, 9, 10, 17, 30, 43] {
            mask[i] = 2;
        }
        for i in [5, 16, 31, 44] {
            mask[i] = 1;
        }
        for from in 0..=mask.len() + 1 {
            let expected = (from..mask.len()).find(|&i| mask[i] == 1);
            assert_eq!(next_unlabelled(&mask, from), expected, "from {from}");
        }
    }
}
