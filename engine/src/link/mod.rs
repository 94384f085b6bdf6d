//! Stage 2: per-camera linking between consecutive frames (method section 3.2).
//!
//! A small state machine fed one frame of rectified features at a time. Each active track predicts
//! its next position `X~ = 2 X_n - X_{n-1}` (eq. 4; its last position when it has only one),
//! candidates must lie in a box of half-side H around the prediction, and the linking cost G
//! (eq. 6) mixes diameter, brightness and position. A detection nobody links to starts a new track;
//! a track with no candidate ends (the method closes no gaps: a velocity needs every frame).
//!
//! The method's prediction needs two positions, so a track's first link has nothing to predict
//! from, and a particle moving more than H per frame never links. mrptv predicts it from the
//! established neighbours' median motion where they agree, and otherwise learns it from the
//! images (neighbour consensus, the idea behind relaxation-labelling PTV, Baek & Lee 1996):
//! among the candidate displacements of a new track, the one most of its nearest neighbours can
//! also make, within `max_displacement_px`. Both are local, so a vortex's fast rim and slow core
//! both link, and both are re-learnt every frame.

use crate::config::{check_non_negative, ConfigError};
use serde::{Deserialize, Serialize};

use crate::geometry::RectPoint;
use crate::spatial::{assign, median, normalising_mean, PointGrid, SortedByX, GRID_CELL_PX};

mod first_steps;

pub use crate::spatial::Assignment;
use first_steps::FirstSteps;

/// Per-camera linking parameters (the file's `[link]` table, with [`TrackConfig`]'s keys).
///
/// [`TrackConfig`]: crate::tracks::TrackConfig
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct LinkConfig {
    /// Half-side H of the hard search box around the prediction, rectified pixels. Must exceed the
    /// largest prediction error, and the largest per-frame displacement for a track's first link.
    pub box_half_side_px: f64,
    /// l1: weight of the diameter term. The method leaves l1..l3 open ("similar magnitude");
    /// 0.01 makes a 10 % diameter or brightness mismatch cost as much as a ~3 px position error
    /// on a 640 px wide image.
    pub weight_diameter: f64,
    /// l2: weight of the brightness term.
    pub weight_brightness: f64,
    /// l3: weight of the x-position term (the y term has weight 1).
    pub weight_x: f64,
    /// How claims on a feature are settled.
    pub assignment: Assignment,
    /// Predict a track's first link from the median motion of nearby established tracks instead
    /// of assuming it stands still (the method). Matters when particles move several diameters
    /// per frame.
    pub predict_new_from_neighbours: bool,
    /// How many established neighbours inform a new track's prediction.
    pub neighbours: usize,
    /// Frames a track may go unseen (coasting on its prediction) before it ends (method: 0).
    pub max_gap_frames: u32,
    /// Frames a track must stay within 1 px of one point to be taken for a fixture (hot pixel,
    /// LED, glint, print on a poster) and left out of stereo matching: a causal model of what
    /// is static in the image, learnt per camera. A particle moving under 0.1 px per frame for
    /// this long is taken for one too. 0 keeps every feature (the method): a room's lamps,
    /// LEDs and posters then become ghosts.
    pub fixture_frames: u32,
    /// Largest per-frame image motion a new track's first link is searched for by neighbour
    /// consensus, rectified pixels (with `predict_new_from_neighbours`; 0 turns consensus off).
    /// Well above the fastest flow a 640-pixel view can follow for a velocity window.
    pub max_displacement_px: f64,
}

impl Default for LinkConfig {
    fn default() -> Self {
        Self {
            box_half_side_px: 20.0,
            weight_diameter: 0.01,
            weight_brightness: 0.01,
            weight_x: 1.0,
            assignment: Assignment::OneToOne,
            predict_new_from_neighbours: true,
            neighbours: 5,
            max_gap_frames: 2,
            max_displacement_px: 100.0,
            fixture_frames: 10,
        }
    }
}

impl LinkConfig {
    /// The published method: each particle takes its own cheapest candidate, a new track
    /// predicts it stands still, no gap is closed, nothing is taken for a fixture.
    pub fn method() -> Self {
        Self {
            assignment: Assignment::PerParticle,
            predict_new_from_neighbours: false,
            max_gap_frames: 0,
            max_displacement_px: 0.0,
            fixture_frames: 0,
            ..Self::default()
        }
    }

    /// Refuses values no run can use, naming the key as the config file spells it.
    pub fn validate(&self) -> Result<(), ConfigError> {
        check_non_negative(
            "link",
            &[
                ("box_half_side_px", self.box_half_side_px),
                ("weight_diameter", self.weight_diameter),
                ("weight_brightness", self.weight_brightness),
                ("weight_x", self.weight_x),
                ("max_displacement_px", self.max_displacement_px),
            ],
        )
    }
}

/// A detection after rectification: what linking and stereo matching need.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Feature {
    /// Centroid, rectified pixels.
    pub rect: RectPoint,
    /// Equivalent diameter D, pixels.
    pub diameter_px: f64,
    /// Brightness B, grey levels.
    pub brightness: f64,
}

/// A feature with its per-camera track.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LinkedFeature {
    /// The feature.
    pub feature: Feature,
    /// Its per-camera track.
    pub track_id: u64,
    /// Apparent displacement per frame, rectified pixels (None on a new track).
    pub motion_px: Option<(f64, f64)>,
    /// Frames this track has been seen, including this one.
    pub age: u32,
    /// The track has stayed put for `fixture_frames` frames: a hot pixel, an LED, a glint or
    /// print on a poster, not a particle (see `LinkConfig::fixture_frames`).
    pub fixed: bool,
}

impl LinkedFeature {
    /// Apparent speed U (method eq. 8), pixels per frame.
    pub fn speed_px(&self) -> Option<f64> {
        self.motion_px.map(|(dx, dy)| dx.hypot(dy))
    }
}

#[derive(Debug, Clone)]
struct ActiveTrack {
    id: u64,
    last: Feature,
    /// Displacement per frame over the last link.
    motion: Option<(f64, f64)>,
    /// Frames since `last` was seen (0: seen in the latest frame).
    missed: u32,
    age: u32,
    /// Where the track has stayed within `FIXTURE_RADIUS_PX` since, and for how many frames.
    anchor: RectPoint,
    anchored_frames: u32,
}

impl ActiveTrack {
    /// A new track at `feature`.
    fn starting_at(id: u64, feature: &Feature) -> Self {
        Self {
            id,
            last: *feature,
            motion: None,
            missed: 0,
            age: 1,
            anchor: feature.rect,
            anchored_frames: 0,
        }
    }

    /// This track continued by `feature`: its motion the step since it was last seen, its
    /// anchor kept while it stays within `FIXTURE_RADIUS_PX` of it.
    fn continued_by(&self, feature: &Feature) -> Self {
        let frames = f64::from(self.missed + 1);
        let motion = (
            (feature.rect.x - self.last.rect.x) / frames,
            (feature.rect.y - self.last.rect.y) / frames,
        );
        let still = (feature.rect.x - self.anchor.x).hypot(feature.rect.y - self.anchor.y)
            <= FIXTURE_RADIUS_PX;
        Self {
            id: self.id,
            last: *feature,
            motion: Some(motion),
            missed: 0,
            age: self.age + 1,
            anchor: if still { self.anchor } else { feature.rect },
            anchored_frames: if still {
                self.anchored_frames + self.missed + 1
            } else {
                0
            },
        }
    }

    /// Where its own motion takes the track in the next frame; `None` before it has one.
    fn moved_on(&self) -> Option<RectPoint> {
        let (dx, dy) = self.motion?;
        let frames = f64::from(self.missed + 1);
        Some(RectPoint {
            x: self.last.rect.x + dx * frames,
            y: self.last.rect.y + dy * frames,
        })
    }
}

/// How far a prediction at constant velocity may miss, as a fraction of the per-frame step: a
/// particle turning through a vortex changes its velocity by up to this much per frame (a
/// sixth of a radian at 5 rad/s and 30 Hz), which a first step from three frames must allow
/// for, and a rejoined 3D track until the tracks have shown how far their own paths turn.
pub(crate) const TURN_PER_FRAME: f64 = 0.3;

/// A track that stays within this distance of one point is not moving.
const FIXTURE_RADIUS_PX: f64 = 1.0;

/// Per-camera linker state.
#[derive(Debug, Clone, Default)]
pub struct CameraLinker {
    tracks: Vec<ActiveTrack>,
    next_id: u64,
}

/// Added per priority tier to a claim's cost: larger than any cost G inside the box.
const TIER_COST: f64 = 1e6;

/// Normalisation of the cost terms: the method's image-wide means and half image size.
#[derive(Debug, Clone, Copy)]
pub struct CostScale {
    /// Half the rectified image width, pixels.
    pub half_width_px: f64,
    /// Half the rectified image height, pixels.
    pub half_height_px: f64,
}

impl CameraLinker {
    /// A linker with no tracks yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// Tracks seen in the latest frame or coasting through a gap.
    pub fn active_tracks(&self) -> usize {
        self.tracks.len()
    }

    /// Where the tracks seen in the last frame that know their motion expect their particle in
    /// the next frame, in the order of the tracks. A fixture expects nothing new, and a track
    /// already coasting has lost its particle: looking for it again finds only its neighbours.
    pub fn expected_positions(&self) -> impl Iterator<Item = RectPoint> + '_ {
        self.tracks
            .iter()
            .filter(|t| t.missed == 0 && t.motion.is_some_and(|(dx, dy)| dx.hypot(dy) > 0.0))
            .filter_map(ActiveTrack::moved_on)
    }

    /// Links one frame's features to the active tracks; returns them in the input order.
    pub fn push(
        &mut self,
        features: &[Feature],
        scale: CostScale,
        config: &LinkConfig,
    ) -> Vec<LinkedFeature> {
        let predictions = self.predictions(features, scale, config);
        let candidates = self.candidates(features, &predictions, scale, config);
        let pairs = assign(
            candidates,
            self.tracks.len(),
            features.len(),
            config.assignment,
        );
        let mut track_of_feature: Vec<Option<usize>> = vec![None; features.len()];
        for (t, f) in pairs {
            track_of_feature[f] = Some(t);
        }
        let mut next_tracks = Vec::with_capacity(features.len() + self.tracks.len());
        let mut linked_tracks = vec![false; self.tracks.len()];
        let mut out = Vec::with_capacity(features.len());
        for (f, feature) in features.iter().enumerate() {
            let track = match track_of_feature[f] {
                Some(t) => {
                    linked_tracks[t] = true;
                    self.tracks[t].continued_by(feature)
                }
                None => {
                    self.next_id += 1;
                    ActiveTrack::starting_at(self.next_id, feature)
                }
            };
            out.push(LinkedFeature {
                feature: *feature,
                track_id: track.id,
                motion_px: track.motion,
                age: track.age,
                fixed: config.fixture_frames > 0 && track.anchored_frames >= config.fixture_frames,
            });
            next_tracks.push(track);
        }
        for (t, old) in self.tracks.iter().enumerate() {
            if !linked_tracks[t] && old.missed < config.max_gap_frames {
                next_tracks.push(ActiveTrack {
                    missed: old.missed + 1,
                    ..old.clone()
                });
            }
        }
        self.tracks = next_tracks;
        out
    }

    /// Where each active track expects its particle in this frame.
    fn predictions(
        &self,
        features: &[Feature],
        scale: CostScale,
        config: &LinkConfig,
    ) -> Vec<RectPoint> {
        // Indexed only when some track has no motion yet: most frames of a steady flow have none.
        let new_tracks =
            config.predict_new_from_neighbours && self.tracks.iter().any(|t| t.motion.is_none());
        let first_steps = (new_tracks && config.max_displacement_px > 0.0)
            .then(|| FirstSteps::new(&self.tracks, features, scale));
        // Tracks with a motion, indexed for new tracks to borrow it: a linear search per new
        // track would cost a dense frame more than its detection.
        let established = (new_tracks && config.neighbours > 0).then(|| {
            let with_motion = self.tracks.iter().enumerate();
            PointGrid::new(
                with_motion.filter_map(|(i, t)| t.motion.map(|_| (t.last.rect, i))),
                GRID_CELL_PX,
            )
        });
        (0..self.tracks.len())
            .map(|t| self.predict(t, first_steps.as_ref(), established.as_ref(), config))
            .collect()
    }

    /// Every (track, feature) pair inside the box around the track's prediction, with its cost
    /// G (method eq. 6) plus its tier's.
    ///
    /// Claims are served in tiers, cheapest first within a tier: tracks seen in the last frame
    /// with a known motion, then new tracks (their first step learnt this frame), then tracks
    /// coasting through a gap. The later tiers' predictions are the weaker ones, and where
    /// particles move many diameters per frame or turn (a vortex) they would otherwise take a
    /// detection from a track that is sure.
    fn candidates(
        &self,
        features: &[Feature],
        predictions: &[RectPoint],
        scale: CostScale,
        config: &LinkConfig,
    ) -> Vec<(f64, usize, usize)> {
        let d_ave = normalising_mean(features.iter().map(|f| f.diameter_px));
        let b_ave = normalising_mean(features.iter().map(|f| f.brightness));
        let sorted_x = SortedByX::new(features.iter().map(|f| f.rect));
        let h = config.box_half_side_px;
        let mut candidates = Vec::new();
        for (t, (track, pred)) in self.tracks.iter().zip(predictions).enumerate() {
            let tier = if track.missed > 0 {
                2.0
            } else if track.motion.is_none() {
                1.0
            } else {
                0.0
            };
            for f in sorted_x.within(pred.x - h, pred.x + h) {
                let feature = &features[f];
                if (feature.rect.y - pred.y).abs() > h {
                    continue;
                }
                let g = config.weight_diameter
                    * ((feature.diameter_px - track.last.diameter_px) / d_ave).powi(2)
                    + config.weight_brightness
                        * ((feature.brightness - track.last.brightness) / b_ave).powi(2)
                    + config.weight_x * ((feature.rect.x - pred.x) / scale.half_width_px).powi(2)
                    + ((feature.rect.y - pred.y) / scale.half_height_px).powi(2);
                candidates.push((g + tier * TIER_COST, t, f));
            }
        }
        candidates
    }

    fn predict(
        &self,
        t: usize,
        first_steps: Option<&FirstSteps>,
        established: Option<&PointGrid>,
        config: &LinkConfig,
    ) -> RectPoint {
        let track = &self.tracks[t];
        let last = track.last.rect;
        let frames = f64::from(track.missed + 1);
        if let Some(expected) = track.moved_on() {
            return expected;
        }
        let Some(established) = established else {
            return last;
        };
        // Established neighbours that agree on a motion (within half the box of their median)
        // are the best guess; where they disagree (particles at different depths, or none is
        // established yet) the step is learnt from the images; else their median, else none.
        let neighbours = self.neighbour_motion(established, last, config);
        if let Some(((dx, dy), true)) = neighbours {
            return RectPoint {
                x: last.x + dx * frames,
                y: last.y + dy * frames,
            };
        }
        if let Some((dx, dy)) = first_steps.and_then(|f| {
            f.consensus_step(t, last, config).or_else(|| {
                (track.missed == 0)
                    .then(|| f.three_frame_step(last, config))
                    .flatten()
            })
        }) {
            return RectPoint {
                x: last.x + dx,
                y: last.y + dy,
            };
        }
        match neighbours {
            Some(((dx, dy), _)) => RectPoint {
                x: last.x + dx * frames,
                y: last.y + dy * frames,
            },
            None => last,
        }
    }

    /// The median motion of the `neighbours` established tracks nearest to `at`, and whether
    /// they agree on it (each within half the linking box).
    /// `established` holds the last positions of the tracks with a motion.
    fn neighbour_motion(
        &self,
        established: &PointGrid,
        at: RectPoint,
        config: &LinkConfig,
    ) -> Option<((f64, f64), bool)> {
        let near: Vec<(f64, f64)> = established
            .nearest_indexed(at.x, at.y, config.neighbours, usize::MAX)
            .into_iter()
            .filter_map(|(_, i)| self.tracks[i].motion)
            .collect();
        if near.is_empty() {
            return None;
        }
        let (mut dxs, mut dys): (Vec<f64>, Vec<f64>) = near.iter().copied().unzip();
        let motion = (median(&mut dxs), median(&mut dys));
        let agree = near.len() == config.neighbours
            && near.iter().all(|(dx, dy)| {
                (dx - motion.0).hypot(dy - motion.1) <= config.box_half_side_px / 2.0
            });
        Some((motion, agree))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const SCALE: CostScale = CostScale {
        half_width_px: 320.0,
        half_height_px: 240.0,
    };

    fn feature(x: f64, y: f64) -> Feature {
        Feature {
            rect: RectPoint { x, y },
            diameter_px: 6.0,
            brightness: 150.0,
        }
    }

    fn ids(linked: &[LinkedFeature]) -> Vec<u64> {
        linked.iter().map(|l| l.track_id).collect()
    }

    #[test]
    fn two_isolated_steppers_keep_their_ids() {
        let mut linker = CameraLinker::new();
        let config = LinkConfig::default();
        let first = linker.push(&[feature(0.0, 0.0), feature(100.0, 50.0)], SCALE, &config);
        for n in 1..10 {
            let n = n as f64;
            // Given in reverse order: identity must follow position, not index.
            let linked = linker.push(
                &[feature(100.0 - 3.0 * n, 50.0), feature(4.0 * n, n)],
                SCALE,
                &config,
            );
            assert_eq!(ids(&linked), vec![first[1].track_id, first[0].track_id]);
        }
    }

    #[test]
    fn prediction_resolves_crossing_paths() {
        // Two particles cross; a nearest-neighbour linker swaps them, the predictor does not.
        let mut linker = CameraLinker::new();
        let config = LinkConfig {
            box_half_side_px: 12.0,
            ..Default::default()
        };
        let mut a_ids = Vec::new();
        for n in 0..8 {
            let n = n as f64;
            let linked = linker.push(
                &[
                    feature(5.0 * n, 20.0 + n),
                    feature(35.0 - 5.0 * n, 27.0 - n),
                ],
                SCALE,
                &config,
            );
            a_ids.push(linked[0].track_id);
        }
        assert!(a_ids.windows(2).all(|w| w[0] == w[1]), "{a_ids:?}");
    }

    #[test]
    fn only_tracks_seen_last_frame_and_moving_expect_a_particle() {
        let config = LinkConfig::default();
        let mut linker = CameraLinker::new();
        let expected = |l: &CameraLinker| -> Vec<(f64, f64)> {
            l.expected_positions().map(|p| (p.x, p.y)).collect()
        };
        linker.push(&[feature(0.0, 0.0), feature(50.0, 50.0)], SCALE, &config);
        assert!(expected(&linker).is_empty(), "no motion yet");
        linker.push(&[feature(3.0, 1.0), feature(50.0, 50.0)], SCALE, &config);
        assert_eq!(
            expected(&linker),
            [(6.0, 2.0)],
            "the still one expects nothing new"
        );
        linker.push(&[feature(50.0, 50.0)], SCALE, &config);
        assert!(
            expected(&linker).is_empty(),
            "a coasting track has lost its particle"
        );
    }

    #[test]
    fn track_coasts_through_a_short_gap_only() {
        let config = LinkConfig::default();
        let mut linker = CameraLinker::new();
        let first = linker.push(&[feature(0.0, 0.0)], SCALE, &config);
        linker.push(&[feature(3.0, 0.0)], SCALE, &config);
        linker.push(&[], SCALE, &config);
        linker.push(&[], SCALE, &config);
        let back = linker.push(&[feature(12.0, 0.0)], SCALE, &config);
        assert_eq!(back[0].track_id, first[0].track_id);
        assert_eq!(back[0].motion_px, Some((3.0, 0.0)));
        for _ in 0..3 {
            linker.push(&[], SCALE, &config);
        }
        assert_eq!(linker.active_tracks(), 0);
        let method = LinkConfig {
            max_gap_frames: 0,
            ..config
        };
        let mut strict = CameraLinker::new();
        strict.push(&[feature(0.0, 0.0)], SCALE, &method);
        strict.push(&[], SCALE, &method);
        assert_eq!(strict.active_tracks(), 0);
    }

    #[test]
    fn particle_leaving_the_box_starts_a_new_track() {
        let mut linker = CameraLinker::new();
        let config = LinkConfig::default();
        let a = linker.push(&[feature(0.0, 0.0)], SCALE, &config);
        let b = linker.push(&[feature(50.0, 0.0)], SCALE, &config);
        assert_ne!(a[0].track_id, b[0].track_id);
        assert_eq!(b[0].age, 1);
        assert_eq!(b[0].motion_px, None);
    }

    #[test]
    fn new_track_borrows_neighbour_motion() {
        let config = LinkConfig {
            box_half_side_px: 8.0,
            ..Default::default()
        };
        let mut linker = CameraLinker::new();
        // Established particles move 15 px/frame, beyond the box; a newcomer does too.
        linker.push(&[feature(0.0, 0.0), feature(0.0, 40.0)], SCALE, &config);
        linker.push(&[feature(6.0, 0.0), feature(6.0, 40.0)], SCALE, &config);
        linker.push(
            &[
                feature(12.0, 0.0),
                feature(12.0, 40.0),
                feature(100.0, 20.0),
            ],
            SCALE,
            &config,
        );
        let with = linker.push(
            &[
                feature(18.0, 0.0),
                feature(18.0, 40.0),
                feature(106.0, 20.0),
            ],
            SCALE,
            &config,
        );
        assert_eq!(with[2].age, 2, "newcomer linked using neighbour motion");
        let mut plain = CameraLinker::new();
        let method = LinkConfig {
            predict_new_from_neighbours: false,
            box_half_side_px: 5.0,
            ..config
        };
        plain.push(&[feature(0.0, 0.0), feature(100.0, 20.0)], SCALE, &method);
        let without = plain.push(&[feature(6.0, 0.0), feature(106.0, 20.0)], SCALE, &method);
        assert_eq!(without[1].age, 1);
    }

    /// Six particles moving 45-75 px per frame (different depths, different image speeds), far
    /// beyond the 20 px box: all are linked by their third frame (consensus where established
    /// neighbours disagree), and keep their identities.
    #[test]
    fn fast_particles_at_different_speeds_link_without_tuning() {
        let config = LinkConfig::default();
        let mut linker = CameraLinker::new();
        let start = [
            (0.0, 0.0),
            (30.0, 200.0),
            (-150.0, 90.0),
            (200.0, -100.0),
            (-60.0, -220.0),
            (120.0, 140.0),
        ];
        let speed = [45.0, 50.0, 58.0, 63.0, 70.0, 75.0];
        let at = |n: f64| -> Vec<Feature> {
            start
                .iter()
                .zip(speed)
                .map(|(&(x, y), v)| feature(x + 0.8 * v * n, y - 0.6 * v * n))
                .collect()
        };
        let mut ids = Vec::new();
        for n in 0..6 {
            ids.push(linker.push(&at(n as f64), SCALE, &config));
        }
        assert!(ids[2].iter().all(|l| l.age >= 2), "{:?}", ids[2]);
        assert!(ids[5].iter().all(|l| l.age >= 5));
        assert_eq!(
            ids[5].iter().map(|l| l.track_id).collect::<Vec<_>>(),
            ids[2].iter().map(|l| l.track_id).collect::<Vec<_>>()
        );
        // The method (no learnt first step) links none of them.
        let mut method = CameraLinker::new();
        let plain = LinkConfig {
            predict_new_from_neighbours: false,
            max_displacement_px: 0.0,
            max_gap_frames: 0,
            ..config
        };
        let last = (0..6)
            .map(|n| method.push(&at(n as f64), SCALE, &plain))
            .last();
        assert!(last.is_some_and(|l| l.iter().all(|f| f.age == 1)));
    }

    /// A uniform 60 px step seen by a crowd: neighbour consensus links a new track on its
    /// second frame already.
    #[test]
    fn consensus_links_a_crowd_on_its_second_frame() {
        let config = LinkConfig::default();
        let mut linker = CameraLinker::new();
        // Scattered, not on a lattice: a lattice makes every multiple of its spacing a
        // displacement all neighbours agree on.
        let mut rng = crate::synth::Rng::new(7);
        let grid: Vec<(f64, f64)> = (0..25)
            .map(|_| (rng.range(-300.0, 230.0), rng.range(-230.0, 220.0)))
            .collect();
        let at = |n: f64| -> Vec<Feature> {
            grid.iter()
                .map(|&(x, y)| feature(x + 60.0 * n, y + 11.0 * n))
                .collect()
        };
        linker.push(&at(0.0), SCALE, &config);
        let second = linker.push(&at(1.0), SCALE, &config);
        let linked = second.iter().filter(|l| l.age == 2).count();
        assert!(
            linked >= 23,
            "{linked} of 25 linked on the second frame: {second:?}"
        );
        assert!(second.iter().filter(|l| l.age == 2).all(|l| l
            .motion_px
            .is_some_and(|(dx, dy)| (dx - 60.0).abs() < 1e-9 && (dy - 11.0).abs() < 1e-9)));
    }

    /// A hot pixel (centroid jitter 0.05 px) becomes a fixture after `fixture_frames`; a
    /// particle creeping 0.5 px per frame never does.
    #[test]
    fn what_stays_put_becomes_a_fixture_and_a_slow_particle_does_not() {
        let config = LinkConfig::default();
        let mut linker = CameraLinker::new();
        let mut fixed = Vec::new();
        for n in 0..30 {
            let jitter = 0.05 * if n % 2 == 0 { 1.0 } else { -1.0 };
            let linked = linker.push(
                &[
                    feature(100.0 + jitter, 50.0),
                    feature(-200.0 + 0.5 * n as f64, 10.0),
                ],
                SCALE,
                &config,
            );
            fixed.push((linked[0].fixed, linked[1].fixed));
        }
        let first = fixed.iter().position(|f| f.0);
        assert_eq!(first, Some(config.fixture_frames as usize), "{fixed:?}");
        assert!(fixed[first.unwrap_or(0)..].iter().all(|f| f.0));
        assert!(fixed.iter().all(|f| !f.1));
    }

    /// Particles turning 0.25 rad per frame around a centre, 24-36 px per frame, each in a
    /// different direction, so no neighbour consensus forms: the third frame's detection,
    /// predicted from the first two at constant velocity, links them from then on. Without
    /// learnt first steps some still start a new track every frame.
    #[test]
    fn turning_particles_link_from_their_third_frame() {
        let config = LinkConfig::default();
        let omega = 0.25;
        let radii = [100.0, 120.0, 144.0];
        let phases = [0.0, 2.1, 4.2];
        let at = |n: f64| -> Vec<Feature> {
            radii
                .iter()
                .zip(phases)
                .map(|(r, p)| feature(r * (p + omega * n).cos(), r * (p + omega * n).sin()))
                .collect()
        };
        let mut linker = CameraLinker::new();
        let mut frames: Vec<Vec<LinkedFeature>> = Vec::new();
        for n in 0..6 {
            frames.push(linker.push(&at(f64::from(n)), SCALE, &config));
        }
        assert!(frames[1].iter().all(|f| f.age == 1), "no step known yet");
        for (n, frame) in frames.iter().enumerate().skip(2) {
            assert_eq!(
                ids(frame),
                ids(&frames[1]),
                "frame {n} keeps the identities"
            );
        }
        assert!(frames[5].iter().all(|f| f.age == 5), "{:?}", frames[5]);
        let off = LinkConfig {
            max_displacement_px: 0.0,
            ..config
        };
        let mut plain = CameraLinker::new();
        let last = (0..6)
            .map(|n| plain.push(&at(f64::from(n)), SCALE, &off))
            .last()
            .expect("six frames");
        assert!(last.iter().any(|f| f.age == 1), "{last:?}");
    }
}
