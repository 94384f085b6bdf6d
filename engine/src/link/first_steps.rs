//! A new track's first step, where its own motion is not known yet: learnt from this frame's
//! features by neighbour consensus, or from the lone detections of the frame before last.

use super::{ActiveTrack, CostScale, Feature, LinkConfig, TURN_PER_FRAME};
use crate::geometry::RectPoint;
use crate::spatial::{binomial_tail, votes_needed, PointGrid, GRID_CELL_PX};

/// What a new track's first step is learnt from: this frame's features and the tracks seen in
/// the last frame (neighbours), each indexed once per frame.
pub(super) struct FirstSteps {
    features: PointGrid,
    seen_last: PointGrid,
    /// Where lone detections of the frame before last were: tracks seen once, then not linked.
    lone_before: PointGrid,
    density_per_px2: f64,
}

impl FirstSteps {
    pub(super) fn new(tracks: &[ActiveTrack], features: &[Feature], scale: CostScale) -> Self {
        Self {
            features: PointGrid::new(
                features.iter().enumerate().map(|(i, f)| (f.rect, i)),
                GRID_CELL_PX,
            ),
            seen_last: PointGrid::new(
                tracks
                    .iter()
                    .enumerate()
                    .filter(|(_, t)| t.missed == 0)
                    .map(|(i, t)| (t.last.rect, i)),
                GRID_CELL_PX,
            ),
            lone_before: PointGrid::new(
                tracks
                    .iter()
                    .enumerate()
                    .filter(|(_, t)| t.missed == 1 && t.age == 1)
                    .map(|(i, t)| (t.last.rect, i)),
                GRID_CELL_PX,
            ),
            density_per_px2: features.len() as f64
                / (4.0 * scale.half_width_px * scale.half_height_px).max(1.0),
        }
    }

    /// A new track's first step by neighbour consensus: of the displacements to this frame's
    /// features within `max_displacement_px`, the one that its nearest neighbours (tracks seen in
    /// the last frame) can also make, each to some feature within a tolerance that grows with
    /// the step (neighbours in a shear or vortex move a little differently). A wider tolerance
    /// also catches unrelated features, so votes are weighed against chance: the step chosen is
    /// the one whose votes are least likely from features scattered at this frame's density,
    /// and only if chance explains them less than once in a thousand. `None` otherwise: no
    /// evidence beats a guess.
    pub(super) fn consensus_step(
        &self,
        t: usize,
        last: RectPoint,
        config: &LinkConfig,
    ) -> Option<(f64, f64)> {
        const CONSENSUS_NEIGHBOURS: usize = 8;
        const CHANCE: f64 = 1e-3;
        let reach = config.max_displacement_px;
        let near = self
            .seen_last
            .nearest(last.x, last.y, CONSENSUS_NEIGHBOURS, t);
        let k = near.len();
        if k < 2 {
            return None;
        }
        let mut best: Option<(f64, (f64, f64))> = None;
        for (c, _) in self.features.near(last.x, last.y, reach) {
            let (dx, dy) = (c.x - last.x, c.y - last.y);
            let step = dx.hypot(dy);
            if step > reach {
                continue;
            }
            let tolerance = (0.15 * step).max(2.0);
            let by_chance_per_neighbour =
                1.0 - (-self.density_per_px2 * 4.0 * tolerance * tolerance).exp();
            // A step is given up once its misses leave too few neighbours to outvote chance:
            // in a dense frame a new track has hundreds of candidate steps, nearly all of them
            // voted for by none or one neighbour.
            let Some(needed) = votes_needed(k, by_chance_per_neighbour, CHANCE) else {
                continue;
            };
            let (mut votes, mut misses) = (0, 0);
            for q in &near {
                if self.features.any_in_box(q.x + dx, q.y + dy, tolerance) {
                    votes += 1;
                } else {
                    misses += 1;
                    if k - misses < needed {
                        break;
                    }
                }
            }
            if votes < needed {
                continue;
            }
            let chance = binomial_tail(k, votes, by_chance_per_neighbour);
            if best.is_none_or(|(b, _)| chance < b) {
                best = Some((chance, (dx, dy)));
            }
        }
        best.map(|(_, d)| d)
    }

    /// A new track's first step from three frames, where its neighbours cannot tell it (they
    /// move differently, as in a vortex, or none is established yet): of the lone detections of
    /// the frame before last within `max_displacement_px`, the one that, with this track's
    /// detection, predicts a detection in this frame best at constant velocity, within
    /// `TURN_PER_FRAME` of the step. Without it a particle moving more than the linking box per
    /// frame through a rotating flow starts a new track every frame.
    pub(super) fn three_frame_step(
        &self,
        last: RectPoint,
        config: &LinkConfig,
    ) -> Option<(f64, f64)> {
        let reach = config.max_displacement_px;
        let mut best: Option<(f64, (f64, f64))> = None;
        for (before, _) in self.lone_before.near(last.x, last.y, reach) {
            let (dx, dy) = (last.x - before.x, last.y - before.y);
            let step = dx.hypot(dy);
            if step > reach {
                continue;
            }
            let tolerance = (TURN_PER_FRAME * step).max(2.0);
            let (x, y) = (last.x + dx, last.y + dy);
            let miss = self
                .features
                .near(x, y, tolerance)
                .map(|(c, _)| (c.x - x).hypot(c.y - y))
                .filter(|&m| m <= tolerance)
                .min_by(f64::total_cmp);
            if let Some(miss) = miss {
                let score = miss / tolerance;
                if best.is_none_or(|(b, _)| score < b) {
                    best = Some((score, (dx, dy)));
                }
            }
        }
        best.map(|(_, d)| d)
    }
}
