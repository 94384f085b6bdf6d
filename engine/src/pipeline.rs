//! The [`Pipeline`]: owns every stage's state and turns one [`StereoFrame`] into a [`FrameOutput`].
//!
//! Offline processing and the live server drive this same type, so both give identical results
//! for identical frames. Nothing in here reads a clock: time comes from frame timestamps.

use std::collections::{BTreeMap, VecDeque};

use nalgebra::{Isometry3, Point3, Vector3};
use serde::{Deserialize, Serialize};

use crate::detect::{DetectConfig, Detection, Detector, Separation};
use crate::kinematics::{
    fit_adaptive, fit_line, fit_quadratic, neighbour_outliers, FitChoice, NeighbourTest,
    QuadraticWindow,
};
use crate::kinematics::{FitError, ScenePrior};
use crate::spatial::{median, PointGrid, GRID_CELL_PX};
use crate::link::{CameraLinker, CostScale, Feature, LinkConfig, LinkedFeature};
use crate::stereo::{match_stereo, DepthLearner, PairHistory, StereoConfig, StereoSearch};
use crate::{ImageView, StereoFrame};
use crate::geometry::{CalibrationError, PixelPoint, RectPoint, Rectification, StereoRig};

/// Velocity estimation parameters.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct VelocityConfig {
    /// M: frames on each side of the centre in the moving least-squares window (method: 5 on
    /// synthetic data, 2 for the fast wind-tunnel case).
    pub half_window_frames: usize,
    /// Frames each side of the window may lack (method: 0, every frame seen). 1 keeps vectors
    /// for particles hidden for a frame or just appearing, at a small cost in precision.
    pub max_missing_per_side: usize,
    /// Reject a vector whose track does not follow a smooth path: RMS fit residual above
    /// `max_residual_ratio` times the depth noise expected from `disparity_sigma_px`, plus
    /// `residual_floor_m`. A wrong stereo pair or a track that swapped particles jumps in depth.
    /// 0 disables the check (the method).
    pub max_residual_ratio: f64,
    /// Disparity noise assumed by the residual check, pixels.
    pub disparity_sigma_px: f64,
    /// Residual always allowed, metres (covers real accelerations over the window).
    pub residual_floor_m: f64,
    /// Choose each vector's fit from its track (see `kinematics::fit_adaptive`): per component a
    /// quadratic over a window of 2..=M frames each side, or a cubic over the widest, whichever
    /// the track's own residuals predict to be most accurate. Off: the method's quadratic over
    /// +-M.
    pub adaptive_fit: bool,
    /// A window narrower than +-M is allowed (down to +-2) when the particle crosses at least
    /// this many pixels within it: precision then comes from the distance travelled, not the
    /// frame count, and a fast particle that is in view for only a few frames still gets
    /// vectors. 0: always +-M (with `max_missing_per_side`).
    pub min_window_travel_px: f64,
    /// With `adaptive_fit`, a straight line from this many frames before the centre to M after
    /// it joins the candidate fits, chosen where the track's own acceleration, lost in its
    /// noise, predicts it to be the most accurate: slow or uniform flow, where a centred window
    /// sees mostly depth noise (creeping flow w error 9.3 % -> see README). No extra latency:
    /// the window still ends M frames after the centre. 0 (the method), or at most M leaves it
    /// out.
    pub line_past_frames: usize,
    /// Each frame's vectors (centred, and causal among themselves) are compared with their
    /// `outlier_neighbours` nearest (in space) and a vector is dropped when a component differs
    /// from the neighbours' median by more than `outlier_threshold` times their median
    /// deviation plus `outlier_noise_fraction` of their median speed, where the neighbours
    /// agree in every component to within `outlier_coherence` of their speed (universal outlier detection, Westerweel & Scarano
    /// 2005; `kinematics::neighbour_outliers`). Catches what each track's own smoothness cannot:
    /// a wrong stereo pair or a swapped particle that moves smoothly, but not with the flow.
    /// 0: off (the method).
    pub outlier_neighbours: usize,
    pub outlier_threshold: f64,
    pub outlier_noise_fraction: f64,
    pub outlier_coherence: f64,
}

impl Default for VelocityConfig {
    fn default() -> Self {
        Self {
            half_window_frames: 5,
            max_missing_per_side: 1,
            max_residual_ratio: 4.0,
            disparity_sigma_px: 0.1,
            residual_floor_m: 0.001,
            adaptive_fit: true,
            min_window_travel_px: 60.0,
            line_past_frames: 15,
            outlier_neighbours: 8,
            outlier_threshold: 4.0,
            outlier_noise_fraction: 0.02,
            outlier_coherence: 0.05,
        }
    }
}

/// The smallest disparity at which a particle's depth counts as measured, pixels: half a
/// pixel of error then moves it by a quarter. Bounds the measurement volume where no depth
/// range is set or learnt (a rig's views overlap out to infinity).
pub const MIN_MEASURED_DISPARITY_PX: f64 = 2.0;

/// Every parameter of the pipeline; the TOML config file has one table per stage.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PipelineConfig {
    pub detect: DetectConfig,
    pub link: LinkConfig,
    pub stereo: StereoConfig,
    pub velocity: VelocityConfig,
}

impl PipelineConfig {
    /// The published method with none of mrptv's improvements: per-particle choices, stereo
    /// search ranges as image fractions (K = 0.25, S = 0.01), no track memory in stereo, no
    /// neighbour prediction, no touching-particle split, no rejection.
    pub fn method() -> Self {
        use crate::spatial::Assignment;
        let mut c = Self::default();
        c.detect.split_touching = false;
        c.detect.fit_overlaps = false;
        c.detect.separate_expected = false;
        c.detect.reject_border = false;
        c.detect.max_axis_ratio = 0.0;
        c.link.assignment = Assignment::PerParticle;
        c.link.predict_new_from_neighbours = false;
        c.link.max_gap_frames = 0;
        c.link.rejoin_frames = 0;
        c.velocity.max_missing_per_side = 0;
        c.stereo.assignment = Assignment::PerParticle;
        c.stereo.pair_memory = 0.0;
        c.stereo.weight_row = 1.0;
        c.stereo.disparity_range_fraction = Some(0.25);
        c.stereo.epipolar_band_fraction = Some(0.01);
        c.stereo.learn_depth_range = false;
        c.velocity.max_residual_ratio = 0.0;
        c.velocity.adaptive_fit = false;
        c.velocity.min_window_travel_px = 0.0;
        c.velocity.line_past_frames = 0;
        c.velocity.outlier_neighbours = 0;
        c.link.max_displacement_px = 0.0;
        c.link.fixture_frames = 0;
        c.detect.noise_sigmas = 0.0;
        c.detect.background_rise_per_frame = 0.0;
        c
    }

    pub fn validate(&self) -> Result<(), PipelineError> {
        let bad =
            |field: &str, reason: &str| Err(PipelineError::Config(format!("{field}: {reason}")));
        let finite_non_negative = [
            ("detect.split_dip_fraction", self.detect.split_dip_fraction),
            ("link.box_half_side_px", self.link.box_half_side_px),
            ("link.weight_diameter", self.link.weight_diameter),
            ("link.weight_brightness", self.link.weight_brightness),
            ("link.weight_x", self.link.weight_x),
            (
                "stereo.disparity_range_fraction",
                self.stereo.disparity_range_fraction.unwrap_or(0.0),
            ),
            (
                "stereo.epipolar_band_fraction",
                self.stereo.epipolar_band_fraction.unwrap_or(0.0),
            ),
            ("stereo.weight_diameter", self.stereo.weight_diameter),
            ("stereo.weight_speed", self.stereo.weight_speed),
            ("stereo.weight_brightness", self.stereo.weight_brightness),
            ("stereo.pair_memory", self.stereo.pair_memory),
            ("stereo.weight_row", self.stereo.weight_row),
            (
                "velocity.max_residual_ratio",
                self.velocity.max_residual_ratio,
            ),
            (
                "velocity.disparity_sigma_px",
                self.velocity.disparity_sigma_px,
            ),
            ("velocity.residual_floor_m", self.velocity.residual_floor_m),
            (
                "velocity.min_window_travel_px",
                self.velocity.min_window_travel_px,
            ),
            ("link.max_displacement_px", self.link.max_displacement_px),
            ("link.rejoin_tolerance_px", self.link.rejoin_tolerance_px),
            (
                "link.rejoin_tolerance_sigmas",
                self.link.rejoin_tolerance_sigmas,
            ),
            (
                "velocity.outlier_threshold",
                self.velocity.outlier_threshold,
            ),
            (
                "velocity.outlier_noise_fraction",
                self.velocity.outlier_noise_fraction,
            ),
            (
                "velocity.outlier_coherence",
                self.velocity.outlier_coherence,
            ),
            ("detect.noise_sigmas", self.detect.noise_sigmas),
            (
                "detect.background_rise_per_frame",
                self.detect.background_rise_per_frame,
            ),
        ];
        for (field, v) in finite_non_negative {
            if !v.is_finite() || v < 0.0 {
                return bad(field, "must be a finite number >= 0");
            }
        }
        if !self.detect.contrast_c.is_finite() || self.detect.contrast_c.abs() > 255.0 {
            return bad(
                "detect.contrast_c",
                "must be a number of grey levels in -255..=255",
            );
        }
        // The summed-area tables are i32; 101 keeps every sum far inside that range.
        let box_size = self.detect.box_size_px;
        if !(3..=101).contains(&box_size) || box_size.is_multiple_of(2) {
            return bad("detect.box_size_px", "must be odd and in 3..=101");
        }
        if self.detect.min_area_px > self.detect.max_area_px {
            return bad("detect.min_area_px", "must not exceed detect.max_area_px");
        }
        if !(self.stereo.epipolar_band_px.is_finite() && self.stereo.epipolar_band_px > 0.0) {
            return bad(
                "stereo.epipolar_band_px",
                "must be a finite number of pixels > 0",
            );
        }
        if let Some([near_m, far_m]) = self.stereo.depth_range_m {
            if !(near_m.is_finite() && near_m > 0.0 && far_m > near_m) {
                return bad(
                    "stereo.depth_range_m",
                    "must be [near, far] metres with 0 < near < far (far may be inf)",
                );
            }
        }
        if self.stereo.pair_memory >= 1.0 {
            return bad(
                "stereo.pair_memory",
                "must be below 1 (1 would never update)",
            );
        }
        // M frames of delay: 100 is over 3 s at 30 Hz, far beyond any useful window, and keeps
        // a client-sent value from overflowing the frame arithmetic or the track memory.
        if !(1..=100).contains(&self.velocity.half_window_frames) {
            return bad("velocity.half_window_frames", "must be in 1..=100");
        }
        if self.velocity.line_past_frames > 300 {
            return bad("velocity.line_past_frames", "must be at most 300");
        }
        if self.velocity.max_missing_per_side >= self.velocity.half_window_frames {
            return bad(
                "velocity.max_missing_per_side",
                "must be below velocity.half_window_frames (each side needs a sample)",
            );
        }
        Ok(())
    }
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PipelineError {
    #[error("calibration: {0}")]
    Calibration(#[from] CalibrationError),
    #[error("config: {0}")]
    Config(String),
    #[error("frame {index}: {camera} image is {width}x{height}, calibration says {expected_width}x{expected_height}")]
    ImageSize {
        index: u64,
        camera: &'static str,
        width: usize,
        height: usize,
        expected_width: u32,
        expected_height: u32,
    },
    #[error("frame {index}: timestamp {t_s} s is not finite or not after the previous frame's {previous_s} s")]
    Timestamp {
        index: u64,
        t_s: f64,
        previous_s: f64,
    },
}

/// A particle matched in both cameras this frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MatchedPoint {
    /// The 3D track this point belongs to.
    pub track_id: u64,
    pub point_in_world: Point3<f64>,
    pub left_px: PixelPoint,
    pub right_px: PixelPoint,
    pub depth_m: f64,
}

/// A velocity estimate for one track at one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VelocityVector {
    pub frame_index: u64,
    pub t_s: f64,
    pub track_id: u64,
    /// Moving-least-squares smoothed position, world frame, metres.
    pub position_in_world: Point3<f64>,
    /// World frame, metres per second (head motion removed when poses are given).
    pub velocity_in_world: Vector3<f64>,
    pub rms_residual_m: f64,
    /// 1-sigma error of each velocity component, metres per second: centroid noise carried
    /// through triangulation and the velocity fit, plus the bias the fit expects from the
    /// path's curvature (`Pipeline` explains the noise model).
    pub velocity_sigma: Vector3<f64>,
    /// 1-sigma error of each position component, metres.
    pub position_sigma: Vector3<f64>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct FrameStats {
    pub detections_left: usize,
    pub detections_right: usize,
    pub matches: usize,
    pub tracks: usize,
    pub vectors: usize,
    pub causal_vectors: usize,
    /// Centred vectors dropped by the smoothness check.
    pub rejected: usize,
    /// Centred vectors dropped for straying from their neighbours (`velocity.outlier_neighbours`).
    pub outliers: usize,
    /// Vectors (centred and causal) dropped as no measurement: outside the measurement volume or
    /// faster than a tracked particle can move (`Pipeline::is_plausible`).
    pub implausible: usize,
    /// Features that continue a track from an earlier frame, per camera.
    pub linked_left: usize,
    pub linked_right: usize,
    /// Stereo pairs that passed the hard filter, and left features with at least one.
    pub stereo_candidates: usize,
    pub left_with_candidates: usize,
    /// Velocity components (three per vector) whose fit the data chose over the method's
    /// quadratic on +-M: a quadratic on a narrower window, or a cubic.
    pub fit_components_narrower: usize,
    pub fit_components_cubic: usize,
    /// Velocity components fitted with a line reaching `line_past_frames` back.
    pub fit_components_line: usize,
    /// New stereo pairs that continued a broken 3D track (`link.rejoin_frames`).
    pub rejoined: usize,
    /// Detections (both cameras) taken for fixtures of the room or sensor and not matched.
    pub fixtures: usize,
    /// Images (0 to 2) thresholded above `contrast_c` because of their noise.
    pub noisy_images: usize,
    /// Frames (0 or 1) matched in the disparity range learnt from the tracks
    /// (`stereo.learn_depth_range`) rather than the full search.
    pub learnt_search: usize,
}

/// Summing frames' statistics gives a run's (`tracks` then counts track-frames).
impl std::ops::AddAssign<&FrameStats> for FrameStats {
    fn add_assign(&mut self, s: &FrameStats) {
        self.detections_left += s.detections_left;
        self.detections_right += s.detections_right;
        self.matches += s.matches;
        self.tracks += s.tracks;
        self.vectors += s.vectors;
        self.causal_vectors += s.causal_vectors;
        self.rejected += s.rejected;
        self.outliers += s.outliers;
        self.implausible += s.implausible;
        self.linked_left += s.linked_left;
        self.linked_right += s.linked_right;
        self.stereo_candidates += s.stereo_candidates;
        self.left_with_candidates += s.left_with_candidates;
        self.fit_components_narrower += s.fit_components_narrower;
        self.fit_components_cubic += s.fit_components_cubic;
        self.fit_components_line += s.fit_components_line;
        self.rejoined += s.rejoined;
        self.fixtures += s.fixtures;
        self.noisy_images += s.noisy_images;
        self.learnt_search += s.learnt_search;
    }
}

/// A frame as the pipeline saw it: its index, sensor time, and whether it came with a pose
/// (its points are then in the world frame, else in the rig frame).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameRef {
    pub index: u64,
    pub t_s: f64,
    pub posed: bool,
}

/// What one frame produced.
///
/// Two velocity estimates, for two uses:
/// - `causal_vectors` describe *this* frame: a line fitted to the track's last `2M + 1` frames,
///   evaluated at the newest one. No latency; a little noisier than the centred estimate and
///   biased by acceleration; for live display.
/// - `vectors` are the method's centred estimates for the frame `M` frames back
///   (`centred_frame`): the window needs `M` frames after the one it describes. These are the
///   measurement (`tracks.csv`).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct FrameOutput {
    pub frame_index: u64,
    pub t_s: f64,
    pub detections_left: Vec<Detection>,
    pub detections_right: Vec<Detection>,
    pub points: Vec<MatchedPoint>,
    pub causal_vectors: Vec<VelocityVector>,
    /// The frame `vectors` describe; `None` until `M` frames have followed the first one.
    pub centred_frame: Option<FrameRef>,
    pub vectors: Vec<VelocityVector>,
    pub stats: FrameStats,
}

#[derive(Debug, Clone)]
struct Sample {
    /// Position in the sequence of pushed frames (frame indices may skip).
    seq: u64,
    frame_index: u64,
    t_s: f64,
    point_in_world: Point3<f64>,
    depth_m: f64,
    /// The less exact of the two cameras' separations: what the sample is good for.
    separation: Separation,
    /// Where the left camera saw it, rectified: how far the particle moves in the image.
    left_rect: crate::geometry::RectPoint,
    /// The left camera's centre when it did: the line of sight, along which noise is largest.
    camera_in_world: Point3<f64>,
}

impl Sample {
    /// An offset from this sample split along the left camera's line of sight (signed, where
    /// depth noise is largest) and across it (squared length, where centroid noise is).
    fn along_and_across_sq(&self, offset: &Vector3<f64>) -> (f64, f64) {
        let sight = (self.point_in_world - self.camera_in_world)
            .try_normalize(1e-12)
            .unwrap_or_else(Vector3::z);
        let along = offset.dot(&sight);
        (along, (offset.norm_squared() - along * along).max(0.0))
    }
}

/// A centred vector, the fit chosen per component (adaptive fits), and what its window says
/// about the scene (`ScenePool`).
struct Centred {
    vector: VelocityVector,
    choice: Option<[FitChoice; 3]>,
    noise_ratio: Option<f64>,
    /// Its window's cubic term and that estimate's variance, for the scene's pool.
    cubic_term: Option<(Vector3<f64>, Vector3<f64>)>,
}

/// A stereo pair that no live 3D track continued: a new track, unless it rejoins an orphan.
struct Birth {
    left_track: u64,
    right_track: u64,
    sample: Sample,
    point: MatchedPoint,
}

/// Where a 3D track without a pair this frame came from, so it can go back if no new pair
/// rejoins it.
#[derive(Debug, Clone, Copy)]
enum Orphan {
    /// Still live under this left track id (coasting through a gap).
    Coasting(u64),
    /// Its left track (this id) paired with a new partner this frame.
    Replaced(u64),
    /// Already retired.
    Retired,
}

#[derive(Debug, Clone)]
struct Track3d {
    id: u64,
    right_track: u64,
    samples: VecDeque<Sample>,
}

pub struct Pipeline {
    config: PipelineConfig,
    rig: StereoRig,
    rectification: Rectification,
    left: Camera,
    right: Camera,
    stereo_search: StereoSearch,
    /// Present while the stereo search may be narrowed to where the tracks are.
    depth_learner: Option<DepthLearner>,
    pair_history: PairHistory,
    /// Live 3D tracks keyed by their left track id.
    tracks: BTreeMap<u64, Track3d>,
    /// Ended tracks whose last samples may still be the centre of a vector.
    retired: Vec<Track3d>,
    next_track_id: u64,
    previous_t_s: Option<f64>,
    /// Frames pushed so far.
    seq: u64,
    /// The last `M + 1` frames pushed, newest at the back.
    recent_frames: VecDeque<FrameRef>,
    scene_pool: ScenePool,
}

/// What the scene's tracks have shown so far, for judging any one window: the typical
/// centroid noise, learnt from the tracks' own fit residuals as a disparity noise variance
/// (pixels squared), and how large the paths' cubic terms typically are.
///
/// Each vector's uncertainty rests on its window's residuals, which are few (7 degrees of
/// freedom for 11 samples): alone, their luck would make some sigmas far too small. Pooled with
/// what the scene's other tracks show (scaled to this particle's depth and line of sight by the
/// triangulation's geometry), the estimate steadies while a particle noisier than the rest
/// still shows it. Likewise a window's cubic term, estimated from few samples, is weighed
/// against the spread the scene's windows show (see `FitError::sigmas`).
#[derive(Debug, Clone, Default)]
struct ScenePool {
    /// Recent windows' noise per unit disparity variance (see `Pipeline::noise_unit`).
    noise_ratios: VecDeque<f64>,
    /// Recent windows' cubic terms squared and their estimates' variances, per component.
    cubic_terms: VecDeque<(Vector3<f64>, Vector3<f64>)>,
    /// What the windows above say, worked out once a frame (`refresh`): every vector of a
    /// frame is judged by the same pool.
    noise_variance: Option<f64>,
    cubic_term_spread: [Option<f64>; 3],
}

impl ScenePool {
    const CAPACITY: usize = 511;
    /// Windows needed before the pool is trusted.
    const MIN_WINDOWS: usize = 16;
    /// Degrees of freedom the pooled estimate is worth against a window's own.
    const WEIGHT_DOF: f64 = 10.0;

    fn push<T>(queue: &mut VecDeque<T>, item: T) {
        if queue.len() == Self::CAPACITY {
            queue.pop_front();
        }
        queue.push_back(item);
    }

    fn add_noise(&mut self, ratio: f64) {
        if ratio.is_finite() && ratio > 0.0 {
            Self::push(&mut self.noise_ratios, ratio);
        }
    }

    fn add_cubic_term(&mut self, term: Vector3<f64>, variance: Vector3<f64>) {
        if term.iter().chain(variance.iter()).all(|v| v.is_finite()) {
            Self::push(&mut self.cubic_terms, (term.map(|d| d * d), variance));
        }
    }

    /// Works out what the pool says from the windows added so far.
    ///
    /// The disparity noise variance: the median window, corrected for the median of a
    /// chi-square sitting below its mean (Wilson-Hilferty, at a typical window's 21 degrees
    /// of freedom: three components of 11 samples less a cubic's 4 terms).
    ///
    /// The spread of the paths' cubic terms per component (see `spread_of_terms`), where the
    /// paths plainly curve.
    fn refresh(&mut self) {
        self.noise_variance = (self.noise_ratios.len() >= Self::MIN_WINDOWS).then(|| {
            let mut sorted: Vec<f64> = self.noise_ratios.iter().copied().collect();
            const TYPICAL_DOF: f64 = 21.0;
            median(&mut sorted) / (1.0 - 2.0 / (9.0 * TYPICAL_DOF)).powi(3)
        });
        self.cubic_term_spread = [0, 1, 2].map(|c| {
            if self.cubic_terms.len() < Self::MIN_WINDOWS {
                return None;
            }
            let terms: Vec<(f64, f64)> = self
                .cubic_terms
                .iter()
                .map(|(d2, v)| (d2[c], v[c]))
                .collect();
            let tau2 = spread_of_terms(&terms);
            let mut variances: Vec<f64> = terms.iter().map(|(_, v)| *v).collect();
            // Only a spread beyond what a typical window resolves says the paths curve.
            // Measured (tau2 over the median window's variance): straight flows 0.04-0.4
            // (uniform, moving head, HoloLens-2 raw, flume), turbulence 10-380, vortex
            // 1800-3700. Counting the spread straight paths' noise shows made their median
            // sigmas 1.4-4 times larger (lines reaching into the past take in much of a cubic
            // term); without the spread, turbulence's w lay 86.9 % within 2 sigma, 97.2 % with.
            (tau2 > median(&mut variances)).then_some(tau2)
        });
    }
}

/// The variance `tau2` of a term spread across windows, from each window's estimate squared and
/// that estimate's own variance `v` (`terms`): estimate over `sqrt(tau2 + v)` is a standard
/// normal, whose square has a median of 0.455, so `tau2` is where the median of
/// `estimate^2 / (tau2 + v)` comes to that. A median, so a few sharply turning paths do not
/// set it; per window, so windows of different noise (near and far particles) are each judged
/// against their own. 0 where the estimates are no larger than their noise.
fn spread_of_terms(terms: &[(f64, f64)]) -> f64 {
    const MEDIAN_OF_CHI_SQUARE_1: f64 = 0.455;
    let standardized = |tau2: f64| {
        let mut ratios: Vec<f64> = terms
            .iter()
            .map(|(d2, v)| d2 / (tau2 + v).max(f64::MIN_POSITIVE))
            .collect();
        median(&mut ratios)
    };
    if terms.is_empty() || standardized(0.0) <= MEDIAN_OF_CHI_SQUARE_1 {
        return 0.0;
    }
    let mut high = terms.iter().map(|(d2, _)| *d2).fold(0.0, f64::max);
    while standardized(high) > MEDIAN_OF_CHI_SQUARE_1 && high.is_finite() {
        high *= 2.0;
    }
    // The median ratio falls as tau2 grows: bisect geometrically from twelve decades below
    // to a relative precision of about 1e-6 (below that, tau2 is nothing next to the noise).
    let mut low = high * 1e-12;
    if standardized(low) <= MEDIAN_OF_CHI_SQUARE_1 {
        return 0.0;
    }
    for _ in 0..24 {
        let middle = (low * high).sqrt();
        if standardized(middle) > MEDIAN_OF_CHI_SQUARE_1 {
            low = middle;
        } else {
            high = middle;
        }
    }
    (low * high).sqrt()
}

impl Pipeline {
    pub fn new(rig: StereoRig, config: PipelineConfig) -> Result<Self, PipelineError> {
        config.validate()?;
        let rectification = Rectification::new(&rig)?;
        let stereo_search = StereoSearch::new(&config.stereo, &rectification)
            .map_err(|e| PipelineError::Config(e.to_string()))?;
        let stereo = &config.stereo;
        let depth_learner = (stereo.learn_depth_range
            && stereo.depth_range_m.is_none()
            && stereo.disparity_range_fraction.is_none())
        .then(|| {
            DepthLearner::new(
                stereo_search,
                rectification.focal_px * rectification.baseline_m,
            )
        });
        Ok(Self {
            depth_learner,
            config,
            rig,
            rectification,
            left: Camera::new(),
            right: Camera::new(),
            stereo_search,
            pair_history: PairHistory::new(),
            tracks: BTreeMap::new(),
            retired: Vec::new(),
            next_track_id: 0,
            previous_t_s: None,
            seq: 0,
            recent_frames: VecDeque::new(),
            scene_pool: ScenePool::default(),
        })
    }

    pub fn config(&self) -> &PipelineConfig {
        &self.config
    }

    pub fn rig(&self) -> &StereoRig {
        &self.rig
    }

    pub fn rectification(&self) -> &Rectification {
        &self.rectification
    }

    /// The stereo hard filter this pipeline settled on for its rig and config.
    pub fn stereo_search(&self) -> &StereoSearch {
        &self.stereo_search
    }

    /// The search narrowed to where the tracks are, when `stereo.learn_depth_range` has learnt
    /// one; the next frame is matched in it.
    pub fn learnt_search(&self) -> Option<StereoSearch> {
        self.depth_learner.as_ref().and_then(DepthLearner::search)
    }

    fn check_image(
        &self,
        index: u64,
        camera: &'static str,
        image: &ImageView<'_>,
    ) -> Result<(), PipelineError> {
        if image.width != self.rig.width as usize || image.height != self.rig.height as usize {
            return Err(PipelineError::ImageSize {
                index,
                camera,
                width: image.width,
                height: image.height,
                expected_width: self.rig.width,
                expected_height: self.rig.height,
            });
        }
        Ok(())
    }

    /// Processes one stereo frame. A rejected frame (wrong size, time going backwards) leaves the
    /// pipeline state untouched, so the caller may report it and carry on.
    pub fn push(&mut self, frame: &StereoFrame<'_>) -> Result<FrameOutput, PipelineError> {
        self.check_image(frame.index, "left", &frame.left)?;
        self.check_image(frame.index, "right", &frame.right)?;
        let previous_s = self.previous_t_s.unwrap_or(f64::NEG_INFINITY);
        if !frame.t_s.is_finite() || frame.t_s <= previous_s {
            return Err(PipelineError::Timestamp {
                index: frame.index,
                t_s: frame.t_s,
                previous_s,
            });
        }
        self.previous_t_s = Some(frame.t_s);
        self.seq += 1;
        let seq = self.seq;
        let m = self.config.velocity.half_window_frames;
        self.recent_frames.push_back(FrameRef {
            index: frame.index,
            t_s: frame.t_s,
            posed: frame.world_from_rig.is_some(),
        });
        if self.recent_frames.len() > m + 1 {
            self.recent_frames.pop_front();
        }

        let mut out = FrameOutput {
            frame_index: frame.index,
            t_s: frame.t_s,
            ..Default::default()
        };
        let rect = &self.rectification;
        let scale = CostScale {
            half_width_px: rect.half_width_px,
            half_height_px: rect.half_height_px,
        };
        // The cameras' own stages need nothing from each other: one core each. Their outputs
        // do not depend on which runs first, so results match a single-threaded run exactly.
        let config = &self.config;
        let (left_camera, right_camera) = (&mut self.left, &mut self.right);
        let (detections_left, detections_right) =
            (&mut out.detections_left, &mut out.detections_right);
        let ((left, left_raw), (right, right_raw)) = rayon::join(
            || {
                left_camera.push(
                    frame.left,
                    config,
                    scale,
                    detections_left,
                    |p| rect.left_to_rect(p),
                    |p| rect.rect_to_left(p),
                )
            },
            || {
                right_camera.push(
                    frame.right,
                    config,
                    scale,
                    detections_right,
                    |p| rect.right_to_rect(p),
                    |p| rect.rect_to_right(p),
                )
            },
        );
        out.stats.noisy_images = [&self.left.detector, &self.right.detector]
            .iter()
            .filter(|d| d.last_contrast_c() < self.config.detect.contrast_c)
            .count();
        // Fixtures (features that have not moved for a while) never enter stereo matching: a
        // static light in the room would otherwise become a 3D point with a velocity of zero.
        let moving = |features: &[LinkedFeature]| -> (Vec<LinkedFeature>, Vec<usize>) {
            features
                .iter()
                .enumerate()
                .filter(|(_, f)| !f.fixed)
                .map(|(i, f)| (*f, i))
                .unzip()
        };
        let (moving_left, left_index) = moving(&left);
        let (moving_right, right_index) = moving(&right);
        out.stats.fixtures = (left.len() - moving_left.len()) + (right.len() - moving_right.len());
        let learnt_search = self.learnt_search();
        out.stats.learnt_search = usize::from(learnt_search.is_some());
        let stereo = match_stereo(
            &moving_left,
            &moving_right,
            scale,
            learnt_search.as_ref().unwrap_or(&self.stereo_search),
            &mut self.pair_history,
            &self.config.stereo,
        );
        let pairs: Vec<(usize, usize)> = stereo
            .pairs
            .iter()
            .map(|&(l, r)| (left_index[l], right_index[r]))
            .collect();
        out.stats.stereo_candidates = stereo.candidates;
        out.stats.left_with_candidates = stereo.left_with_candidates;
        out.stats.linked_left = left.iter().filter(|f| f.age > 1).count();
        out.stats.linked_right = right.iter().filter(|f| f.age > 1).count();

        let world_from_rig = frame.world_from_rig.unwrap_or_else(Isometry3::identity);
        let max_gap = u64::from(self.config.link.max_gap_frames);
        let m = m as u64;
        let history = self.history_frames();
        let mut tracks = BTreeMap::new();
        // Pairs that no live 3D track continues, and 3D tracks that no pair continued this
        // frame: the first may rejoin the second.
        let mut births: Vec<Birth> = Vec::new();
        let mut orphans: Vec<(Orphan, Track3d)> = Vec::new();
        for &(li, ri) in &pairs {
            let (l, r): (&LinkedFeature, &LinkedFeature) = (&left[li], &right[ri]);
            let Some(t) = rect.triangulate(l.feature.rect, r.feature.rect) else {
                continue;
            };
            let sample = Sample {
                seq,
                frame_index: frame.index,
                t_s: frame.t_s,
                point_in_world: world_from_rig * t.point_in_rig,
                depth_m: t.depth_m,
                separation: out.detections_left[left_raw[li]]
                    .separation
                    .max(out.detections_right[right_raw[ri]].separation),
                left_rect: l.feature.rect,
                camera_in_world: world_from_rig * Point3::origin(),
            };
            let point = MatchedPoint {
                track_id: 0,
                point_in_world: sample.point_in_world,
                left_px: out.detections_left[left_raw[li]].centroid,
                right_px: out.detections_right[right_raw[ri]].centroid,
                depth_m: t.depth_m,
            };
            match self.tracks.remove(&l.track_id) {
                // Without track-consistent pairing (the method) a left track keeps its 3D track
                // whatever its partner; with it, a new partner means a new particle.
                Some(mut track)
                    if track.right_track == r.track_id || self.config.stereo.pair_memory == 0.0 =>
                {
                    track.right_track = r.track_id;
                    out.points.push(MatchedPoint {
                        track_id: track.id,
                        ..point
                    });
                    Self::push_sample(&mut track, sample, history);
                    tracks.insert(l.track_id, track);
                }
                dropped => {
                    if let Some(track) = dropped {
                        orphans.push((Orphan::Replaced(l.track_id), track));
                    }
                    births.push(Birth {
                        left_track: l.track_id,
                        right_track: r.track_id,
                        sample,
                        point,
                    });
                }
            }
        }
        let rejoin_frames = u64::from(self.config.link.rejoin_frames);
        if rejoin_frames > 0 && !births.is_empty() {
            for (left_track, track) in std::mem::take(&mut self.tracks) {
                if seq - Self::last_seq(&track) <= rejoin_frames + 1 {
                    orphans.push((Orphan::Coasting(left_track), track));
                } else {
                    self.tracks.insert(left_track, track);
                }
            }
            let (recent, old): (Vec<Track3d>, Vec<Track3d>) = std::mem::take(&mut self.retired)
                .into_iter()
                .partition(|t| seq - Self::last_seq(t) <= rejoin_frames + 1);
            self.retired = old;
            orphans.extend(recent.into_iter().map(|t| (Orphan::Retired, t)));
        }
        let rejoined = self.rejoin(&births, &orphans, frame.t_s);
        out.stats.rejoined = rejoined.iter().flatten().count();
        let mut orphans: Vec<Option<(Orphan, Track3d)>> = orphans.into_iter().map(Some).collect();
        for (birth, rejoins) in births.into_iter().zip(rejoined) {
            let Birth {
                left_track,
                right_track,
                sample,
                point,
            } = birth;
            let joined = rejoins.and_then(|(o, before)| {
                let (_, mut track) = orphans[o].take()?;
                // A track of one sample rejoined through the one before it: the three are one
                // particle, so the earlier sample leads the track.
                if let Some((_, earlier)) = before.and_then(|a| orphans[a].take()) {
                    for s in earlier.samples.into_iter().rev() {
                        track.samples.push_front(s);
                    }
                }
                Some(track)
            });
            let mut track = match joined {
                Some(track) => track,
                None => {
                    self.next_track_id += 1;
                    Track3d {
                        id: self.next_track_id,
                        right_track,
                        samples: VecDeque::new(),
                    }
                }
            };
            track.right_track = right_track;
            out.points.push(MatchedPoint {
                track_id: track.id,
                ..point
            });
            Self::push_sample(&mut track, sample, history);
            tracks.insert(left_track, track);
        }
        for (kind, track) in orphans.into_iter().flatten() {
            match kind {
                Orphan::Coasting(left_track) => {
                    self.tracks.insert(left_track, track);
                }
                Orphan::Replaced(_) | Orphan::Retired => self.retired.push(track),
            }
        }
        // A 3D track unseen this frame survives a gap as long as its left track may coast; after
        // that it is retired, and kept M frames for the centred vectors its last samples still
        // give (with a window narrower than M near a track's end).
        for (left_track, track) in std::mem::take(&mut self.tracks) {
            if tracks.contains_key(&left_track) {
                self.retired.push(track);
                continue;
            }
            if seq - Self::last_seq(&track) <= max_gap {
                tracks.insert(left_track, track);
            } else {
                self.retired.push(track);
            }
        }
        self.tracks = tracks;
        if let Some(learner) = &mut self.depth_learner {
            // Tracks seen this frame for CONFIRMED_SAMPLES frames: ghosts rarely last that long.
            const CONFIRMED_SAMPLES: usize = 5;
            let confirmed = self.tracks.values().filter_map(|t| {
                let last = t.samples.back()?;
                (last.seq == seq && t.samples.len() >= CONFIRMED_SAMPLES).then_some(last.depth_m)
            });
            learner.add(seq, confirmed);
        }
        self.retired.retain(|t| seq - Self::last_seq(t) <= m);
        let mut centred = Vec::new();
        for track in self.tracks.values().chain(&self.retired) {
            match self.centred_vector(track, seq) {
                Some(Ok(found)) if self.is_plausible(&found.vector, track) => centred.push(found),
                Some(Ok(_)) => out.stats.implausible += 1,
                Some(Err(())) => out.stats.rejected += 1,
                None => {}
            }
            if let Some(v) = self.causal_vector(track, seq) {
                if self.is_plausible(&v, track) {
                    out.causal_vectors.push(v);
                } else {
                    out.stats.implausible += 1;
                }
            }
        }
        // Live causal vectors are judged too: the holograms should not show what the
        // recording will drop.
        let test = self.neighbour_test();
        let mut causal_outliers = outliers_among(out.causal_vectors.iter(), &test).into_iter();
        out.causal_vectors
            .retain(|_| !causal_outliers.next().unwrap_or(false));
        let outliers = outliers_among(centred.iter().map(|c| &c.vector), &test);
        let mut learnt = false;
        for (found, outlier) in centred.into_iter().zip(outliers) {
            if outlier {
                out.stats.outliers += 1;
                continue;
            }
            // Learnt after the frame's vectors, so a frame's sigmas do not depend on the order
            // of its tracks.
            if let Some(ratio) = found.noise_ratio {
                self.scene_pool.add_noise(ratio);
            }
            if let Some((term, variance)) = found.cubic_term {
                self.scene_pool.add_cubic_term(term, variance);
            }
            learnt = true;
            out.vectors.push(found.vector);
            for c in found.choice.iter().flatten() {
                if c.order == 1 {
                    out.stats.fit_components_line += 1;
                } else if c.order > 2 {
                    out.stats.fit_components_cubic += 1;
                } else if usize::from(c.half_window_frames) < m as usize {
                    out.stats.fit_components_narrower += 1;
                }
            }
        }
        if learnt {
            self.scene_pool.refresh();
        }
        out.centred_frame = (self.recent_frames.len() == m as usize + 1)
            .then(|| self.recent_frames.front().copied())
            .flatten();
        out.stats.detections_left = out.detections_left.len();
        out.stats.detections_right = out.detections_right.len();
        out.stats.matches = out.points.len();
        out.stats.tracks = self.tracks.len();
        out.stats.vectors = out.vectors.len();
        out.stats.causal_vectors = out.causal_vectors.len();
        Ok(out)
    }

    fn neighbour_test(&self) -> NeighbourTest {
        let v = &self.config.velocity;
        NeighbourTest {
            neighbours: v.outlier_neighbours,
            threshold: v.outlier_threshold,
            noise_fraction: v.outlier_noise_fraction,
            coherence: v.outlier_coherence,
        }
    }

    /// Fit residual above which a track is judged rough, for a sample at `depth_m`; `None` when
    /// the check is off.
    fn max_residual_m(&self, depth_m: f64) -> Option<f64> {
        let v = &self.config.velocity;
        (v.max_residual_ratio > 0.0).then(|| {
            v.max_residual_ratio
                * self
                    .rectification
                    .depth_sigma_m(depth_m, v.disparity_sigma_px)
                + v.residual_floor_m
        })
    }

    /// Whether a centred window strays from its quadratic more than noise explains, judged
    /// along the line of sight (depth noise, large) and across it (centroid noise, small)
    /// separately: a track that swapped to a neighbouring particle jumps sideways by a few
    /// pixels, which a single limit set by the depth noise would let through.
    fn is_rough(&self, window: &[&Sample], fit: &QuadraticWindow, depth_m: f64) -> bool {
        let v = &self.config.velocity;
        if v.max_residual_ratio <= 0.0 {
            return false;
        }
        let (mut along_sq, mut across_sq) = (0.0, 0.0);
        for (s, r) in window.iter().zip(fit.residuals()) {
            let (along, across) = s.along_and_across_sq(&r);
            along_sq += along * along;
            across_sq += across;
        }
        let n = window.len() as f64;
        let along_limit = v.max_residual_ratio
            * self
                .rectification
                .depth_sigma_m(depth_m, v.disparity_sigma_px)
            + v.residual_floor_m;
        // Two directions across the line of sight, each with the centroid noise.
        let across_limit =
            v.max_residual_ratio * std::f64::consts::SQRT_2 * depth_m * v.disparity_sigma_px
                / self.rectification.focal_px
                + v.residual_floor_m;
        (along_sq / n).sqrt() > along_limit || (across_sq / n).sqrt() > across_limit
    }

    /// The causal estimate for the newest frame: a straight line through the track's clean
    /// samples of the last `2M + 1` frames, evaluated at the newest. The track must be seen in
    /// the newest frame and have at least `M + 1` clean samples. Measured on the synthetic
    /// scenes, a line beats the quadratic here: an end-point derivative of a quadratic amplifies
    /// noise about six-fold, and young tracks (few samples) were the worst vectors (README,
    /// "Live service"). Rough tracks get no causal vector (not counted as rejected: their
    /// centred check comes later).
    /// Whether a vector can be a measurement at all, whatever the config: a wearer must never
    /// see, and a recording never keep, an arrow tens of metres away at hundreds of m/s.
    /// - Inside the measurement volume: its particle's depth is resolved, seen at a disparity of
    ///   at least `MIN_MEASURED_DISPARITY_PX` (beyond, half a pixel of matching error moves the
    ///   depth by more than a quarter of itself: a match there says little more than "far").
    /// - No faster than a tracked particle can move: over one frame interval its step must
    ///   move the particle across the image, or change its disparity, by at most half the
    ///   image's longer side (a particle must stay in view for the frames its velocity is
    ///   fitted over, and each camera can contribute that much to the disparity).
    fn is_plausible(&self, v: &VelocityVector, track: &Track3d) -> bool {
        let Some(at) = track
            .samples
            .iter()
            .find(|s| s.frame_index == v.frame_index)
        else {
            return true;
        };
        let focal_px = self.rectification.focal_px;
        let focal_baseline = focal_px * self.rectification.baseline_m;
        let depth = at.depth_m;
        if !(depth > 0.0 && depth * MIN_MEASURED_DISPARITY_PX <= focal_baseline) {
            return false;
        }
        let (first, last) = match (track.samples.front(), track.samples.back()) {
            (Some(first), Some(last)) if last.seq > first.seq => (first, last),
            _ => return true,
        };
        let frame_interval_s = (last.t_s - first.t_s) / (last.seq - first.seq) as f64;
        let reach_px = f64::from(self.rig.width.max(self.rig.height)) / 2.0;
        let step = v.velocity_in_world * frame_interval_s;
        let (along, across_sq) = at.along_and_across_sq(&step);
        across_sq.sqrt() * focal_px / depth <= reach_px
            && along.abs() * focal_baseline / (depth * depth) <= 2.0 * reach_px
    }

    fn causal_vector(&self, track: &Track3d, seq: u64) -> Option<VelocityVector> {
        let newest = track.samples.back().filter(|s| s.seq == seq)?;
        let m = self.config.velocity.half_window_frames;
        let recent = |worst: Separation| -> Vec<(f64, Point3<f64>)> {
            track
                .samples
                .iter()
                .filter(|s| s.separation <= worst && seq - s.seq <= 2 * m as u64)
                .map(|s| (s.t_s, s.point_in_world))
                .collect()
        };
        let mut points = recent(Separation::Clear);
        if points.len() < m + 1 {
            points = recent(Separation::Fitted);
        }
        if points.len() < m + 1 {
            return None;
        }
        let fit = fit_line(&points, newest.t_s)?;
        if self
            .max_residual_m(newest.depth_m)
            .is_some_and(|max| fit.rms_residual > max)
        {
            return None;
        }
        let (velocity_sigma, position_sigma) = fit.error.sigmas(self.scene_prior(newest).as_ref());
        Some(VelocityVector {
            frame_index: newest.frame_index,
            t_s: newest.t_s,
            track_id: track.id,
            position_in_world: fit.position,
            velocity_in_world: fit.velocity,
            rms_residual_m: fit.rms_residual,
            velocity_sigma,
            position_sigma,
        })
    }

    /// A sample's noise variance per world component for a unit disparity variance: the
    /// disparity error moves it along the left camera's line of sight by `z^2 / (f b)` per
    /// pixel, and across it each camera's centroid error (disparity's over sqrt 2), averaged
    /// over the two cameras, by `z / (2 f)` per pixel.
    fn noise_unit(&self, sample: &Sample) -> Vector3<f64> {
        let focal_px = self.rectification.focal_px;
        let z = sample.depth_m;
        let along = z * z / (focal_px * self.rectification.baseline_m);
        let across = z / (2.0 * focal_px);
        let sight = (sample.point_in_world - sample.camera_in_world)
            .try_normalize(1e-12)
            .unwrap_or_else(Vector3::z);
        sight.map(|s| along * along * s * s + across * across * (1.0 - s * s))
    }

    /// What the scene's pool says about a window centred on `sample`: its noise scaled to where
    /// `sample` sits (`noise_unit`), for `FitError::sigmas`.
    fn scene_prior(&self, sample: &Sample) -> Option<ScenePrior> {
        self.scene_pool.noise_variance.map(|k| ScenePrior {
            noise_variance: self.noise_unit(sample) * k,
            noise_dof: ScenePool::WEIGHT_DOF,
            cubic_term_spread: self.scene_pool.cubic_term_spread,
        })
    }

    /// What a window's residuals say the disparity noise variance is (see `noise_unit`).
    fn noise_ratio(&self, error: &FitError, sample: &Sample) -> Option<f64> {
        // Fewer residuals than this say too little to teach the pool.
        const MIN_DOF: f64 = 4.0;
        (error.noise_dof >= MIN_DOF)
            .then(|| error.noise_variance.sum() / self.noise_unit(sample).sum())
    }

    /// Frames of a track's history kept behind its newest sample: the velocity windows reach
    /// M before their centre (and the line `line_past_frames`), which is M behind the newest.
    fn history_frames(&self) -> u64 {
        let v = &self.config.velocity;
        (v.half_window_frames + v.half_window_frames.max(v.line_past_frames)) as u64
    }

    fn push_sample(track: &mut Track3d, sample: Sample, history: u64) {
        let oldest = sample.seq.saturating_sub(history);
        track.samples.push_back(sample);
        while track.samples.front().is_some_and(|s| s.seq < oldest) {
            track.samples.pop_front();
        }
    }

    /// For each new pair, the orphaned 3D track it continues, if any, and for a one-sample
    /// orphan the one-sample orphan of the frame before that completes the path: the
    /// continuation whose prediction the pair meets best, within the rejoin tolerances
    /// (one-to-one, closest first).
    fn rejoin(
        &self,
        births: &[Birth],
        orphans: &[(Orphan, Track3d)],
        t_s: f64,
    ) -> Vec<Option<(usize, Option<usize>)>> {
        let mut rejoined = vec![None; births.len()];
        let link = &self.config.link;
        if link.rejoin_frames == 0 || births.is_empty() || orphans.is_empty() {
            return rejoined;
        }
        let focal_px = self.rectification.focal_px;
        let disparity_sigma_px = self.config.velocity.disparity_sigma_px;
        // What each orphan predicts: (orphan, the orphan before it, predicted world point,
        // predicted left image point, per-frame image step).
        let mut predictions = Vec::new();
        let lone_grid = PointGrid::new(
            orphans
                .iter()
                .enumerate()
                .filter_map(|(o, (_, t))| match t.samples.as_slices().0 {
                    [only] if t.samples.len() == 1 => Some((only.left_rect, o)),
                    _ => None,
                }),
            link.max_displacement_px.max(16.0),
        );
        for (o, (_, track)) in orphans.iter().enumerate() {
            if let Some((world, image)) = Self::predicted_position(track, t_s) {
                let last = track.samples.back().map(|s| s.left_rect);
                let step = last.map_or(0.0, |l| (image.x - l.x).hypot(image.y - l.y));
                predictions.push((o, None, world, image, step));
                continue;
            }
            let Some(b) = track.samples.back() else {
                continue;
            };
            // Two lone samples in consecutive frames predict a third at constant velocity.
            let reach = link.max_displacement_px;
            for (a_rect, a) in lone_grid.near(b.left_rect.x, b.left_rect.y, reach) {
                let Some(sample_a) = orphans[*a].1.samples.back() else {
                    continue;
                };
                if sample_a.seq + 1 != b.seq
                    || (b.left_rect.x - a_rect.x).hypot(b.left_rect.y - a_rect.y) > reach
                {
                    continue;
                }
                let ahead = (t_s - b.t_s) / (b.t_s - sample_a.t_s);
                let world = b.point_in_world + (b.point_in_world - sample_a.point_in_world) * ahead;
                let image = RectPoint {
                    x: b.left_rect.x + (b.left_rect.x - a_rect.x) * ahead,
                    y: b.left_rect.y + (b.left_rect.y - a_rect.y) * ahead,
                };
                let step = (b.left_rect.x - a_rect.x).hypot(b.left_rect.y - a_rect.y);
                predictions.push((o, Some(*a), world, image, step));
            }
        }
        let birth_grid = PointGrid::new(
            births
                .iter()
                .enumerate()
                .map(|(i, b)| (b.sample.left_rect, i)),
            16.0,
        );
        let along_scale = |depth_m: f64| {
            link.rejoin_tolerance_sigmas
                * self
                    .rectification
                    .depth_sigma_m(depth_m, disparity_sigma_px)
        };
        let cost = |sample: &Sample, predicted: &Point3<f64>, across_px: f64, along_m: f64| {
            let (along, across_sq) =
                sample.along_and_across_sq(&(sample.point_in_world - predicted));
            (across_sq.sqrt() * focal_px / (sample.depth_m * across_px)).powi(2)
                + (along / along_m).powi(2)
        };
        let mut candidates = Vec::new();
        for (h, (_, _, world, image, step)) in predictions.iter().enumerate() {
            // A prediction misses by about the change in velocity over a frame, which grows
            // with the step (a vortex turns its particles by a fixed angle per frame).
            let across_px = link
                .rejoin_tolerance_px
                .max(crate::link::TURN_PER_FRAME * step);
            for (_, b) in birth_grid.near(image.x, image.y, 2.0 * across_px) {
                let sample = &births[*b].sample;
                let c = cost(sample, world, across_px, along_scale(sample.depth_m));
                if c <= 1.0 {
                    candidates.push((c, *b, h));
                }
            }
        }
        // A one-sample track has no path to predict from; but where its left track went on
        // (only the partner changed), the left camera vouches for the continuity across the
        // line of sight, and the depth may have changed by no more than the particle moved
        // across it.
        for (o, (kind, track)) in orphans.iter().enumerate() {
            let (Orphan::Replaced(left_track), [last]) = (kind, track.samples.as_slices().0) else {
                continue;
            };
            let Some(b) = births
                .iter()
                .position(|birth| birth.left_track == *left_track)
            else {
                continue;
            };
            let sample = &births[b].sample;
            let moved_m = (sample.left_rect.x - last.left_rect.x)
                .hypot(sample.left_rect.y - last.left_rect.y)
                * sample.depth_m
                / focal_px;
            let (along, _) =
                sample.along_and_across_sq(&(sample.point_in_world - last.point_in_world));
            let c = (along.abs() / (along_scale(sample.depth_m) + moved_m)).powi(2);
            if c <= 1.0 {
                predictions.push((o, None, last.point_in_world, last.left_rect, 0.0));
                candidates.push((c, b, predictions.len() - 1));
            }
        }
        candidates.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
        let mut taken = vec![false; orphans.len()];
        for (_, b, h) in candidates {
            let (o, before, ..) = predictions[h];
            if rejoined[b].is_some() || taken[o] || before.is_some_and(|a| taken[a]) {
                continue;
            }
            rejoined[b] = Some((o, before));
            taken[o] = true;
            if let Some(a) = before {
                taken[a] = true;
            }
        }
        rejoined
    }

    /// Where a track's last few samples put it at `t_s`, in the world and in the left image: a
    /// quadratic through up to five of them, a line through two; `None` for a single sample.
    fn predicted_position(track: &Track3d, t_s: f64) -> Option<(Point3<f64>, RectPoint)> {
        let recent = track.samples.iter().rev().take(5);
        let world: Vec<(f64, Point3<f64>)> =
            recent.clone().map(|s| (s.t_s, s.point_in_world)).collect();
        let image: Vec<(f64, Point3<f64>)> = recent
            .map(|s| (s.t_s, Point3::new(s.left_rect.x, s.left_rect.y, 0.0)))
            .collect();
        let fit = |points: &[(f64, Point3<f64>)]| match points.len() {
            0 | 1 => None,
            2 => fit_line(points, t_s),
            _ => fit_quadratic(points, t_s),
        };
        let world = fit(&world)?.position;
        let image = fit(&image)?.position;
        Some((
            world,
            RectPoint {
                x: image.x,
                y: image.y,
            },
        ))
    }

    fn last_seq(track: &Track3d) -> u64 {
        track.samples.back().map_or(0, |s| s.seq)
    }

    /// The centred estimate for the frame `M` frames back, if the track's window supports one;
    /// `Err` if rejected as rough. The centre frame must be seen, and each side of a window of
    /// `+-w` frames may miss at most `max_missing_per_side` frames (to a gap, or to the track's
    /// start or end; a narrower window may miss none). `w` is M, or narrower down to 2 where the particle crosses
    /// `min_window_travel_px` within it; with `adaptive_fit` the fit is chosen per component
    /// among the windows the track supports (returned with the vector).
    fn centred_vector(&self, track: &Track3d, seq: u64) -> Option<Result<Centred, ()>> {
        let velocity = &self.config.velocity;
        let m = velocity.half_window_frames as u64;
        let centre_seq = seq.checked_sub(m)?;
        // Samples only cut out of overlapping particles keep the track's identity but do not
        // enter the fit: their centroids are biased. Samples separated by a trustworthy spot fit
        // stand in only where the clear ones cannot carry a fit, so a vector the clear samples
        // give is not diluted. The fit needs no sample at the centre itself, so a particle
        // hidden in an overlap at the centre frame still gets a vector from its neighbours in
        // time.
        let centre = track.samples.iter().find(|s| s.seq == centre_seq)?;
        let (mut windows, mut any_supported) =
            self.candidate_windows(track, centre, Separation::Clear);
        let fitted_in_window = || {
            track
                .samples
                .iter()
                .any(|s| s.separation == Separation::Fitted && s.seq.abs_diff(centre_seq) <= m)
        };
        let mut worst = Separation::Clear;
        if !any_supported && fitted_in_window() {
            worst = Separation::Fitted;
            (windows, any_supported) = self.candidate_windows(track, centre, worst);
        }
        if windows.is_empty() {
            return any_supported.then_some(Err(()));
        }
        let (fit, choice) = if velocity.adaptive_fit {
            let past = self.past_window(track, centre, worst, windows.last());
            let adaptive = fit_adaptive(&windows, past.as_ref(), centre.t_s)?;
            (adaptive.fit, Some(adaptive.choice))
        } else {
            (windows.last()?.motion()?, None)
        };
        let prior = self.scene_prior(centre);
        let (velocity_sigma, position_sigma) = fit.error.sigmas(prior.as_ref());
        Some(Ok(Centred {
            vector: VelocityVector {
                frame_index: centre.frame_index,
                t_s: centre.t_s,
                track_id: track.id,
                position_in_world: fit.position,
                velocity_in_world: fit.velocity,
                rms_residual_m: fit.rms_residual,
                velocity_sigma,
                position_sigma,
            },
            choice,
            noise_ratio: self.noise_ratio(&fit.error, centre),
            cubic_term: (fit.error.cubic_term_gain > 0.0).then(|| {
                let noise = fit.error.pooled_noise(prior.as_ref());
                (fit.error.cubic_term, fit.error.cubic_term_variance(&noise))
            }),
        }))
    }

    /// The velocity windows a track's samples (those separated at least as well as `worst`)
    /// support around `centre`, narrowest first, leaving out rough ones; and whether any window
    /// was supported at all (all rough: the track is rejected, not merely short).
    fn candidate_windows(
        &self,
        track: &Track3d,
        centre: &Sample,
        worst: Separation,
    ) -> (Vec<QuadraticWindow>, bool) {
        let velocity = &self.config.velocity;
        let m = velocity.half_window_frames as u64;
        let centre_seq = centre.seq;
        let usable_within = |w: u64| {
            track
                .samples
                .iter()
                .filter(move |s| s.separation <= worst && s.seq.abs_diff(centre_seq) <= w)
        };
        // Fitted samples enter full windows only: in a narrowed one the few samples cannot show
        // a fit that swapped two crossing particles (measured on the wind tunnel: u 0.11 % ->
        // 0.18 % with them in narrowed windows too).
        let narrowest = if worst == Separation::Clear {
            self.narrowest_window(usable_within(m), m)
        } else {
            m
        };
        // Candidate windows, narrowest first; a window whose samples stray from a smooth path
        // (a swapped particle, a wrong stereo pair) is left out, and narrower ones that end
        // before the stray sample may still serve.
        let mut windows = Vec::new();
        let mut any_supported = false;
        for w in narrowest..=m {
            let before = usable_within(w).filter(|s| s.seq < centre_seq).count() as u64;
            let after = usable_within(w).filter(|s| s.seq > centre_seq).count() as u64;
            // A narrowed window is complete: it has few samples to spare, and a quadratic through
            // three or four of them says nothing about the track's smoothness.
            let needed = if w < m {
                w
            } else {
                w.saturating_sub(velocity.max_missing_per_side as u64)
                    .max(1)
            };
            if before < needed || after < needed {
                continue;
            }
            any_supported = true;
            let samples: Vec<&Sample> = usable_within(w).collect();
            let points = samples.iter().map(|s| (s.t_s, s.point_in_world)).collect();
            // Ill-posed only without distinct sample times, which the counts above exclude.
            let Some(window) = QuadraticWindow::new(w as usize, points, centre.t_s) else {
                continue;
            };
            if self.is_rough(&samples, &window, centre.depth_m) {
                continue;
            }
            windows.push(window);
        }
        (windows, any_supported)
    }

    /// The window for a line reaching `line_past_frames` before `centre` and M after it, where
    /// the track's samples (separated at least as well as `worst`) fill it (the full +-M window
    /// `widest` is supported, and at most `max_missing_per_side` frames before the centre are
    /// missing) and do not stray from a smooth path.
    fn past_window(
        &self,
        track: &Track3d,
        centre: &Sample,
        worst: Separation,
        widest: Option<&QuadraticWindow>,
    ) -> Option<QuadraticWindow> {
        let velocity = &self.config.velocity;
        let (m, past) = (velocity.half_window_frames, velocity.line_past_frames);
        if past <= m || widest?.half_window_frames < m {
            return None;
        }
        let samples: Vec<&Sample> = track
            .samples
            .iter()
            .filter(|s| {
                s.separation <= worst
                    && s.seq + past as u64 >= centre.seq
                    && s.seq <= centre.seq + m as u64
            })
            .collect();
        let before = samples.iter().filter(|s| s.seq < centre.seq).count();
        if before + velocity.max_missing_per_side < past {
            return None;
        }
        let points = samples.iter().map(|s| (s.t_s, s.point_in_world)).collect();
        let window = QuadraticWindow::new(m, points, centre.t_s)?;
        (!self.is_rough(&samples, &window, centre.depth_m)).then_some(window)
    }

    /// The narrowest half-window (2..=m) a track's samples may be fitted over: the particle must
    /// cross `min_window_travel_px` within it, judged from its mean image speed over `samples`.
    fn narrowest_window<'a>(&self, samples: impl Iterator<Item = &'a Sample>, m: u64) -> u64 {
        let travel_px = self.config.velocity.min_window_travel_px;
        let mut samples = samples;
        let Some(first) = samples.next() else {
            return m;
        };
        let Some(last) = samples.last() else {
            return m;
        };
        if travel_px <= 0.0 || last.seq == first.seq {
            return m;
        }
        let (a, b) = (first.left_rect, last.left_rect);
        let speed_px = (b.x - a.x).hypot(b.y - a.y) / (last.seq - first.seq) as f64;
        let frames_each_side = (travel_px / (2.0 * speed_px)).ceil();
        if frames_each_side.is_finite() {
            (frames_each_side as u64).clamp(2.min(m), m)
        } else {
            m
        }
    }
}

/// Which of a frame's vectors stray from their neighbours (see `kinematics::neighbour_outliers`).
fn outliers_among<'a>(
    vectors: impl Iterator<Item = &'a VelocityVector>,
    test: &NeighbourTest,
) -> Vec<bool> {
    let vectors: Vec<_> = vectors
        .map(|v| (v.position_in_world, v.velocity_in_world))
        .collect();
    neighbour_outliers(&vectors, test)
}

/// One camera's stages, which need nothing from the other camera: detection, rectification and
/// per-camera linking.
struct Camera {
    detector: Detector,
    linker: CameraLinker,
}

impl Camera {
    fn new() -> Self {
        Self {
            detector: Detector::new(),
            linker: CameraLinker::new(),
        }
    }

    /// Detects into `detections`, looking again where the tracks expect particles, and links
    /// the rectified features; returns the linked features and, index for index, the detection
    /// each came from (detections whose centroid the lens model cannot undistort are left out).
    fn push(
        &mut self,
        image: ImageView<'_>,
        config: &PipelineConfig,
        scale: CostScale,
        detections: &mut Vec<Detection>,
        to_rect: impl Fn(PixelPoint) -> Option<RectPoint>,
        from_rect: impl Fn(RectPoint) -> Option<PixelPoint>,
    ) -> (Vec<LinkedFeature>, Vec<usize>) {
        self.detector.detect(image, &config.detect, detections);
        if config.detect.separate_expected {
            let expected: Vec<PixelPoint> = self
                .linker
                .expected_positions()
                .filter_map(&from_rect)
                .collect();
            self.detector
                .separate_expected(image, &config.detect, &expected, detections);
        }
        let (features, detection_of): (Vec<Feature>, Vec<usize>) = detections
            .iter()
            .enumerate()
            .filter_map(|(i, d)| {
                to_rect(d.centroid).map(|rect| {
                    (
                        Feature {
                            rect,
                            diameter_px: d.diameter_px,
                            brightness: d.brightness,
                        },
                        i,
                    )
                })
            })
            .unzip();
        (
            self.linker.push(&features, scale, &config.link),
            detection_of,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Terms drawn with spread `tau2`, each estimated with a noise whose variance varies a
    /// hundredfold between windows (near and far particles).
    fn drawn_terms(tau2: f64, seed: u64) -> Vec<(f64, f64)> {
        let mut rng = crate::synth::Rng::new(seed);
        (0..511)
            .map(|_| {
                let v = 10f64.powf(rng.range(-1.0, 1.0));
                let d = rng.normal() * tau2.sqrt() + rng.normal() * v.sqrt();
                (d * d, v)
            })
            .collect()
    }

    #[test]
    fn the_spread_of_terms_is_told_from_their_noise() {
        for (tau2, seed) in [(0.3, 1), (3.0, 2), (30.0, 3)] {
            let estimate = spread_of_terms(&drawn_terms(tau2, seed));
            assert!(
                (estimate / tau2 - 1.0).abs() < 0.25,
                "tau2 {tau2}: estimated {estimate}"
            );
        }
        // No spread: estimates no larger than their noise say nothing is there.
        let none: Vec<f64> = (4..9)
            .map(|seed| spread_of_terms(&drawn_terms(0.0, seed)))
            .collect();
        assert!(none.iter().all(|&t| t < 0.1), "{none:?}");
        assert_eq!(spread_of_terms(&[]), 0.0);
    }
    use crate::synth::{Scenario, ScenarioSpec, Synthesizer};

    fn frame<'a>(
        index: u64,
        t_s: f64,
        w: usize,
        h: usize,
        left: &'a [u8],
        right: &'a [u8],
    ) -> StereoFrame<'a> {
        StereoFrame {
            index,
            t_s,
            world_from_rig: None,
            left: ImageView::new(w, h, left).expect("sized"),
            right: ImageView::new(w, h, right).expect("sized"),
        }
    }

    #[test]
    fn bad_frames_are_rejected_and_leave_the_state_untouched() {
        let spec = ScenarioSpec::new(Scenario::Flume);
        let (w, h) = (spec.rig.width as usize, spec.rig.height as usize);
        let mut synth = Synthesizer::new(spec.clone(), 20, 1);
        let frames: Vec<_> = (0..14).map(|_| synth.next_frame()).collect();
        let run = |with_faults: bool| {
            let mut pipeline =
                Pipeline::new(spec.rig.clone(), PipelineConfig::default()).expect("valid");
            let mut vectors = Vec::new();
            for f in &frames {
                if with_faults {
                    let small = vec![0u8; 16 * 16];
                    let e = pipeline
                        .push(&frame(f.index, f.t_s, 16, 16, &small, &small))
                        .unwrap_err();
                    assert!(
                        e.to_string()
                            .contains("left image is 16x16, calibration says 640x480"),
                        "{e}"
                    );
                    if f.index > 0 {
                        let e = pipeline
                            .push(&frame(f.index, f.t_s - 1.0, w, h, &f.left, &f.right))
                            .unwrap_err();
                        assert!(matches!(e, PipelineError::Timestamp { .. }), "{e}");
                    }
                    let e = pipeline
                        .push(&frame(f.index, f64::NAN, w, h, &f.left, &f.right))
                        .unwrap_err();
                    assert!(matches!(e, PipelineError::Timestamp { .. }), "{e}");
                }
                vectors.extend(
                    pipeline
                        .push(&frame(f.index, f.t_s, w, h, &f.left, &f.right))
                        .expect("valid")
                        .vectors,
                );
            }
            vectors
        };
        let clean = run(false);
        assert!(!clean.is_empty());
        assert_eq!(clean, run(true), "rejected frames change nothing");
    }

    #[test]
    fn invalid_config_is_refused_up_front() {
        let spec = ScenarioSpec::new(Scenario::Flume);
        let mut config = PipelineConfig::default();
        config.detect.box_size_px = 14;
        let e = Pipeline::new(spec.rig.clone(), config)
            .err()
            .expect("refused");
        assert_eq!(
            e.to_string(),
            "config: detect.box_size_px: must be odd and in 3..=101"
        );
        let mut config = PipelineConfig::default();
        config.velocity.max_missing_per_side = 5;
        assert!(Pipeline::new(spec.rig, config).is_err());
    }

    #[test]
    fn vectors_arrive_m_frames_late_for_the_centre_frame() {
        let spec = ScenarioSpec::new(Scenario::Flume);
        let (w, h) = (spec.rig.width as usize, spec.rig.height as usize);
        let mut synth = Synthesizer::new(spec.clone(), 10, 2);
        let mut pipeline =
            Pipeline::new(spec.rig.clone(), PipelineConfig::default()).expect("valid");
        let m = PipelineConfig::default().velocity.half_window_frames as u64;
        for _ in 0..20 {
            let f = synth.next_frame();
            let out = pipeline
                .push(&frame(f.index, f.t_s, w, h, &f.left, &f.right))
                .expect("valid");
            assert!(
                out.vectors.iter().all(|v| v.frame_index + m == f.index),
                "centre lags by M"
            );
            assert_eq!(out.stats.vectors, out.vectors.len());
            let expected_centre = f.index.checked_sub(m);
            assert_eq!(out.centred_frame.map(|c| c.index), expected_centre);
            assert!(
                out.causal_vectors.iter().all(|v| v.frame_index == f.index),
                "causal vectors describe the newest frame"
            );
            if f.index > m {
                assert!(!out.causal_vectors.is_empty(), "frame {}", f.index);
            }
        }
    }

    #[test]
    fn particles_too_far_for_their_depth_to_be_measured_give_no_vectors() {
        // The flume's particles, moved out to where their disparity is 1-1.5 px and scaled to
        // keep their size in the image: found, matched and tracked, but never published.
        let near = ScenarioSpec::new(Scenario::Flume);
        let rect = Rectification::new(&near.rig).expect("rectifies");
        let focal_baseline = rect.focal_px * rect.baseline_m;
        let run = |spec: &ScenarioSpec| {
            let (w, h) = (spec.rig.width as usize, spec.rig.height as usize);
            let mut synth = Synthesizer::new(spec.clone(), 30, 5);
            let mut pipeline =
                Pipeline::new(spec.rig.clone(), PipelineConfig::default()).expect("valid");
            let mut totals = FrameStats::default();
            for _ in 0..30 {
                let f = synth.next_frame();
                let out = pipeline
                    .push(&frame(f.index, f.t_s, w, h, &f.left, &f.right))
                    .expect("valid");
                let vectors = out.vectors.len() + out.causal_vectors.len();
                assert_eq!(out.stats.vectors + out.stats.causal_vectors, vectors);
                totals += &out.stats;
            }
            totals
        };
        let mut far = near.clone();
        let scale = focal_baseline / 1.25 / (0.5 * (near.domain_min.z + near.domain_max.z));
        far.domain_min = Point3::from(near.domain_min.coords * scale);
        far.domain_max = Point3::from(near.domain_max.coords * scale);
        far.diameter_m *= scale;
        far.diameter_sd_m *= scale;
        far.illumination *= scale * scale;
        far.flow = match &near.flow {
            crate::synth::Flow::Uniform(v) => crate::synth::Flow::Uniform(v * scale),
            other => panic!("the flume's flow is uniform: {other:?}"),
        };
        let (near_stats, far_stats) = (run(&near), run(&far));
        assert!(
            near_stats.vectors > 100 && near_stats.implausible == 0,
            "{near_stats:?}"
        );
        assert!(
            far_stats.matches > 100,
            "the far particles are seen: {far_stats:?}"
        );
        assert_eq!(
            far_stats.vectors + far_stats.causal_vectors,
            0,
            "{far_stats:?}"
        );
        assert!(far_stats.implausible > 100, "{far_stats:?}");
    }

    #[test]
    fn both_cameras_in_parallel_give_exactly_what_one_thread_gives() {
        let spec = ScenarioSpec::new(Scenario::Dense);
        let (w, h) = (spec.rig.width as usize, spec.rig.height as usize);
        let mut synth = Synthesizer::new(spec.clone(), 400, 3);
        let frames: Vec<_> = (0..16).map(|_| synth.next_frame()).collect();
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("thread pool");
            pool.install(|| {
                let mut pipeline =
                    Pipeline::new(spec.rig.clone(), PipelineConfig::default()).expect("valid");
                frames
                    .iter()
                    .map(|f| {
                        pipeline
                            .push(&frame(f.index, f.t_s, w, h, &f.left, &f.right))
                            .expect("valid")
                    })
                    .collect::<Vec<_>>()
            })
        };
        let (one, two) = (run(1), run(2));
        assert!(one.iter().map(|o| o.vectors.len()).sum::<usize>() > 100);
        assert_eq!(one, two);
    }
}
