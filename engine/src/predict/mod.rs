//! Track-first step 1: every live 3D track predicts where its particle is at the new frame's
//! time, in the world frame (so head motion is no prediction error), from its own recent
//! samples; the frame's pose and the rectification carry the prediction into both images.
//!
//! Three models predict: a line through the last few samples, a quadratic through a few more,
//! and the quadratic through the newest three (a path turning by a large angle per frame
//! leaves a quadratic over six samples behind). Each track scores all three against where its
//! particle was then found and follows the one that has missed least (a vortex's curved path
//! wants a quadratic, a noisy straight one the line); before its first prediction it scores
//! them on its own newest samples, each predicted from the ones before it. The newest three
//! samples extrapolate their noise about four times over, so a noisy track would follow them
//! now and then by chance alone: they are followed only where the flow turns, where at least a
//! quarter of the tracks have missed less with them than with either other model.
//! Its search radius is a few times its own mean miss in the images, learnt the same way; a
//! track that has not been scored yet borrows the scene's.
//!
//! A track predicts itself once it has [`MIN_SAMPLES`] samples, or from its third sample where
//! its motion agrees with its mature neighbours' ([`neighbours`]): a young ghost does not.
//! Younger still (one or two samples: a new stereo pair), it is carried by its neighbours' flow
//! where it lies among them, and is looked for there like any other track: a hypothesis that
//! time settles, in 3D, where the chain would link it per camera.

use std::collections::VecDeque;

use nalgebra::{Isometry3, Point3};
use rayon::prelude::*;

use crate::geometry::{RectPoint, Rectification};
use crate::spatial::median;
use crate::tracks::{Sample, Track3d};
use crate::velocity::fit::{fit_line, quadratic_position};

mod neighbours;
use neighbours::{Neighbours, YOUNG_SAMPLES};

/// Samples a track needs before it predicts itself unvouched; below that the per-frame chain
/// carries it unless its neighbours vouch for it. A prediction keeps finding what resembles its
/// particle, so a track adopted too young on its own word may be a ghost pair the chain would
/// have dropped: in dense seeding a few of those last five frames, almost none eight.
const MIN_SAMPLES: usize = 8;
/// Samples the line is fitted to: enough to average centroid noise, few enough to turn.
const LINE_SAMPLES: usize = 4;
/// Samples the quadratic is fitted to.
const QUADRATIC_SAMPLES: usize = 6;
/// A found particle lies within this many of its track's miss sigmas of the prediction.
const GATE_SIGMAS: f64 = 4.0;
/// No search radius is narrower: two particle images whose centres are closer than a pixel
/// are one detection, so a narrower gate would only lose particles to centroid noise.
const MIN_GATE_PX: f64 = 1.0;
/// Weight of the newest miss in a track's running means.
const MISS_WEIGHT: f64 = 0.3;
/// Newest samples a track that has never been scored predicts from the samples before each,
/// to choose its model before its first prediction.
const HINDCAST_SAMPLES: usize = 4;

/// The models a track predicts with.
const LINE: usize = 0;
const QUADRATIC: usize = 1;
const TURNING: usize = 2;
const MODELS: usize = 3;
/// Samples the turning model is the quadratic through: the fewest that follow a turn.
const TURNING_SAMPLES: usize = 3;
/// The share of scored tracks that must have missed less with the turning model for the flow
/// to be taken as turning: a quarter, as a vortex's slow centre or a shear's slow side may
/// hold most of them. In a straight flow (noise alone) under a twentieth of them do.
const TURNING_SHARE: f64 = 0.25;
/// Tracks scored on every model needed to tell whether the flow turns.
const TURNING_TEACHERS: usize = 8;

/// What a track has learnt of how well it predicts itself.
#[derive(Debug, Clone, Default)]
pub(crate) struct Predictor {
    /// Running mean squared 3D miss of each model, metres squared.
    miss_sq_m: [Option<f64>; MODELS],
    /// Running mean squared miss of the followed model in the images, rectified pixels squared.
    miss_sq_px: Option<f64>,
    /// The last prediction of each model, and the frame it was for, to be scored when found.
    pending: Option<(u64, [Option<Point3<f64>>; MODELS])>,
}

impl Predictor {
    /// The track's own miss sigma in the images, once it has one.
    pub(crate) fn sigma_px(&self) -> Option<f64> {
        self.miss_sq_px.map(f64::sqrt)
    }

    /// Scores this frame's predictions against where the particle was found: `sample`, at
    /// `miss_px` rectified pixels (both cameras together) from the followed prediction where
    /// the prediction found it (none where the per-camera chain did: only the models' misses
    /// in the world are scored then).
    pub(crate) fn score(&mut self, sample: &Sample, miss_px: Option<f64>) {
        let Some((seq, predicted)) = self.pending.take() else {
            return;
        };
        if seq != sample.seq {
            return;
        }
        for (model, p) in predicted.iter().enumerate() {
            if let Some(p) = p {
                let miss = (p - sample.point_in_world).norm_squared();
                self.miss_sq_m[model] = Some(running_mean(self.miss_sq_m[model], miss));
            }
        }
        if let Some(miss_px) = miss_px {
            self.miss_sq_px = Some(running_mean(self.miss_sq_px, miss_px * miss_px));
        }
    }

    /// Scores the models on the track's own newest samples ([`HINDCAST_SAMPLES`]), each
    /// predicted from the samples before it, where none has been scored yet: a track's
    /// first prediction then follows the model that fits its path (a line from a vortex's
    /// curve misses by its whole bend, and claims whatever lies there).
    fn hindcast(&mut self, samples: &VecDeque<Sample>) {
        if self.miss_sq_m != [None; MODELS] {
            return;
        }
        // Each hindcast sample is predicted from the models' samples before it.
        let history = newest(samples, HINDCAST_SAMPLES + QUADRATIC_SAMPLES);
        for k in history.len().saturating_sub(HINDCAST_SAMPLES).max(2)..history.len() {
            let (t_s, at) = history[k];
            for (model, p) in models_at(&history[..k], t_s).iter().enumerate() {
                if let Some(p) = p {
                    let miss = (p - at).norm_squared();
                    self.miss_sq_m[model] = Some(running_mean(self.miss_sq_m[model], miss));
                }
            }
        }
    }

    /// The model to follow: the one that has missed least, the line until another has; the
    /// turning model only where the flow `turns`.
    fn followed(&self, turns: bool) -> usize {
        let offered = if turns { MODELS } else { TURNING };
        (QUADRATIC..offered).fold(LINE, |best, model| {
            match (self.miss_sq_m[model], self.miss_sq_m[best]) {
                (Some(miss), Some(least)) if miss < least => model,
                _ => best,
            }
        })
    }

    /// Whether the turning model has missed less than both others, once all are scored.
    fn turns(&self) -> Option<bool> {
        self.miss_sq_m
            .iter()
            .all(Option::is_some)
            .then(|| self.followed(true) == TURNING)
    }
}

fn running_mean(mean: Option<f64>, value: f64) -> f64 {
    mean.map_or(value, |m| m + MISS_WEIGHT * (value - m))
}

/// One track's prediction for the new frame.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Prediction {
    /// The track's key among the live tracks.
    pub(crate) key: u64,
    /// Its projection into the rectified left image.
    pub(crate) left: RectPoint,
    /// Its projection into the rectified right image.
    pub(crate) right: RectPoint,
    /// How far from the projections, rectified pixels, its particle may be found.
    pub(crate) gate_px: f64,
}

impl Prediction {
    /// Its projection into camera `camera`'s rectified image (0: left, 1: right).
    pub(crate) fn at(&self, camera: usize) -> RectPoint {
        if camera == 0 {
            self.left
        } else {
            self.right
        }
    }
}

/// Tracks per parallel task: a track's prediction takes about a microsecond, and a task
/// handed to the other core pays for its waking.
pub(super) const TRACKS_PER_TASK: usize = 128;

/// Predicts every live track (unseen for at most `max_gap_frames`) of at least
/// [`MIN_SAMPLES`] samples, or of fewer that moves as its neighbours do, at frame `seq`, time
/// `t_s`, seen from pose `world_from_rig`. A track with no miss sigma of its own uses the
/// median of those that have one, or else the particle images' radius `image_radius_px`; no
/// gate is wider than that radius (a detection farther from the prediction than its own
/// radius is another blob).
pub(crate) fn predict<'a>(
    tracks: impl Iterator<Item = (u64, &'a mut Track3d)>,
    seq: u64,
    t_s: f64,
    world_from_rig: &Isometry3<f64>,
    rect: &Rectification,
    max_gap_frames: u64,
    image_radius_px: f64,
) -> Vec<Prediction> {
    let rig_from_world = world_from_rig.inverse();
    let recent: Vec<(u64, &mut Track3d)> = tracks
        .filter(|(_, t)| seq - t.last_seq() <= max_gap_frames + 1)
        .collect();
    let views: Vec<&Track3d> = recent.iter().map(|(_, t)| &**t).collect();
    let neighbours = Neighbours::of(&views, MIN_SAMPLES, rect.focal_px);
    let turns = flow_turns(&views);
    let widest = image_radius_px.max(MIN_GATE_PX);
    // Each track predicts on its own: both cores where they hold tracks enough (see
    // [`TRACKS_PER_TASK`]), in the tracks' order.
    let predicted: Vec<(Prediction, Option<f64>)> = recent
        .into_par_iter()
        .with_min_len(TRACKS_PER_TASK)
        .enumerate()
        .filter_map(|(i, (key, track))| {
            let p = predict_one(track, i, (&neighbours, widest, turns), (seq, t_s))?;
            let (left, right) = rect.project(&(rig_from_world * p))?;
            let prediction = Prediction {
                key,
                left,
                right,
                gate_px: 0.0,
            };
            Some((prediction, track.predictor.sigma_px()))
        })
        .collect();
    let mut own: Vec<f64> = predicted.iter().filter_map(|(_, s)| *s).collect();
    let scene_sigma_px = if own.is_empty() {
        image_radius_px
    } else {
        median(&mut own)
    };
    predicted
        .into_iter()
        .map(|(p, sigma)| {
            let gate_px = GATE_SIGMAS * sigma.unwrap_or(scene_sigma_px);
            Prediction {
                gate_px: gate_px.clamp(MIN_GATE_PX, widest),
                ..p
            }
        })
        .collect()
}

/// Whether the flow turns: at least [`TURNING_SHARE`] of the `tracks` scored on every model
/// have missed less with the turning model than with either other.
fn flow_turns(tracks: &[&Track3d]) -> bool {
    let verdicts: Vec<bool> = tracks.iter().filter_map(|t| t.predictor.turns()).collect();
    let turning = verdicts.iter().filter(|&&turns| turns).count();
    verdicts.len() >= TURNING_TEACHERS && turning as f64 >= TURNING_SHARE * verdicts.len() as f64
}

/// Where a track (the `own`-th the `neighbours` were built from) puts its particle at
/// frame `seq`, time `t_s`, in the world, if it predicts at all: trusted on its own samples
/// or vouched for by its neighbours, or carried by their flow where that flow predicts its
/// neighbours within `widest_px` (the widest gate); the turning model is followed only where
/// the flow `turns`. The predictions it makes are kept to be scored when it is found.
fn predict_one(
    track: &mut Track3d,
    own: usize,
    (neighbours, widest_px, turns): (&Neighbours, f64, bool),
    (seq, t_s): (u64, f64),
) -> Option<Point3<f64>> {
    let n = track.samples.len();
    let trusted = n >= MIN_SAMPLES || (n >= YOUNG_SAMPLES && neighbours.vouch_for(track, own));
    let carried = (!trusted && n < YOUNG_SAMPLES)
        .then(|| neighbours.carry(track, own, t_s, widest_px))
        .flatten();
    if !trusted && carried.is_none() {
        return None;
    }
    let models = match carried {
        Some(p) => [Some(p), None, None],
        None => {
            track.predictor.hindcast(&track.samples);
            model_predictions(track, t_s)
        }
    };
    // A carried prediction is the neighbours' flow, not either model's: only its miss in the
    // images is the track's (it sets the next gate).
    let scored = if carried.is_some() {
        [None; MODELS]
    } else {
        models
    };
    track.predictor.pending = Some((seq, scored));
    models[track.predictor.followed(turns)].or(models[LINE])
}

/// Where the three models put the track's particle at `t_s`.
fn model_predictions(track: &Track3d, t_s: f64) -> [Option<Point3<f64>>; MODELS] {
    models_at(&newest(&track.samples, QUADRATIC_SAMPLES), t_s)
}

/// Where the line (through the newest [`LINE_SAMPLES`] of `history`, time and position), the
/// quadratic (through the newest [`QUADRATIC_SAMPLES`], once there are more than the line's)
/// and the turning model (the quadratic through the newest [`TURNING_SAMPLES`]) put a particle
/// at `t_s`.
fn models_at(history: &[(f64, Point3<f64>)], t_s: f64) -> [Option<Point3<f64>>; MODELS] {
    let n = history.len();
    let line = fit_line(&history[n.saturating_sub(LINE_SAMPLES)..], t_s).map(|f| f.position);
    let quadratic = (n > LINE_SAMPLES)
        .then(|| quadratic_position(&history[n.saturating_sub(QUADRATIC_SAMPLES)..], t_s))
        .flatten();
    let turning = (n >= TURNING_SAMPLES)
        .then(|| quadratic_position(&history[n - TURNING_SAMPLES..], t_s))
        .flatten();
    [line, quadratic, turning]
}

/// A track's newest `n` samples as (time, position in the world).
fn newest(samples: &VecDeque<Sample>, n: usize) -> Vec<(f64, Point3<f64>)> {
    let skip = samples.len().saturating_sub(n);
    samples
        .iter()
        .skip(skip)
        .map(|s| (s.t_s, s.point_in_world))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::detect::Separation;
    use crate::geometry::RectPoint;
    use crate::synth::{Scenario, ScenarioSpec};
    use nalgebra::Vector3;
    use std::collections::VecDeque;

    fn track(path: impl Fn(f64) -> Point3<f64>, frames: u64) -> Track3d {
        let samples = (1..=frames)
            .map(|seq| Sample {
                seq,
                frame_index: seq,
                t_s: seq as f64 * 0.1,
                point_in_world: path(seq as f64 * 0.1),
                depth_m: 0.5,
                separation: Separation::Clear,
                left_rect: RectPoint::default(),
                camera_in_world: Point3::origin(),
                seen_from: None,
            })
            .collect::<VecDeque<_>>();
        Track3d {
            samples,
            ..Track3d::new(1, 1)
        }
    }

    #[test]
    fn the_projection_is_what_triangulation_inverts() {
        let rig = ScenarioSpec::new(Scenario::HololensRaw).rig;
        let rect = Rectification::new(&rig).expect("rectifies");
        let point = Point3::new(0.03, -0.02, 0.45);
        let (l, r) = rect.project(&point).expect("in front");
        let back = rect.triangulate(l, r).expect("triangulates");
        assert!((back.point_in_rig - point).norm() < 1e-12, "{back:?}");
    }

    /// A track on a quadratic path, predicted for three more frames and scored each time
    /// against where its particle was, at `miss_px` from the prediction in the images (none:
    /// found by the chain).
    fn followed_on_a_curve(miss_px: Option<f64>) -> (Track3d, impl Fn(f64) -> Point3<f64>) {
        let path = |t: f64| Point3::new(0.1 * t, 0.5 * t * t, 0.5);
        let mut t = track(path, MIN_SAMPLES as u64);
        let rig = ScenarioSpec::new(Scenario::Flume).rig;
        let rect = Rectification::new(&rig).expect("rectifies");
        let pose = Isometry3::identity();
        for seq in MIN_SAMPLES as u64 + 1..MIN_SAMPLES as u64 + 4 {
            let at = seq as f64 * 0.1;
            let p = predict(std::iter::once((9, &mut t)), seq, at, &pose, &rect, 2, 2.0);
            assert_eq!(p.len(), 1);
            let sample = Sample {
                seq,
                t_s: at,
                point_in_world: path(at),
                ..t.samples[0].clone()
            };
            t.predictor.score(&sample, miss_px);
            t.samples.push_back(sample);
        }
        (t, path)
    }

    #[test]
    fn a_curved_path_is_followed_by_the_quadratic_once_it_has_missed_less() {
        let (t, path) = followed_on_a_curve(Some(0.5));
        assert_eq!(t.predictor.followed(false), QUADRATIC);
        let models = model_predictions(&t, 1.5);
        let miss = (models[QUADRATIC].expect("fitted") - path(1.5)).norm();
        assert!(miss < 1e-9, "a quadratic path is predicted exactly: {miss}");
        assert!((t.predictor.sigma_px().expect("scored") - 0.5).abs() < 1e-12);
    }

    #[test]
    fn a_track_on_a_curve_follows_the_quadratic_from_its_first_prediction() {
        // Never scored: its own newest samples, each predicted from those before it, show the
        // line missing the bend.
        let path = |t: f64| Point3::new(0.1 * t, 0.5 * t * t, 0.5);
        let mut t = track(path, MIN_SAMPLES as u64);
        let rig = ScenarioSpec::new(Scenario::Flume).rig;
        let rect = Rectification::new(&rig).expect("rectifies");
        let seq = MIN_SAMPLES as u64 + 1;
        let at = seq as f64 * 0.1;
        let pose = Isometry3::identity();
        let p = predict(std::iter::once((9, &mut t)), seq, at, &pose, &rect, 2, 2.0);
        assert_eq!(t.predictor.followed(false), QUADRATIC);
        let (left, _) = rect.project(&path(at)).expect("in front");
        let miss = (p[0].left.x - left.x).hypot(p[0].left.y - left.y);
        assert!(miss < 1e-6, "{miss} px");
    }

    /// Particles on circles about the same axis, `turn` radians a frame (0.1 s), their
    /// positions off by `noise_m` (a fixed pseudo-random pattern); `count` tracks of
    /// [`MIN_SAMPLES`] samples, each scored on its own newest samples.
    fn circling(count: usize, turn: f64, noise_m: f64) -> Vec<Track3d> {
        (0..count)
            .map(|k| {
                let (radius, phase) = (0.03 + 0.004 * k as f64, k as f64);
                // A hash of the time: uncorrelated from one sample to the next.
                let jitter = move |t: f64| {
                    let h = ((t * 129.898 + k as f64 * 78.233).sin() * 43_758.545).fract();
                    2.0 * h * noise_m
                };
                let path = move |t: f64| {
                    let angle = phase + turn * t / 0.1;
                    let n = jitter(t);
                    Point3::new(radius * angle.cos() + n, radius * angle.sin() - n, 0.5 + n)
                };
                let mut t = track(path, MIN_SAMPLES as u64);
                t.predictor.hindcast(&t.samples);
                t
            })
            .collect()
    }

    #[test]
    fn where_the_flow_turns_fast_tracks_follow_the_quadratic_through_their_newest_samples() {
        let tracks = circling(10, 0.4, 0.0);
        let views: Vec<&Track3d> = tracks.iter().collect();
        assert!(flow_turns(&views));
        for t in &tracks {
            assert_eq!(t.predictor.followed(true), TURNING);
            // Left to the other two, the track would follow the quadratic over six samples,
            // which a turn of 0.4 rad a frame leaves behind.
            assert_eq!(t.predictor.followed(false), QUADRATIC);
        }
    }

    #[test]
    fn where_tracks_only_scatter_the_flow_does_not_turn() {
        // Slow circles with centroid noise: the newest three samples extrapolate the noise
        // fourfold, and the line through four misses least.
        let tracks = circling(20, 0.02, 0.001);
        let views: Vec<&Track3d> = tracks.iter().collect();
        let turning = tracks.iter().filter(|t| t.predictor.turns() == Some(true));
        let n = turning.count();
        assert!(n < 5, "{n} of 20 tracks follow the turning model");
        assert!(!flow_turns(&views));
        // Too few tracks tell nothing.
        let fast = circling(TURNING_TEACHERS - 1, 0.4, 0.0);
        assert!(!flow_turns(&fast.iter().collect::<Vec<_>>()));
    }

    #[test]
    fn particles_the_chain_finds_teach_the_model_but_not_the_gate() {
        let (t, _) = followed_on_a_curve(None);
        assert_eq!(t.predictor.followed(false), QUADRATIC);
        assert_eq!(t.predictor.sigma_px(), None);
    }

    #[test]
    fn gates_come_from_misses_and_stay_within_a_pixel_and_the_image_radius() {
        let rig = ScenarioSpec::new(Scenario::Flume).rig;
        let rect = Rectification::new(&rig).expect("rectifies");
        let path = |t: f64| Point3::from(Vector3::new(0.1, 0.0, 0.0) * t + Vector3::z() * 0.5);
        let n = MIN_SAMPLES as u64;
        let (mut a, mut b) = (track(path, n), track(path, n));
        b.predictor.miss_sq_px = Some(0.25);
        let pose = Isometry3::identity();
        let gates = |tracks: Vec<(u64, &mut Track3d)>, seq: u64, radius_px: f64| {
            predict(
                tracks.into_iter(),
                seq,
                0.1 * seq as f64,
                &pose,
                &rect,
                2,
                radius_px,
            )
            .iter()
            .map(|p| p.gate_px)
            .collect::<Vec<_>>()
        };
        // The unscored track borrows the scored one's sigma: 4 x 0.5 px.
        assert_eq!(
            gates(vec![(1, &mut a), (2, &mut b)], n + 1, 9.0),
            [2.0, 2.0]
        );
        // Alone, it starts from the image radius, here within the one-pixel floor...
        assert_eq!(gates(vec![(1, &mut a)], n + 1, 0.1), [MIN_GATE_PX]);
        // ... and no gate is wider than the particle images' radius.
        assert_eq!(gates(vec![(2, &mut b)], n + 1, 1.5), [1.5]);
        // A track unseen for longer than the gap it may coast over predicts nothing.
        assert!(gates(vec![(1, &mut a)], n + 4, 1.0).is_empty());
    }
}
