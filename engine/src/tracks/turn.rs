//! How far a broken 3D track's path may have turned since it was last seen, learnt from the
//! tracks' own steps. A rejoined track is looked for where a line through its last samples
//! puts it, and misses by about the change in its velocity over a frame: in a vortex that
//! grows with the step (the path turns through a fixed angle per frame), in a uniform flow it
//! is centroid noise. Each continuation of a track tells how far a constant-velocity
//! prediction from its two samples before would have missed it, per pixel of the step; the
//! median of the recent ones is robust to the wrong links among them.

use std::collections::VecDeque;

use super::{Sample, Track3d};
use crate::link::TURN_PER_FRAME;
use crate::spatial::median;

/// Continuations remembered: a few frames' worth in a dense flow, the run so far in a sparse one.
const KEPT: usize = 400;
/// Continuations needed before the learnt turn replaces the vortex-sized default.
const MIN_TEACHERS: usize = 20;
/// The median of a two-dimensional Gaussian miss is 1.18 times its per-axis sigma, so 2.5
/// medians are three sigmas.
const TOLERANCE_MEDIANS: f64 = 2.5;

/// The recent misses of constant-velocity predictions, per pixel of step.
#[derive(Debug, Clone, Default)]
pub(super) struct Turns {
    ratios: VecDeque<f64>,
}

impl Turns {
    /// Learns from `track` continued by `new`, where its two newest samples and `new` are in
    /// consecutive frames and the step before `new` is longer than `min_step_px` (shorter steps
    /// are judged by that floor, not by their turn).
    pub(super) fn learn(&mut self, track: &Track3d, new: &Sample, min_step_px: f64) {
        let n = track.samples.len();
        if n < 2 {
            return;
        }
        let (a, b) = (&track.samples[n - 2], &track.samples[n - 1]);
        if a.seq + 1 != b.seq || b.seq + 1 != new.seq {
            return;
        }
        let ahead = (new.t_s - b.t_s) / (b.t_s - a.t_s);
        let (step_x, step_y) = (b.left_rect.x - a.left_rect.x, b.left_rect.y - a.left_rect.y);
        let step_px = step_x.hypot(step_y);
        if !(step_px > min_step_px && ahead.is_finite()) {
            return;
        }
        let miss_px = (new.left_rect.x - (b.left_rect.x + step_x * ahead))
            .hypot(new.left_rect.y - (b.left_rect.y + step_y * ahead));
        self.ratios.push_back(miss_px / step_px);
        if self.ratios.len() > KEPT {
            self.ratios.pop_front();
        }
    }

    /// How far, per pixel of a track's step, its rejoining particle may lie from the line's
    /// prediction: three sigmas of the recent misses, or a vortex's turn before there are
    /// enough of them.
    pub(super) fn per_frame(&self) -> f64 {
        if self.ratios.len() < MIN_TEACHERS {
            return TURN_PER_FRAME;
        }
        let mut ratios: Vec<f64> = self.ratios.iter().copied().collect();
        TOLERANCE_MEDIANS * median(&mut ratios)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::detect::Separation;
    use crate::geometry::RectPoint;
    use nalgebra::Point3;

    fn sample(seq: u64, x: f64, y: f64) -> Sample {
        Sample {
            seq,
            frame_index: seq,
            t_s: seq as f64 / 30.0,
            point_in_world: Point3::new(x, y, 0.5),
            depth_m: 0.5,
            separation: Separation::Clear,
            left_rect: RectPoint { x, y },
            camera_in_world: Point3::origin(),
            seen_from: None,
        }
    }

    /// A particle on a circle, turning through `turn` radians per frame with steps of
    /// `step_px`: its first `n` samples.
    fn circle(turn: f64, step_px: f64, n: u64) -> Vec<Sample> {
        let radius = step_px / (2.0 * (turn / 2.0).sin());
        (0..n)
            .map(|k| {
                let angle = turn * k as f64;
                sample(k + 1, radius * angle.cos(), radius * angle.sin())
            })
            .collect()
    }

    fn learnt_from(paths: &[Vec<Sample>], min_step_px: f64) -> Turns {
        let mut turns = Turns::default();
        for path in paths {
            let mut track = Track3d::new(1, 1);
            for s in path {
                turns.learn(&track, s, min_step_px);
                track.samples.push_back(s.clone());
            }
        }
        turns
    }

    #[test]
    fn a_vortex_teaches_its_turn_and_a_straight_flow_almost_none() {
        // A line misses a circle by the chord turned through: 2 sin(turn / 2) of a step.
        let vortex = learnt_from(&vec![circle(0.3, 20.0, 8); 5], 3.0);
        let expected = TOLERANCE_MEDIANS * 2.0 * (0.15f64).sin();
        assert!((vortex.per_frame() - expected).abs() < 1e-9, "{vortex:?}");
        let straight = learnt_from(&vec![circle(1e-6, 20.0, 8); 5], 3.0);
        assert!(straight.per_frame() < 1e-5, "{straight:?}");
    }

    #[test]
    fn too_few_steps_or_steps_within_the_floor_keep_the_default() {
        assert_eq!(Turns::default().per_frame(), TURN_PER_FRAME);
        let slow = learnt_from(&vec![circle(0.3, 2.0, 8); 5], 3.0);
        assert_eq!(slow.per_frame(), TURN_PER_FRAME);
    }
}
