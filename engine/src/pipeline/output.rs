//! What one frame produces: its detections, matched points, vectors and counts.

use nalgebra::Point3;

use crate::detect::Detection;
use crate::geometry::PixelPoint;
use crate::velocity::VelocityVector;

/// A particle matched in both cameras this frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MatchedPoint {
    /// The 3D track this point belongs to.
    pub track_id: u64,
    /// Where it is, world frame (rig frame without a pose), metres.
    pub point_in_world: Point3<f64>,
    /// Its detections' centroids in the raw left and right images.
    pub left_px: PixelPoint,
    /// See `left_px`.
    pub right_px: PixelPoint,
    /// Its depth along the rectified viewing direction, metres.
    pub depth_m: f64,
}

/// What one frame's stages did, counted (summed over frames, a run's: see `AddAssign`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct FrameStats {
    /// Detections in the left image.
    pub detections_left: usize,
    /// Detections in the right image.
    pub detections_right: usize,
    /// Particles matched in both cameras.
    pub matches: usize,
    /// Live 3D tracks after the frame.
    pub tracks: usize,
    /// Centred vectors (the measurement).
    pub vectors: usize,
    /// Causal vectors (for live display).
    pub causal_vectors: usize,
    /// Centred vectors dropped by the smoothness check.
    pub rejected: usize,
    /// Centred vectors dropped for straying from their neighbours (`velocity.outlier_neighbours`).
    pub outliers: usize,
    /// Vectors (centred and causal) dropped as no measurement: outside the measurement volume or
    /// faster than a tracked particle can move.
    pub implausible: usize,
    /// Left features that continue a track from an earlier frame.
    pub linked_left: usize,
    /// Right features that continue a track from an earlier frame.
    pub linked_right: usize,
    /// Stereo pairs that passed the hard filter.
    pub stereo_candidates: usize,
    /// Left features with at least one stereo candidate.
    pub left_with_candidates: usize,
    /// Velocity components (three per vector) whose fit the data chose over the method's
    /// quadratic on +-M: a quadratic on a narrower window ...
    pub fit_components_narrower: usize,
    /// ... or a cubic.
    pub fit_components_cubic: usize,
    /// Velocity components fitted with a line reaching `line_past_frames` back.
    pub fit_components_line: usize,
    /// New stereo pairs that continued a broken 3D track (`link.rejoin_frames`).
    pub rejoined: usize,
    /// 3D tracks that predicted their particle in this frame (`link.track_first`).
    pub predicted: usize,
    /// ... and found it in both images.
    pub found: usize,
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
        self.predicted += s.predicted;
        self.found += s.found;
        self.fixtures += s.fixtures;
        self.noisy_images += s.noisy_images;
        self.learnt_search += s.learnt_search;
    }
}

/// A frame as the pipeline saw it: its index, sensor time, and whether it came with a pose
/// (its points are then in the world frame, else in the rig frame).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameRef {
    /// The frame's index as the source numbered it.
    pub index: u64,
    /// Its sensor time, seconds.
    pub t_s: f64,
    /// Whether it came with a pose.
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
    /// The frame pushed.
    pub frame_index: u64,
    /// Its sensor time, seconds.
    pub t_s: f64,
    /// Its left image's detections, in raster order.
    pub detections_left: Vec<Detection>,
    /// Its right image's detections, in raster order.
    pub detections_right: Vec<Detection>,
    /// Per left detection, whether it continues a per-camera track from an earlier frame.
    pub continued_left: Vec<bool>,
    /// See `continued_left`.
    pub continued_right: Vec<bool>,
    /// Its particles matched in both cameras.
    pub points: Vec<MatchedPoint>,
    /// Particles one image showed and the other hid, whose 3D tracks went on with a partial
    /// sample (`link.track_first`): on the seen image's line of sight at the predicted depth;
    /// the hidden image's pixel is where the sample projects. Not stereo matches: not in
    /// `points`, and not counted in `stats.matches`.
    pub partial_points: Vec<MatchedPoint>,
    /// Vectors for this frame, without latency (see above).
    pub causal_vectors: Vec<VelocityVector>,
    /// The frame `vectors` describe; `None` until `M` frames have followed the first one.
    pub centred_frame: Option<FrameRef>,
    /// The centred vectors for `centred_frame` (see above).
    pub vectors: Vec<VelocityVector>,
    /// What the frame's stages did.
    pub stats: FrameStats,
}
