//! The [`Pipeline`]: owns every stage's state and turns one [`StereoFrame`] into a
//! [`FrameOutput`], the stages in order.
//!
//! Offline processing and the live server drive this same type, so both give identical results
//! for identical frames. Nothing in here reads a clock: time comes from frame timestamps.

use std::collections::VecDeque;

use nalgebra::{Isometry3, Point3};

use crate::config::ConfigError;
use crate::detect::{Detection, Separation};
use crate::geometry::{CalibrationError, PixelPoint, RectPoint, Rectification, StereoRig};
use crate::link::{CostScale, LinkedFeature};
use crate::predict::{self, Prediction};
use crate::shake::refine::{best_known, CameraShake};
use crate::shake::{self, Shaken};
use crate::stereo::{match_stereo, DepthLearner, PairHistory, StereoSearch};
use crate::tracks::{Pair, Sample, Sight, Tracks};
use crate::velocity::Velocities;
use crate::{ImageView, StereoFrame};

mod camera;
mod config;
mod found;
mod output;

use camera::{Camera, CameraOutput, Expected};
pub use config::PipelineConfig;
pub use output::{FrameOutput, FrameRef, FrameStats, MatchedPoint};

/// Why a pipeline cannot be set up, or a frame is refused.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PipelineError {
    /// The rig cannot be rectified.
    #[error("calibration: {0}")]
    Calibration(#[from] CalibrationError),
    /// The config cannot be used with this rig.
    #[error("config: {0}")]
    Config(#[from] ConfigError),
    /// A frame's image is not the calibrated size.
    #[error("frame {index}: {camera} image is {width}x{height}, calibration says {expected_width}x{expected_height}")]
    ImageSize {
        /// The frame's index.
        index: u64,
        /// `left` or `right`.
        camera: &'static str,
        /// The image's size.
        width: usize,
        /// See `width`.
        height: usize,
        /// The size `rig.json` gives.
        expected_width: u32,
        /// See `expected_width`.
        expected_height: u32,
    },
    /// A frame's time does not follow the previous frame's.
    #[error("frame {index}: timestamp {t_s} s is not finite or not after the previous frame's {previous_s} s")]
    Timestamp {
        /// The frame's index.
        index: u64,
        /// Its time.
        t_s: f64,
        /// The previous frame's time (-inf for the first).
        previous_s: f64,
    },
}

/// Confirmed 3D tracks (seen for this many frames) teach the stereo search where the volume is:
/// ghosts rarely last that long.
const CONFIRMED_SAMPLES: usize = 5;

/// A found track learns its particle's shapes again every this many samples (the shape
/// follows the particle's depth).
const RELEARN_SHAPE_SAMPLES: usize = 10;

/// The engine's state machine: push stereo frames in time order, get each frame's output.
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
    tracks: Tracks,
    velocities: Velocities,
    previous_t_s: Option<f64>,
    /// Frames pushed so far.
    seq: u64,
    /// The last `M + 1` frames pushed, newest at the back.
    recent_frames: VecDeque<FrameRef>,
    /// The particle images' radius in the last image with detections, pixels: the scale a
    /// prediction's search starts from before any track has learnt its own.
    image_radius_px: f64,
    /// What each camera's shake has learnt (track-first).
    shake: [CameraShake; 2],
}

impl Pipeline {
    /// A pipeline for `rig` with `config`, refused where the config is invalid or the rig
    /// cannot be rectified.
    pub fn new(rig: StereoRig, config: PipelineConfig) -> Result<Self, PipelineError> {
        config.validate()?;
        let rectification = Rectification::new(&rig)?;
        let stereo_search =
            StereoSearch::new(&config.stereo, &rectification).map_err(ConfigError::from)?;
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
            tracks: Tracks::new(&config),
            velocities: Velocities::new(&config.velocity, &rectification, rig.width, rig.height),
            config,
            rig,
            rectification,
            left: Camera::new(),
            right: Camera::new(),
            stereo_search,
            pair_history: PairHistory::new(),
            previous_t_s: None,
            seq: 0,
            recent_frames: VecDeque::new(),
            image_radius_px: 1.0,
            shake: Default::default(),
        })
    }

    /// The config it runs with.
    pub fn config(&self) -> &PipelineConfig {
        &self.config
    }

    /// The rig it was set up for.
    pub fn rig(&self) -> &StereoRig {
        &self.rig
    }

    /// The rig's virtual co-directional pair, where linking and matching happen.
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

    /// Processes one stereo frame. A rejected frame (wrong size, time going backwards) leaves the
    /// pipeline state untouched, so the caller may report it and carry on.
    pub fn push(&mut self, frame: &StereoFrame<'_>) -> Result<FrameOutput, PipelineError> {
        // A frame's stages fork onto the pool's threads many times (each camera, the tracks'
        // fits). Forked from a thread outside the pool, each fork waits for a pool thread to
        // take it and hand it back; the whole frame run on a pool thread makes one such trip.
        rayon::scope(|_| self.push_on_pool(frame))
    }

    /// [`Self::push`], on a thread of rayon's pool.
    fn push_on_pool(&mut self, frame: &StereoFrame<'_>) -> Result<FrameOutput, PipelineError> {
        self.check_frame(frame)?;
        let seq = self.advance(frame);
        let mut out = FrameOutput {
            frame_index: frame.index,
            t_s: frame.t_s,
            ..Default::default()
        };
        let predictions = self.predict(frame, seq);
        let (left, right) = self.detect_and_link(frame, &predictions, &mut out);
        let band_px = self
            .learnt_search()
            .unwrap_or(self.stereo_search)
            .epipolar_band_px;
        let mut shaken = shake::find(&predictions, &left.linked, &right.linked, band_px);
        self.take_found(
            frame,
            seq,
            (&left, &right),
            &predictions,
            &mut shaken,
            band_px,
            &mut out,
        );
        let paired = self.match_pairs(&left, &right, &shaken, &mut out.stats);
        let pairs = self.triangulate(frame, seq, &left, &right, &paired, &out);
        out.stats.rejoined =
            self.tracks
                .update(seq, frame.t_s, pairs, &self.rectification, &mut out.points);
        if self.config.tracks.track_first {
            self.learn_young_shapes(frame, (&left, &right), &paired, &out);
        }
        if let Some(learner) = &mut self.depth_learner {
            learner.add(seq, self.tracks.confirmed_depths(seq, CONFIRMED_SAMPLES));
        }
        self.velocities.estimate(self.tracks.all(), seq, &mut out);
        let m = self.config.velocity.half_window_frames;
        out.centred_frame = (self.recent_frames.len() == m + 1)
            .then(|| self.recent_frames.front().copied())
            .flatten();
        out.stats.detections_left = out.detections_left.len();
        out.stats.detections_right = out.detections_right.len();
        out.stats.matches = out.points.len();
        out.stats.tracks = self.tracks.live_count();
        out.stats.vectors = out.vectors.len();
        out.stats.causal_vectors = out.causal_vectors.len();
        Ok(out)
    }

    /// Refuses a frame whose images are not the rig's size or whose time does not follow the
    /// previous frame's.
    fn check_frame(&self, frame: &StereoFrame<'_>) -> Result<(), PipelineError> {
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
        Ok(())
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

    /// Takes an accepted frame into the clock: its time, its sequence number (returned), and
    /// the last M + 1 frames.
    fn advance(&mut self, frame: &StereoFrame<'_>) -> u64 {
        self.previous_t_s = Some(frame.t_s);
        self.seq += 1;
        self.recent_frames.push_back(FrameRef {
            index: frame.index,
            t_s: frame.t_s,
            posed: frame.world_from_rig.is_some(),
        });
        if self.recent_frames.len() > self.config.velocity.half_window_frames + 1 {
            self.recent_frames.pop_front();
        }
        self.seq
    }

    /// Both cameras' own stages (detection, rectification, linking), which need nothing from
    /// each other: one core each. Their outputs do not depend on which runs first, so results
    /// match a single-threaded run exactly.
    fn detect_and_link(
        &mut self,
        frame: &StereoFrame<'_>,
        predictions: &[Prediction],
        out: &mut FrameOutput,
    ) -> (CameraOutput, CameraOutput) {
        let rect = &self.rectification;
        let expected = |c: usize| Expected {
            predicted: predictions
                .iter()
                .map(|p| {
                    let shapes = self.tracks.shapes(p.key);
                    (p.at(c), p.gate_px, best_known(shapes[c], shapes[1 - c]))
                })
                .collect(),
            shake: &self.shake[c],
        };
        let (expected_left, expected_right) = (expected(0), expected(1));
        let scale = cost_scale(rect);
        let config = &self.config;
        let (left_camera, right_camera) = (&mut self.left, &mut self.right);
        let (detections_left, detections_right) =
            (&mut out.detections_left, &mut out.detections_right);
        let (left, right) = rayon::join(
            || {
                left_camera.push(
                    frame.left,
                    config,
                    scale,
                    detections_left,
                    &expected_left,
                    (|p| rect.left_to_rect(p), |p| rect.rect_to_left(p)),
                )
            },
            || {
                right_camera.push(
                    frame.right,
                    config,
                    scale,
                    detections_right,
                    &expected_right,
                    (|p| rect.right_to_rect(p), |p| rect.rect_to_right(p)),
                )
            },
        );
        out.stats.noisy_images = [&self.left, &self.right]
            .iter()
            .filter(|c| c.detector.last_contrast_c() < self.config.detect.contrast_c)
            .count();
        if self.config.tracks.track_first {
            self.image_radius_px =
                median_radius_px(&out.detections_left).unwrap_or(self.image_radius_px);
        }
        (left, right)
    }

    /// Stereo pairs `(left, right)` of the linked features no prediction claimed, matched in
    /// the search learnt from the tracks where there is one. Fixtures (features that have not
    /// moved for a while) never enter: a static light in the room would otherwise become a 3D
    /// point with a velocity of zero.
    fn match_pairs(
        &mut self,
        left: &CameraOutput,
        right: &CameraOutput,
        shaken: &Shaken,
        stats: &mut FrameStats,
    ) -> Vec<(usize, usize)> {
        let (moving_left, left_index) = moving(&left.linked, &shaken.claimed_left);
        let (moving_right, right_index) = moving(&right.linked, &shaken.claimed_right);
        stats.fixtures = fixtures(&left.linked) + fixtures(&right.linked);
        let learnt_search = self.learnt_search();
        stats.learnt_search = usize::from(learnt_search.is_some());
        let stereo = match_stereo(
            &moving_left,
            &moving_right,
            cost_scale(&self.rectification),
            learnt_search.as_ref().unwrap_or(&self.stereo_search),
            &mut self.pair_history,
            &self.config.stereo,
        );
        stats.stereo_candidates = stereo.candidates;
        stats.left_with_candidates = stereo.left_with_candidates;
        stereo
            .pairs
            .iter()
            .map(|&(l, r)| (left_index[l], right_index[r]))
            .collect()
    }

    /// Every live track's prediction for this frame (none unless `tracks.track_first`).
    fn predict(&mut self, frame: &StereoFrame<'_>, seq: u64) -> Vec<Prediction> {
        if !self.config.tracks.track_first {
            return Vec::new();
        }
        let world_from_rig = frame.world_from_rig.unwrap_or_else(Isometry3::identity);
        let max_gap = self.tracks.max_gap_frames();
        predict::predict(
            self.tracks.live_mut(),
            seq,
            frame.t_s,
            &world_from_rig,
            &self.rectification,
            max_gap,
            self.image_radius_px,
        )
    }

    /// The pairs triangulated, in the world frame (the rig's without a pose); pairs the
    /// rectified geometry cannot triangulate are left out.
    fn triangulate(
        &self,
        frame: &StereoFrame<'_>,
        seq: u64,
        left: &CameraOutput,
        right: &CameraOutput,
        pairs: &[(usize, usize)],
        out: &FrameOutput,
    ) -> Vec<Pair> {
        pairs
            .iter()
            .filter_map(|&(li, ri)| {
                let spots = Self::spots_of(left, right, (li, ri), out);
                let (sample, point) = self.sample_at(frame, seq, spots)?;
                Some(Pair {
                    left_track: left.linked[li].track_id,
                    right_track: right.linked[ri].track_id,
                    sample,
                    point,
                })
            })
            .collect()
    }

    /// Where a left and a right feature (by index) are seen, as detected.
    fn spots_of(
        left: &CameraOutput,
        right: &CameraOutput,
        (li, ri): (usize, usize),
        out: &FrameOutput,
    ) -> [Spot; 2] {
        [
            left.spot(li, &out.detections_left),
            right.spot(ri, &out.detections_right),
        ]
    }

    /// The sample and the point of a particle seen at `spots` in the two images; `None` where
    /// the rectified geometry cannot triangulate them.
    fn sample_at(
        &self,
        frame: &StereoFrame<'_>,
        seq: u64,
        [l, r]: [Spot; 2],
    ) -> Option<(Sample, MatchedPoint)> {
        let world_from_rig = frame.world_from_rig.unwrap_or_else(Isometry3::identity);
        let t = self.rectification.triangulate(l.rect, r.rect)?;
        let sample = Sample {
            seq,
            frame_index: frame.index,
            t_s: frame.t_s,
            point_in_world: world_from_rig * t.point_in_rig,
            depth_m: t.depth_m,
            separation: l.separation.max(r.separation),
            left_rect: l.rect,
            camera_in_world: world_from_rig * Point3::origin(),
            seen_from: self.seen_from([l, r], &world_from_rig),
        };
        let point = MatchedPoint {
            track_id: 0,
            point_in_world: sample.point_in_world,
            left_px: l.px,
            right_px: r.px,
            depth_m: t.depth_m,
        };
        Some((sample, point))
    }

    /// For a particle one image hid and the other told apart (clear or fitted): the camera
    /// that saw it, world frame.
    fn seen_from(&self, spots: [Spot; 2], world_from_rig: &Isometry3<f64>) -> Option<Sight> {
        let hidden = spots
            .iter()
            .position(|s| s.separation == Separation::Hidden)?;
        let seen = 1 - hidden;
        let separation = spots[seen].separation;
        (separation <= Separation::Fitted).then(|| Sight {
            camera_in_world: world_from_rig * self.rectification.camera_in_rig(seen),
            separation,
        })
    }
}

/// Where a particle is seen in one image.
#[derive(Debug, Clone, Copy)]
struct Spot {
    /// Its centre, rectified.
    rect: RectPoint,
    /// The detection's centroid, or the fitted centre where it has no detection, raw pixels.
    px: PixelPoint,
    /// How it was told apart from its neighbours.
    separation: Separation,
}

/// The normalisation of the cost terms: half the rectified image's size.
fn cost_scale(rect: &Rectification) -> CostScale {
    CostScale {
        half_width_px: rect.half_width_px,
        half_height_px: rect.half_height_px,
    }
}

/// The features that are neither fixtures nor `claimed`, and, index for index, where each
/// stands in `features`.
fn moving(features: &[LinkedFeature], claimed: &[bool]) -> (Vec<LinkedFeature>, Vec<usize>) {
    features
        .iter()
        .zip(claimed)
        .enumerate()
        .filter(|(_, (f, claimed))| !f.fixed && !**claimed)
        .map(|(i, (f, _))| (*f, i))
        .unzip()
}

fn fixtures(features: &[LinkedFeature]) -> usize {
    features.iter().filter(|f| f.fixed).count()
}

/// Half the median diameter of `detections`: the particle images' radius.
fn median_radius_px(detections: &[Detection]) -> Option<f64> {
    let mut diameters: Vec<f64> = detections.iter().map(|d| d.diameter_px).collect();
    (!diameters.is_empty()).then(|| 0.5 * crate::spatial::median(&mut diameters))
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::synth::{Scenario, ScenarioSpec, Synthesizer};
    use crate::VelocityVector;

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
        // Both loops: the chain, and the tracks first.
        for track_first in [false, true] {
            let mut config = PipelineConfig::default();
            config.tracks.track_first = track_first;
            far_particles_give_no_vectors(&config);
        }
    }

    fn far_particles_give_no_vectors(config: &PipelineConfig) {
        let near = ScenarioSpec::new(Scenario::Flume);
        let rect = Rectification::new(&near.rig).expect("rectifies");
        let focal_baseline = rect.focal_px * rect.baseline_m;
        let run = |spec: &ScenarioSpec| {
            let (w, h) = (spec.rig.width as usize, spec.rig.height as usize);
            let mut synth = Synthesizer::new(spec.clone(), 30, 5);
            let mut pipeline = Pipeline::new(spec.rig.clone(), config.clone()).expect("valid");
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

    /// A flume run: its vectors, its summed statistics, and how many distinct 3D tracks and
    /// distinct particles (the truth particle nearest each vector) the vectors are on.
    struct FlumeRun {
        vectors: Vec<VelocityVector>,
        stats: FrameStats,
        tracks: usize,
        particles: usize,
    }

    fn flume_run(config: PipelineConfig) -> FlumeRun {
        let spec = ScenarioSpec::new(Scenario::Flume);
        let (w, h) = (spec.rig.width as usize, spec.rig.height as usize);
        let mut synth = Synthesizer::new(spec.clone(), 60, 4);
        let mut pipeline = Pipeline::new(spec.rig.clone(), config).expect("valid");
        let (mut vectors, mut stats) = (Vec::new(), FrameStats::default());
        let mut truth = std::collections::BTreeMap::new();
        for _ in 0..40 {
            let f = synth.next_frame();
            let out = pipeline
                .push(&frame(f.index, f.t_s, w, h, &f.left, &f.right))
                .expect("valid");
            truth.insert(f.index, f.truth);
            stats += &out.stats;
            vectors.extend(out.vectors);
        }
        let nearest_pid = |v: &VelocityVector| {
            truth[&v.frame_index]
                .iter()
                .min_by(|a, b| {
                    let d = |r: &crate::synth::TruthRow| (r.position - v.position_in_world).norm();
                    d(a).total_cmp(&d(b))
                })
                .map(|r| r.pid)
        };
        let tracks: std::collections::BTreeSet<u64> = vectors.iter().map(|v| v.track_id).collect();
        let particles: std::collections::BTreeSet<u64> =
            vectors.iter().filter_map(nearest_pid).collect();
        FlumeRun {
            tracks: tracks.len(),
            particles: particles.len(),
            vectors,
            stats,
        }
    }

    #[test]
    fn tracks_first_find_their_particles_and_measure_them_as_well_as_the_chain() {
        let mut chain_config = PipelineConfig::default();
        chain_config.tracks.track_first = false;
        let chain = flume_run(chain_config);
        let first = flume_run(PipelineConfig::default());
        assert!(PipelineConfig::default().tracks.track_first, "the default");
        let truth = match ScenarioSpec::new(Scenario::Flume).flow {
            crate::synth::Flow::Uniform(v) => v,
            other => panic!("the flume's flow is uniform: {other:?}"),
        };
        let rms = |vectors: &[VelocityVector]| {
            let sq: f64 = vectors
                .iter()
                .map(|v| (v.velocity_in_world - truth).norm_squared())
                .sum();
            (sq / vectors.len() as f64).sqrt() / truth.norm()
        };
        let (stats, chain_stats) = (first.stats, chain.stats);
        assert_eq!(chain_stats.predicted, 0, "the chain predicts nothing");
        assert!(stats.predicted > 1000, "{stats:?}");
        assert!(stats.found * 10 > stats.predicted * 9, "{stats:?}");
        eprintln!(
            "chain: {} vectors on {} tracks of {} particles, {:.3} % rms; \
             tracks first: {} on {} of {}, {:.3} %",
            chain.vectors.len(),
            chain.tracks,
            chain.particles,
            100.0 * rms(&chain.vectors),
            first.vectors.len(),
            first.tracks,
            first.particles,
            100.0 * rms(&first.vectors)
        );
        assert!(
            first.vectors.len() >= chain.vectors.len(),
            "no fewer vectors"
        );
        assert!(first.particles >= chain.particles, "no fewer particles");
        // Tracks per particle: a particle followed in more pieces is a broken track.
        assert!(
            first.tracks * chain.particles * 100 <= chain.tracks * first.particles * 105,
            "hardly more broken tracks"
        );
        assert!(
            rms(&first.vectors) <= 1.1 * rms(&chain.vectors),
            "no less accurate"
        );
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
