//! Stage 4: 3D tracks. Each frame's stereo pairs, triangulated, continue the 3D tracks of their
//! camera tracks; a pair no live 3D track continues is a new particle, unless it lies where a
//! broken 3D track's recent path predicts, or where the flow around a young one carries it
//! (`rejoin`, `flow`). A 3D track survives a gap as long as its
//! left camera track coasts, and is then retired and kept the `M` frames its last samples may
//! still centre a velocity window on.

use std::collections::{BTreeMap, VecDeque};

use nalgebra::{Point3, Vector3};
use serde::{Deserialize, Serialize};

use crate::config::{check_non_negative, ConfigError};
use crate::detect::Separation;
use crate::geometry::{RectPoint, Rectification};
use crate::pipeline::{MatchedPoint, PipelineConfig};
use crate::predict::Predictor;
use crate::shake::refine::Shape;
use crate::spatial::{median, PointGrid, GRID_CELL_PX};

mod consensus;
mod flow;
mod rejoin;
mod turn;

/// How broken 3D tracks are rejoined (the file keeps these keys in `[link]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct TrackConfig {
    /// Frames a 3D track may go without a stereo pair and still be continued by a new one (a
    /// new track in either camera, or a new partner): the new pair must lie where the track's
    /// recent path in the world predicts, within `rejoin_tolerance_px` across the line of sight
    /// and `rejoin_tolerance_sigmas` depth-noise sigmas along it. A per-camera track breaks
    /// where particles cross or crowd; without this its 3D track, and the velocity window,
    /// ended there. 0 keeps a 3D track only while both camera tracks go on (the method).
    pub rejoin_frames: u32,
    /// How far across the line of sight a rejoining pair may lie from the prediction, pixels:
    /// the floor; a fast particle may lie as far off as the tracks' paths are seen to turn in
    /// a frame.
    pub rejoin_tolerance_px: f64,
    /// How far along the line of sight, in depth-noise sigmas (`velocity.disparity_sigma_px`).
    pub rejoin_tolerance_sigmas: f64,
    /// Track first (the default): every 3D track of eight samples or more (or of three that
    /// moves as its mature neighbours do) predicts its particle in the new frame and takes the
    /// detections nearest its projections in both images (learnt gates), before the
    /// per-camera chain (2D linking, stereo matching) runs on the detections no track
    /// explains. False: the chain alone (the method's frame loop).
    pub track_first: bool,
}

impl Default for TrackConfig {
    fn default() -> Self {
        Self {
            rejoin_frames: 2,
            rejoin_tolerance_px: 3.0,
            rejoin_tolerance_sigmas: 12.0,
            track_first: true,
        }
    }
}

impl TrackConfig {
    /// The published method: a 3D track lives only while both its camera tracks do.
    pub fn method() -> Self {
        Self {
            rejoin_frames: 0,
            track_first: false,
            ..Self::default()
        }
    }

    /// Refuses values no run can use, naming the key as the config file spells it.
    pub fn validate(&self) -> Result<(), ConfigError> {
        check_non_negative(
            "link",
            &[
                ("rejoin_tolerance_px", self.rejoin_tolerance_px),
                ("rejoin_tolerance_sigmas", self.rejoin_tolerance_sigmas),
            ],
        )
    }
}

/// One triangulated particle of one frame, as a 3D track holds it.
#[derive(Debug, Clone)]
pub(crate) struct Sample {
    /// Position in the sequence of pushed frames (frame indices may skip).
    pub(crate) seq: u64,
    pub(crate) frame_index: u64,
    pub(crate) t_s: f64,
    pub(crate) point_in_world: Point3<f64>,
    pub(crate) depth_m: f64,
    /// The less exact of the two cameras' separations: what the sample is good for.
    pub(crate) separation: Separation,
    /// Where the left camera saw it, rectified: how far the particle moves in the image.
    pub(crate) left_rect: RectPoint,
    /// The left camera's centre when it did: the line of sight, along which noise is largest.
    pub(crate) camera_in_world: Point3<f64>,
    /// For a particle one camera hid ([`Separation::Hidden`]) and the other told apart: where
    /// that one saw it from. Across its line of sight the sample is measured; along it, only
    /// predicted.
    pub(crate) seen_from: Option<Sight>,
}

/// The camera that alone saw a sample's particle: its centre (world frame) and how it told the
/// particle apart from its neighbours.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Sight {
    pub(crate) camera_in_world: Point3<f64>,
    pub(crate) separation: Separation,
}

impl Sample {
    /// An offset from this sample split along the left camera's line of sight (signed, where
    /// depth noise is largest) and across it (squared length, where centroid noise is).
    pub(crate) fn along_and_across_sq(&self, offset: &Vector3<f64>) -> (f64, f64) {
        let sight = (self.point_in_world - self.camera_in_world)
            .try_normalize(1e-12)
            .unwrap_or_else(Vector3::z);
        let along = offset.dot(&sight);
        (along, (offset.norm_squared() - along * along).max(0.0))
    }
}

/// A particle's 3D track: its samples of the recent frames, oldest first.
#[derive(Debug, Clone)]
pub(crate) struct Track3d {
    pub(crate) id: u64,
    /// The right camera track it is paired with now.
    pub(crate) right_track: u64,
    pub(crate) samples: VecDeque<Sample>,
    /// How well it predicts itself (track-first).
    pub(crate) predictor: Predictor,
    /// Its particle's image shape in the left and right cameras, learnt where it stood alone
    /// (track-first).
    pub(crate) shapes: [Option<Shape>; 2],
}

impl Track3d {
    /// A new track `id`, paired with right camera track `right_track`, with no samples yet.
    pub(crate) fn new(id: u64, right_track: u64) -> Self {
        Self {
            id,
            right_track,
            samples: VecDeque::new(),
            predictor: Predictor::default(),
            shapes: [None; 2],
        }
    }

    /// The frame sequence number of its newest sample.
    pub(crate) fn last_seq(&self) -> u64 {
        self.samples.back().map_or(0, |s| s.seq)
    }
}

/// A stereo pair of this frame, triangulated: the camera tracks it belongs to, the sample it
/// gives and the point it is reported as.
pub(crate) struct Pair {
    pub(crate) left_track: u64,
    pub(crate) right_track: u64,
    pub(crate) sample: Sample,
    pub(crate) point: MatchedPoint,
}

/// The keys of tracks continued by their own predictions where no camera track carries them
/// (found in one image only, or their left camera track leads another 3D track): apart from
/// every camera track id.
const FOUND_KEYS: u64 = 1 << 63;

/// A track's particle as its prediction found it this frame.
pub(crate) struct FoundSample {
    /// The track's key among the live tracks.
    pub(crate) key: u64,
    pub(crate) sample: Sample,
    /// How far from the prediction it was found, rectified pixels (both cameras together).
    pub(crate) miss_px: f64,
    pub(crate) point: MatchedPoint,
    /// The camera tracks (left, right) of the detections it was found at, where both images
    /// showed it.
    pub(crate) camera_tracks: Option<(u64, u64)>,
}

/// Samples from which a track has a path of its own: a younger one is carried by the flow
/// around it (`rejoin`); an older one continued into a frame took a known step, which is not
/// put to its neighbours' vote but votes itself (`consensus`).
const PATH_SAMPLES: usize = 3;

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

/// What the 3D tracks take from the other stages' settings.
#[derive(Debug, Clone, Copy)]
struct Limits {
    /// Frames a left camera track may coast (`link.max_gap_frames`).
    max_gap_frames: u64,
    /// Frames of history kept behind a track's newest sample (what velocity windows reach).
    history_frames: u64,
    /// Frames a retired track is kept (M: its last samples may still centre a window).
    retired_frames: u64,
    /// A left track that changes partner starts a new 3D track (`stereo.pair_memory` > 0).
    partner_defines_track: bool,
    /// Largest per-frame image motion of a track's first steps (`link.max_displacement_px`).
    max_displacement_px: f64,
    /// Disparity noise of the depth model (`velocity.disparity_sigma_px`).
    disparity_sigma_px: f64,
}

/// The 3D tracks: live ones keyed by their left camera track, and retired ones still in reach
/// of a velocity window.
#[derive(Debug, Clone)]
pub(crate) struct Tracks {
    config: TrackConfig,
    limits: Limits,
    live: BTreeMap<u64, Track3d>,
    retired: Vec<Track3d>,
    next_id: u64,
    /// How far the tracks' paths turn per frame (what a rejoin allows for).
    turns: turn::Turns,
    /// How much neighbouring particles' steps differ per metre between them, as the last flow
    /// showed: what their votes on each other's steps allow for.
    flow_gradient: Option<f64>,
}

impl Tracks {
    /// No tracks yet, with the settings of `config`.
    pub(crate) fn new(config: &PipelineConfig) -> Self {
        let v = &config.velocity;
        let m = v.half_window_frames;
        Self {
            config: config.tracks.clone(),
            limits: Limits {
                max_gap_frames: u64::from(config.link.max_gap_frames),
                history_frames: (m + m.max(v.line_past_frames)) as u64,
                retired_frames: m as u64,
                partner_defines_track: config.stereo.pair_memory != 0.0,
                max_displacement_px: config.link.max_displacement_px,
                disparity_sigma_px: v.disparity_sigma_px,
            },
            live: BTreeMap::new(),
            retired: Vec::new(),
            next_id: 0,
            turns: turn::Turns::default(),
            flow_gradient: None,
        }
    }

    /// Live tracks, then retired ones.
    pub(crate) fn all(&self) -> impl Iterator<Item = &Track3d> {
        self.live.values().chain(&self.retired)
    }

    /// How many tracks are live.
    pub(crate) fn live_count(&self) -> usize {
        self.live.len()
    }

    /// The live tracks, by key, to be predicted.
    pub(crate) fn live_mut(&mut self) -> impl Iterator<Item = (u64, &mut Track3d)> {
        self.live.iter_mut().map(|(k, t)| (*k, t))
    }

    /// The particle image shapes the live track under `key` has learnt (none for another key).
    pub(crate) fn shapes(&self, key: u64) -> [Option<Shape>; 2] {
        self.live.get(&key).map_or([None; 2], |t| t.shapes)
    }

    /// Whether the live track under `key` should learn its shapes again: when the samples it
    /// keeps (at most the history a velocity window reaches) number a multiple of `every`, so
    /// that a particle that has moved in depth since it was first learnt keeps its shape. A
    /// track keeps a bounded history, so a steady one relearns only while its history fills
    /// (with the default settings at its 10th and 20th samples), and one whose history has a
    /// gap at every frame the count stays on a multiple.
    pub(crate) fn relearns(&self, key: u64, every: usize) -> bool {
        self.live
            .get(&key)
            .is_some_and(|t| t.samples.len() % every == 0)
    }

    /// Sets the shapes of the live track under `key`.
    pub(crate) fn set_shapes(&mut self, key: u64, shapes: [Option<Shape>; 2]) {
        if let Some(t) = self.live.get_mut(&key) {
            t.shapes = shapes;
        }
    }

    /// How many of the live track's newest samples under `key` in a row are hidden in one
    /// image ([`Separation::Hidden`]).
    pub(crate) fn hidden_run(&self, key: u64) -> usize {
        self.live.get(&key).map_or(0, |t| {
            t.samples
                .iter()
                .rev()
                .take_while(|s| s.separation == Separation::Hidden)
                .count()
        })
    }

    /// Frames a live track may go unseen and still be continued.
    pub(crate) fn max_gap_frames(&self) -> u64 {
        self.limits.max_gap_frames
    }

    /// Continues the tracks whose particles their predictions found this frame (each point
    /// appended to `points`, or to `partial_points` where one image hid the particle). A track
    /// found in both images goes on under the camera tracks of the detections it was found at,
    /// as a stereo pair of them would: where its next prediction misses a particle the
    /// per-camera chain still links, the chain's pair continues it. No pair of this frame can
    /// continue it a second time: its detections were claimed.
    pub(crate) fn take_found(
        &mut self,
        found: Vec<FoundSample>,
        (points, partial_points): (&mut Vec<MatchedPoint>, &mut Vec<MatchedPoint>),
    ) {
        for FoundSample {
            key,
            sample,
            miss_px,
            point,
            camera_tracks,
        } in found
        {
            let Some(mut track) = self.live.remove(&key) else {
                continue;
            };
            track.predictor.score(&sample, Some(miss_px));
            self.turns.learn(&track, &sample);
            // A particle hidden in one image was not matched: it is no stereo point.
            let to = if sample.separation == Separation::Hidden {
                &mut *partial_points
            } else {
                &mut *points
            };
            to.push(MatchedPoint {
                track_id: track.id,
                ..point
            });
            push_sample(&mut track, sample, self.limits.history_frames);
            let key = match camera_tracks {
                Some((l, r)) if !self.live.contains_key(&l) => {
                    track.right_track = r;
                    l
                }
                _ => FOUND_KEYS | track.id,
            };
            self.live.insert(key, track);
        }
    }

    /// The depths of the live tracks seen in frame `seq` for at least `samples` samples.
    pub(crate) fn confirmed_depths(
        &self,
        seq: u64,
        samples: usize,
    ) -> impl Iterator<Item = f64> + '_ {
        self.live.values().filter_map(move |t| {
            let last = t.samples.back()?;
            (last.seq == seq && t.samples.len() >= samples).then_some(last.depth_m)
        })
    }

    /// Takes frame `seq`'s pairs (time `t_s`) into the tracks; appends each pair's point, with
    /// its 3D track, to `points`, and returns how many pairs rejoined a broken track.
    pub(crate) fn update(
        &mut self,
        seq: u64,
        t_s: f64,
        pairs: Vec<Pair>,
        rect: &Rectification,
        points: &mut Vec<MatchedPoint>,
    ) -> usize {
        let mut continued = BTreeMap::new();
        let mut births: Vec<Pair> = Vec::new();
        let mut orphans: Vec<(Orphan, Track3d)> = Vec::new();
        for pair in pairs {
            match self.live.remove(&pair.left_track) {
                // Without track-consistent pairing (the method) a left track keeps its 3D track
                // whatever its partner; with it, a new partner means a new particle.
                Some(track)
                    if track.right_track == pair.right_track
                        || !self.limits.partner_defines_track =>
                {
                    self.extend(track, pair, points, &mut continued);
                }
                dropped => {
                    if let Some(track) = dropped {
                        orphans.push((Orphan::Replaced(pair.left_track), track));
                    }
                    births.push(pair);
                }
            }
        }
        if self.config.rejoin_frames > 0 && !births.is_empty() {
            self.gather_recent_orphans(seq, &mut orphans);
        }
        let rejoined =
            self.settle_births(births, orphans, (seq, t_s), rect, points, &mut continued);
        self.retire_unseen(seq, continued);
        rejoined
    }

    /// Adds a pair's sample to `track` (its partner now the pair's) and keeps the track among
    /// this frame's `continued`, under the pair's left track.
    fn extend(
        &mut self,
        mut track: Track3d,
        pair: Pair,
        points: &mut Vec<MatchedPoint>,
        continued: &mut BTreeMap<u64, Track3d>,
    ) {
        track.right_track = pair.right_track;
        // A particle the chain found where the track's prediction missed it teaches the
        // predictor too: scored only on what its prediction found, a track on a turning path
        // would never learn that its quadratic follows it better than its line.
        track.predictor.score(&pair.sample, None);
        self.turns.learn(&track, &pair.sample);
        points.push(MatchedPoint {
            track_id: track.id,
            ..pair.point
        });
        push_sample(&mut track, pair.sample, self.limits.history_frames);
        continued.insert(pair.left_track, track);
    }

    /// Moves the live tracks that a new pair may still rejoin (unseen for at most
    /// `rejoin_frames`) and the recently retired ones into `orphans`.
    fn gather_recent_orphans(&mut self, seq: u64, orphans: &mut Vec<(Orphan, Track3d)>) {
        let reach = u64::from(self.config.rejoin_frames) + 1;
        for (left_track, track) in std::mem::take(&mut self.live) {
            if seq - track.last_seq() <= reach && track.last_seq() != seq {
                orphans.push((Orphan::Coasting(left_track), track));
            } else {
                self.live.insert(left_track, track);
            }
        }
        let (recent, old): (Vec<Track3d>, Vec<Track3d>) = std::mem::take(&mut self.retired)
            .into_iter()
            .partition(|t| seq - t.last_seq() <= reach);
        self.retired = old;
        orphans.extend(recent.into_iter().map(|t| (Orphan::Retired, t)));
    }

    /// Gives each new pair the orphan it rejoins, or a new track; returns the orphans no pair
    /// took to where they came from, and counts the rejoined pairs. A young orphan is carried
    /// by the flow into this frame (frame `seq`, time `t_s`) where the flow is known.
    fn settle_births(
        &mut self,
        births: Vec<Pair>,
        orphans: Vec<(Orphan, Track3d)>,
        (seq, t_s): (u64, f64),
        rect: &Rectification,
        points: &mut Vec<MatchedPoint>,
        continued: &mut BTreeMap<u64, Track3d>,
    ) -> usize {
        let flow = (self.config.rejoin_frames > 0 && !births.is_empty())
            .then(|| self.flow_into(seq, &births, &orphans, continued, rect));
        if let Some(gradient) = flow.as_ref().and_then(flow::Flow::gradient) {
            self.flow_gradient = Some(gradient);
        }
        let joins = rejoin::rejoin(
            (&self.config, &self.limits, &self.turns),
            rect,
            flow.as_ref(),
            &births,
            &orphans,
            t_s,
        );
        let rejoined = joins.iter().flatten().count();
        let mut orphans: Vec<Option<(Orphan, Track3d)>> = orphans.into_iter().map(Some).collect();
        for (birth, join) in births.into_iter().zip(joins) {
            let track = match join.and_then(|j| rejoin::take_joined(&mut orphans, j)) {
                Some(track) => track,
                None => {
                    self.next_id += 1;
                    Track3d::new(self.next_id, birth.right_track)
                }
            };
            self.extend(track, birth, points, continued);
        }
        for (kind, track) in orphans.into_iter().flatten() {
            match kind {
                Orphan::Coasting(left_track) => {
                    self.live.insert(left_track, track);
                }
                Orphan::Replaced(_) | Orphan::Retired => self.retired.push(track),
            }
        }
        rejoined
    }

    /// The flow into frame `seq` by neighbour consensus among every particle seen in the frame
    /// before (live tracks, `continued` ones and `orphans`) and in this one (`continued` and
    /// found tracks, and the `births`); a settled track's step is known.
    fn flow_into(
        &self,
        seq: u64,
        births: &[Pair],
        orphans: &[(Orphan, Track3d)],
        continued: &BTreeMap<u64, Track3d>,
        rect: &Rectification,
    ) -> flow::Flow {
        let seen = |s: &Sample| s.separation != Separation::Hidden;
        let mut before: Vec<&Sample> = Vec::new();
        let mut known = Vec::new();
        let mut after: Vec<&Sample> = Vec::new();
        for track in continued.values().chain(self.live.values()) {
            let newest = track.samples.back().filter(|s| s.seq == seq && seen(s));
            let previous = track
                .samples
                .iter()
                .rev()
                .find(|s| s.seq < seq)
                .filter(|s| s.seq + 1 == seq && seen(s));
            if let Some(newest) = newest {
                after.push(newest);
            }
            if let Some(previous) = previous {
                before.push(previous);
                let trusted = track.samples.len() >= PATH_SAMPLES;
                known.push((trusted && newest.is_some()).then(|| after.len() - 1));
            }
        }
        for (_, track) in orphans {
            if let Some(last) = track.samples.back().filter(|s| s.seq + 1 == seq && seen(s)) {
                before.push(last);
                known.push(None);
            }
        }
        after.extend(births.iter().map(|b| &b.sample).filter(|s| seen(s)));
        let after_grid = left_image_grid(&after);
        let steps = consensus::steps(
            (&before, &known),
            (&after, &after_grid),
            (self.limits.max_displacement_px, self.flow_gradient),
            rect,
            self.limits.disparity_sigma_px,
        );
        flow::Flow::of(
            steps.into_iter().map(|(i, j)| (before[i], after[j])),
            image_spacing_px(&after, &after_grid),
            rect,
            self.limits.disparity_sigma_px,
        )
    }

    /// Makes this frame's `continued` tracks the live ones. A live track unseen this frame
    /// survives a gap as long as its left track may coast; after that (or where its left track
    /// id now leads another 3D track) it is retired, and kept M frames for the centred vectors
    /// its last samples still give.
    fn retire_unseen(&mut self, seq: u64, mut continued: BTreeMap<u64, Track3d>) {
        for (left_track, track) in std::mem::take(&mut self.live) {
            if continued.contains_key(&left_track) {
                self.retired.push(track);
                continue;
            }
            if seq - track.last_seq() <= self.limits.max_gap_frames {
                continued.insert(left_track, track);
            } else {
                self.retired.push(track);
            }
        }
        self.live = continued;
        let kept = self.limits.retired_frames;
        self.retired.retain(|t| seq - t.last_seq() <= kept);
    }
}

/// `samples` indexed by where the left image saw them (rectified), each by its index.
fn left_image_grid(samples: &[&Sample]) -> PointGrid {
    PointGrid::new(samples.iter().map(|s| s.left_rect).zip(0..), GRID_CELL_PX)
}

/// The median distance in the left image from each of `samples` to its nearest neighbour
/// (`grid` indexes them by their left image points).
fn image_spacing_px(samples: &[&Sample], grid: &PointGrid) -> f64 {
    let mut distances: Vec<f64> = samples
        .iter()
        .enumerate()
        .filter_map(|(i, s)| {
            let nearest = grid.nearest(s.left_rect.x, s.left_rect.y, 1, i);
            Some(nearest.first()?.distance_sq(s.left_rect).sqrt())
        })
        .collect();
    median(&mut distances)
}

/// Appends `sample` to `track`, forgetting samples more than `history` frames older.
fn push_sample(track: &mut Track3d, sample: Sample, history: u64) {
    let oldest = sample.seq.saturating_sub(history);
    track.samples.push_back(sample);
    while track.samples.front().is_some_and(|s| s.seq < oldest) {
        track.samples.pop_front();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::{Scenario, ScenarioSpec};

    fn sample(seq: u64) -> Sample {
        Sample {
            seq,
            frame_index: seq,
            t_s: seq as f64 / 30.0,
            point_in_world: Point3::new(0.001 * seq as f64, 0.0, 0.5),
            depth_m: 0.5,
            separation: Separation::Clear,
            left_rect: RectPoint::default(),
            camera_in_world: Point3::origin(),
            seen_from: None,
        }
    }

    fn point() -> MatchedPoint {
        MatchedPoint {
            track_id: 0,
            point_in_world: Point3::origin(),
            left_px: Default::default(),
            right_px: Default::default(),
            depth_m: 0.5,
        }
    }

    fn pair(left_track: u64, right_track: u64, seq: u64) -> Pair {
        Pair {
            left_track,
            right_track,
            sample: sample(seq),
            point: point(),
        }
    }

    /// A track its prediction found in both images goes on under the camera tracks of the
    /// detections it was found at: the next frame's pair of those camera tracks continues it.
    #[test]
    fn a_track_found_by_its_prediction_is_continued_by_its_detections_camera_tracks() {
        let rig = ScenarioSpec::new(Scenario::Flume).rig;
        let rect = Rectification::new(&rig).expect("rectifies");
        let mut tracks = Tracks::new(&PipelineConfig::default());
        let mut points = Vec::new();
        tracks.update(1, sample(1).t_s, vec![pair(3, 4, 1)], &rect, &mut points);
        let (key, id) = {
            let (key, track) = tracks.live_mut().next().expect("a track");
            (key, track.id)
        };
        let found = FoundSample {
            key,
            sample: sample(2),
            miss_px: 0.3,
            point: point(),
            camera_tracks: Some((5, 6)),
        };
        tracks.take_found(vec![found], (&mut points, &mut Vec::new()));
        tracks.update(3, sample(3).t_s, vec![pair(5, 6, 3)], &rect, &mut points);
        let live: Vec<(u64, u64, usize)> = tracks
            .live_mut()
            .map(|(k, t)| (k, t.id, t.samples.len()))
            .collect();
        assert_eq!(live, vec![(5, id, 3)]);
    }

    /// A fast vortex whose particles all start new camera tracks in the second frame (each
    /// moved farther than the linking box): the flow their neighbours agree on carries every
    /// particle's track on.
    #[test]
    fn particles_whose_camera_tracks_all_broke_are_carried_on_by_the_flow() {
        let rig = ScenarioSpec::new(Scenario::Flume).rig;
        let rect = Rectification::new(&rig).expect("rectifies");
        let (before, after) = consensus::tests::vortex(&rect);
        let pairs = |samples: &[Sample], first_id: u64| -> Vec<Pair> {
            samples
                .iter()
                .zip(first_id..)
                .map(|(s, id)| Pair {
                    left_track: id,
                    right_track: id + 1000,
                    sample: s.clone(),
                    point: point(),
                })
                .collect()
        };
        let mut tracks = Tracks::new(&PipelineConfig::default());
        let mut points = Vec::new();
        let t = |s: &[Sample]| s[0].t_s;
        tracks.update(1, t(&before), pairs(&before, 1), &rect, &mut points);
        let rejoined = tracks.update(2, t(&after), pairs(&after, 5000), &rect, &mut points);
        let carried: Vec<&Track3d> = tracks.all().filter(|t| t.samples.len() == 2).collect();
        let right = carried
            .iter()
            .filter(|t| {
                let i = before
                    .iter()
                    .position(|s| s.point_in_world == t.samples[0].point_in_world);
                i.is_some_and(|i| after[i].point_in_world == t.samples[1].point_in_world)
            })
            .count();
        assert_eq!(rejoined, carried.len());
        assert!(right >= 70, "{right} of {} carried right", before.len());
        assert_eq!(right, carried.len(), "none carried wrong");
    }
}
