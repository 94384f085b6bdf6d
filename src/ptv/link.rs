//! Stage 2: per-camera linking between consecutive frames (method section 3.2).
//!
//! A small state machine fed one frame of rectified features at a time. Each active track predicts
//! its next position `X~ = 2 X_n - X_{n-1}` (eq. 4; its last position when it has only one),
//! candidates must lie in a box of half-side H around the prediction, and the linking cost G
//! (eq. 6) mixes diameter, brightness and position. A detection nobody links to starts a new track;
//! a track with no candidate ends (the method closes no gaps: a velocity needs every frame).

use serde::{Deserialize, Serialize};

use crate::geometry::RectPoint;

/// How candidates are assigned once every cost is known.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Assignment {
    /// The method: each particle takes its own cheapest candidate. Where two claim the same
    /// candidate, the cheaper claim wins and the other particle goes unmatched.
    PerParticle,
    /// Globally cheapest pairs first, each candidate used once: a particle that loses its first
    /// choice still gets its next-best free candidate.
    OneToOne,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
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
    pub assignment: Assignment,
    /// Predict a track's first link from the median motion of nearby established tracks instead
    /// of assuming it stands still (the method). Matters when particles move several diameters
    /// per frame.
    pub predict_new_from_neighbours: bool,
    /// How many established neighbours inform a new track's prediction.
    pub neighbours: usize,
    /// Frames a track may go unseen (coasting on its prediction) before it ends (method: 0).
    pub max_gap_frames: u32,
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
        }
    }
}

/// A detection after rectification: what linking and stereo matching need.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Feature {
    pub rect: RectPoint,
    pub diameter_px: f64,
    pub brightness: f64,
}

/// A feature with its per-camera track.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LinkedFeature {
    pub feature: Feature,
    pub track_id: u64,
    /// Apparent displacement per frame, rectified pixels (None on a new track).
    pub motion_px: Option<(f64, f64)>,
    /// Frames this track has been seen, including this one.
    pub age: u32,
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
}

/// Per-camera linker state.
#[derive(Debug, Clone, Default)]
pub struct CameraLinker {
    tracks: Vec<ActiveTrack>,
    next_id: u64,
}

/// Normalisation of the cost terms: the method's image-wide means and half image size.
#[derive(Debug, Clone, Copy)]
pub struct CostScale {
    pub half_width_px: f64,
    pub half_height_px: f64,
}

/// The mean that normalises a cost term (D_ave, B_ave, U_ave); 1 when there is nothing to average,
/// so an empty frame never divides by zero.
pub(crate) fn normalising_mean(values: impl Iterator<Item = f64>) -> f64 {
    let (sum, n) = values.fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    if n == 0 || sum <= 0.0 {
        1.0
    } else {
        sum / n as f64
    }
}

/// Picks pairs `(row, column)` from candidate `(cost, row, column)` triples.
pub(crate) fn assign(
    mut candidates: Vec<(f64, usize, usize)>,
    rows: usize,
    columns: usize,
    mode: Assignment,
) -> Vec<(usize, usize)> {
    // Sorting by (cost, row, column) keeps the outcome independent of input order.
    candidates.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
    let mut row_done = vec![false; rows];
    let mut column_done = vec![false; columns];
    let mut pairs = Vec::new();
    for (_, r, c) in candidates {
        if row_done[r] {
            continue;
        }
        match mode {
            Assignment::OneToOne => {
                if column_done[c] {
                    continue;
                }
                row_done[r] = true;
                column_done[c] = true;
                pairs.push((r, c));
            }
            Assignment::PerParticle => {
                // This is the row's own cheapest candidate; if a cheaper claim took it, the row
                // stays unmatched.
                row_done[r] = true;
                if !column_done[c] {
                    column_done[c] = true;
                    pairs.push((r, c));
                }
            }
        }
    }
    pairs.sort_unstable();
    pairs
}

impl CameraLinker {
    pub fn new() -> Self {
        Self::default()
    }

    /// Tracks seen in the latest frame or coasting through a gap.
    pub fn active_tracks(&self) -> usize {
        self.tracks.len()
    }

    /// Links one frame's features to the active tracks; returns them in the input order.
    pub fn push(
        &mut self,
        features: &[Feature],
        scale: CostScale,
        config: &LinkConfig,
    ) -> Vec<LinkedFeature> {
        let d_ave = normalising_mean(features.iter().map(|f| f.diameter_px));
        let b_ave = normalising_mean(features.iter().map(|f| f.brightness));
        let predictions: Vec<RectPoint> = (0..self.tracks.len())
            .map(|t| self.predict(t, config))
            .collect();
        let sorted_x = SortedByX::new(features);
        let h = config.box_half_side_px;
        let mut candidates = Vec::new();
        for (t, (track, pred)) in self.tracks.iter().zip(&predictions).enumerate() {
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
                candidates.push((g, t, f));
            }
        }
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
                    let old = &self.tracks[t];
                    let frames = f64::from(old.missed + 1);
                    ActiveTrack {
                        id: old.id,
                        last: *feature,
                        motion: Some((
                            (feature.rect.x - old.last.rect.x) / frames,
                            (feature.rect.y - old.last.rect.y) / frames,
                        )),
                        missed: 0,
                        age: old.age + 1,
                    }
                }
                None => {
                    self.next_id += 1;
                    ActiveTrack {
                        id: self.next_id,
                        last: *feature,
                        motion: None,
                        missed: 0,
                        age: 1,
                    }
                }
            };
            out.push(LinkedFeature {
                feature: *feature,
                track_id: track.id,
                motion_px: track.motion,
                age: track.age,
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

    fn predict(&self, t: usize, config: &LinkConfig) -> RectPoint {
        let track = &self.tracks[t];
        let last = track.last.rect;
        let frames = f64::from(track.missed + 1);
        if let Some((dx, dy)) = track.motion {
            return RectPoint {
                x: last.x + dx * frames,
                y: last.y + dy * frames,
            };
        }
        if !config.predict_new_from_neighbours || config.neighbours == 0 {
            return last;
        }
        let mut near: Vec<(f64, (f64, f64))> = self
            .tracks
            .iter()
            .filter_map(|o| {
                o.motion
                    .map(|m| ((o.last.rect.x - last.x).hypot(o.last.rect.y - last.y), m))
            })
            .collect();
        if near.is_empty() {
            return last;
        }
        let k = config.neighbours.min(near.len());
        near.select_nth_unstable_by(k - 1, |a, b| a.0.total_cmp(&b.0));
        let (mut dxs, mut dys): (Vec<f64>, Vec<f64>) = near[..k].iter().map(|n| n.1).unzip();
        RectPoint {
            x: last.x + median(&mut dxs) * frames,
            y: last.y + median(&mut dys) * frames,
        }
    }
}

pub(crate) fn median(values: &mut [f64]) -> f64 {
    values.sort_by(f64::total_cmp);
    let n = values.len();
    if n == 0 {
        0.0
    } else if n % 2 == 1 {
        values[n / 2]
    } else {
        (values[n / 2 - 1] + values[n / 2]) / 2.0
    }
}

/// Feature indices sorted by x, so a box query costs a binary search plus its hits.
pub(crate) struct SortedByX {
    order: Vec<(f64, usize)>,
}

impl SortedByX {
    pub(crate) fn new(features: &[Feature]) -> Self {
        let mut order: Vec<(f64, usize)> = features
            .iter()
            .enumerate()
            .map(|(i, f)| (f.rect.x, i))
            .collect();
        order.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        Self { order }
    }

    pub(crate) fn within(&self, min_x: f64, max_x: f64) -> impl Iterator<Item = usize> + '_ {
        let start = self.order.partition_point(|(x, _)| *x < min_x);
        self.order[start..]
            .iter()
            .take_while(move |(x, _)| *x <= max_x)
            .map(|(_, i)| *i)
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

    #[test]
    fn per_particle_loser_goes_unmatched_one_to_one_gets_next_best() {
        let candidates = vec![(0.1, 0, 0), (0.2, 1, 0), (0.5, 1, 1)];
        assert_eq!(
            assign(candidates.clone(), 2, 2, Assignment::PerParticle),
            vec![(0, 0)]
        );
        assert_eq!(
            assign(candidates, 2, 2, Assignment::OneToOne),
            vec![(0, 0), (1, 1)]
        );
    }
}
