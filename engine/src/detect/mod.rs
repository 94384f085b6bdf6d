//! Stage 1: particle detection in one grayscale image (method section 3.1), one module per
//! operation, in the order an image goes through them:
//!
//! 1. `blur`: the 5x5 Gaussian blur; on the way the `background` model (what stands still
//!    in the image, [`DetectConfig::background_rise_per_frame`]) is taken out of each row;
//! 2. `threshold`: the adaptive threshold against the 15x15 box mean minus C;
//! 3. `regions`: the 8-connected regions of the binary image and their moments;
//! 4. `split`: regions of several particles split between their peaks or cut until each part
//!    is round ([`DetectConfig::split_touching`]), and `fit`: the parts fitted together as
//!    `spots` ([`DetectConfig::fit_overlaps`]);
//! 5. `expected`: a region fitted again where the tracks expect more particles than its shape
//!    showed ([`Detector::separate_expected`]).

use crate::config::{check_non_negative, ConfigError};
use serde::{Deserialize, Serialize};

use crate::geometry::PixelPoint;
use crate::ImageView;

mod background;
mod blur;
mod expected;
pub use expected::Parting;
mod fit;
mod regions;
mod split;
mod spots;
mod threshold;

use background::Background;
use blur::Blur;
use regions::Regions;
use threshold::{effective_contrast, Threshold, Tiles};

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
    /// How each pixel weighs in a centroid.
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

impl DetectConfig {
    /// The published method: every region as it comes (no split, no fit, none dropped for its
    /// shape or the border), C alone, no background model.
    pub fn method() -> Self {
        Self {
            split_touching: false,
            fit_overlaps: false,
            separate_expected: false,
            reject_border: false,
            max_axis_ratio: 0.0,
            noise_sigmas: 0.0,
            background_rise_per_frame: 0.0,
            ..Self::default()
        }
    }

    /// Refuses values no run can use, naming the key as the config file spells it.
    pub fn validate(&self) -> Result<(), ConfigError> {
        check_non_negative(
            "detect",
            &[
                ("split_dip_fraction", self.split_dip_fraction),
                ("noise_sigmas", self.noise_sigmas),
                ("background_rise_per_frame", self.background_rise_per_frame),
            ],
        )?;
        let bad = |key, reason| Err(ConfigError::invalid("detect", key, reason));
        if !self.contrast_c.is_finite() || self.contrast_c.abs() > 255.0 {
            return bad(
                "contrast_c",
                "must be a number of grey levels in -255..=255",
            );
        }
        // The summed-area tables are i32; 101 keeps every sum far inside that range.
        let box_size = self.box_size_px;
        if !(3..=101).contains(&box_size) || box_size.is_multiple_of(2) {
            return bad("box_size_px", "must be odd and in 3..=101");
        }
        if self.min_area_px > self.max_area_px {
            return bad("min_area_px", "must not exceed detect.max_area_px");
        }
        Ok(())
    }
}

/// One detected particle image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Detection {
    /// Intensity-weighted centroid, raw image pixels.
    pub centroid: PixelPoint,
    /// Equivalent diameter: the circle with the region's area, pixels.
    pub diameter_px: f64,
    /// Intensity at the centroid (bilinear) above the background model, grey levels.
    pub brightness: f64,
    /// Pixels in the region (or its share of a fitted region).
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
    /// (it explains the pixels and the spots are apart), or, for a spot seeded where a track
    /// expected it, its centre is pinned down by the pixels: centroids within about
    /// 0.1 px. Measured where a track's clear samples do not support a velocity fit on their
    /// own.
    Fitted,
    /// Overlapping, cut in two by 2-means, and no trustworthy spot fit: its centroid may be
    /// pulled towards its neighbour, so good for tracking and not for measuring.
    Cut,
    /// Not seen at all: hidden in this image (behind a neighbour's image, an occluder or the
    /// image edge) while the other image shows it, and placed where its track predicts it
    /// (track-first partial samples). Measured across the other camera's line of sight where
    /// that camera told it apart; along it, only predicted.
    Hidden,
}

/// One camera's detection stage: reusable buffers, so the hot path allocates nothing once warmed
/// up, and the background model, which carries from image to image.
#[derive(Debug, Default)]
pub struct Detector {
    blur: Blur,
    background: Background,
    tiles: Tiles,
    threshold: Threshold,
    regions: Regions,
    /// The contrast constant in use for the current image.
    contrast_c: f64,
}

impl Detector {
    /// A detector with empty buffers and no background learnt yet.
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
        self.detect_tracked(image, config, &[], out);
    }

    /// [`Self::detect`] where tracks expect particles at `tracked` (raw pixels): a region one of
    /// them falls on is split but its parts are not spot-fitted, as the tracks fit the
    /// particles there themselves, with the image shapes they learnt.
    pub fn detect_tracked(
        &mut self,
        image: ImageView<'_>,
        config: &DetectConfig,
        tracked: &[PixelPoint],
        out: &mut Vec<Detection>,
    ) {
        out.clear();
        let (w, h) = (image.width, image.height);
        if w == 0 || h == 0 {
            return;
        }
        let rise = self
            .background
            .prepare(w * h, config.background_rise_per_frame);
        self.blur
            .run(image, &mut self.background, rise, &mut self.tiles);
        self.contrast_c = effective_contrast(config, image);
        self.threshold.run(
            &self.blur.blurred,
            (w, h),
            &mut self.tiles,
            config.box_size_px,
            self.contrast_c,
            &mut self.regions.mask,
        );
        self.regions.mark_tracked(image, tracked);
        self.regions
            .label(image, config, &self.blur.blurred, &self.background, out);
        self.regions.unmark_tracked();
        self.background.commit(rise);
    }

    /// The contrast constant the last image was thresholded with: `contrast_c`, or lower where
    /// the image's noise called for it (`noise_sigmas`).
    pub fn last_contrast_c(&self) -> f64 {
        self.contrast_c
    }
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
    fn a_region_a_track_expects_a_particle_on_is_left_to_the_tracks_fit() {
        let w = 32;
        let truth = [(12.3, 10.4), (16.9, 11.8)];
        let img = gaussian_spots(w, 22, 1.5, &truth);
        let image = ImageView::new(w, 22, &img).expect("sized");
        let config = DetectConfig::default();
        let mut out = Vec::new();
        let elsewhere = [PixelPoint { x: 28.0, y: 3.0 }];
        let on_it = [PixelPoint { x: 12.0, y: 10.0 }];
        Detector::new().detect_tracked(image, &config, &elsewhere, &mut out);
        assert!(
            out.iter().all(|d| d.separation == Separation::Fitted),
            "{out:?}"
        );
        Detector::new().detect_tracked(image, &config, &on_it, &mut out);
        assert_eq!(out.len(), 2, "{out:?}");
        assert!(
            out.iter().all(|d| d.separation == Separation::Cut),
            "{out:?}"
        );
        // The marks are the image's only: the next image fits the region again.
        let mut detector = Detector::new();
        detector.detect_tracked(image, &config, &on_it, &mut out);
        detector.detect(image, &config, &mut out);
        assert!(
            out.iter().all(|d| d.separation == Separation::Fitted),
            "{out:?}"
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
        detector.separate_expected(image, &config, &expected, None, &mut out);
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
