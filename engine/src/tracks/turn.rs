//! How far a broken 3D track's path may have turned since it was last seen, learnt from the
//! tracks' own steps. A rejoined track is looked for where a line through its last samples
//! puts it, and misses by centroid noise (the same at every step, which the pixel tolerance
//! allows for) plus the change in its velocity over a frame: in a vortex that grows with the
//! step (the path turns through a fixed angle per frame), in a uniform flow it is nothing.
//! Each continuation of a track tells how far a constant-velocity prediction from its two
//! samples before would have missed it; how much more the longer steps miss than the shorter
//! ones is the turn. Medians keep it robust to the wrong links among the continuations.

use std::collections::VecDeque;

use super::{Sample, Track3d};
use crate::link::TURN_PER_FRAME;
use crate::spatial::median;

/// Continuations remembered: a few frames' worth in a dense flow, the run so far in a sparse one.
const KEPT: usize = 400;
/// Continuations needed before the learnt turn replaces the vortex-sized default.
const MIN_TEACHERS: usize = 20;
/// The longer steps tell a turn from noise once their median squared step is at least this
/// many times the shorter steps' (the longer at least 1.4 times as long).
const DISTINCT_STEPS_SQ: f64 = 2.0;
/// The square root of the median squared two-dimensional Gaussian miss is 1.18 times its
/// per-axis sigma, so 2.5 of them are three sigmas.
const TOLERANCE_MEDIANS: f64 = 2.5;

/// The recent continuations: each one's squared step and squared miss, pixels squared.
#[derive(Debug, Clone, Default)]
pub(super) struct Turns {
    steps: VecDeque<(f64, f64)>,
}

impl Turns {
    /// Learns from `track` continued by `new`, where its two newest samples and `new` are in
    /// consecutive frames.
    pub(super) fn learn(&mut self, track: &Track3d, new: &Sample) {
        let n = track.samples.len();
        if n < 2 {
            return;
        }
        let (a, b) = (&track.samples[n - 2], &track.samples[n - 1]);
        if a.seq + 1 != b.seq || b.seq + 1 != new.seq {
            return;
        }
        let ahead = (new.t_s - b.t_s) / (b.t_s - a.t_s);
        if !ahead.is_finite() {
            return;
        }
        let (step_x, step_y) = (b.left_rect.x - a.left_rect.x, b.left_rect.y - a.left_rect.y);
        let miss_sq = (new.left_rect.x - (b.left_rect.x + step_x * ahead)).powi(2)
            + (new.left_rect.y - (b.left_rect.y + step_y * ahead)).powi(2);
        self.steps
            .push_back((step_x * step_x + step_y * step_y, miss_sq));
        if self.steps.len() > KEPT {
            self.steps.pop_front();
        }
    }

    /// How far, per pixel of a track's step, its rejoining particle may lie from the line's
    /// prediction: three sigmas of the turn, or a vortex's turn before there are enough
    /// continuations. A miss is centroid noise (the same at every step; the pixel tolerance
    /// allows for it) plus the turn (in proportion to the step), so the turn is what the
    /// misses grow by from the shorter half of the steps to the longer: the median squared
    /// miss of each half against its median squared step.
    pub(super) fn per_frame(&self) -> f64 {
        if self.steps.len() < MIN_TEACHERS {
            return TURN_PER_FRAME;
        }
        let mut by_step: Vec<(f64, f64)> = self.steps.iter().copied().collect();
        by_step.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
        let (shorter, longer) = by_step.split_at(by_step.len() / 2);
        let medians = |half: &[(f64, f64)]| {
            let mut steps: Vec<f64> = half.iter().map(|s| s.0).collect();
            let mut misses: Vec<f64> = half.iter().map(|s| s.1).collect();
            (median(&mut steps), median(&mut misses))
        };
        let ((step_short, miss_short), (step_long, miss_long)) =
            (medians(shorter), medians(longer));
        // Steps too alike cannot tell a turn from noise.
        if step_long < DISTINCT_STEPS_SQ * step_short {
            return TURN_PER_FRAME;
        }
        let turn_sq = ((miss_long - miss_short) / (step_long - step_short)).max(0.0);
        TOLERANCE_MEDIANS * turn_sq.sqrt()
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

    fn learnt_from(paths: &[Vec<Sample>]) -> Turns {
        let mut turns = Turns::default();
        for path in paths {
            let mut track = Track3d::new(1, 1);
            for s in path {
                turns.learn(&track, s);
                track.samples.push_back(s.clone());
            }
        }
        turns
    }

    #[test]
    fn a_vortex_teaches_its_turn_and_a_straight_flow_none() {
        // A solid-body vortex: every particle turns through the same angle per frame, so a
        // line misses by the chord turned through, 2 sin(turn / 2) of the step, whatever the
        // radius.
        let vortex: Vec<Vec<Sample>> = [5.0, 10.0, 20.0, 40.0]
            .iter()
            .map(|&step| circle(0.3, step, 8))
            .collect();
        let expected = TOLERANCE_MEDIANS * 2.0 * (0.15f64).sin();
        let learnt = learnt_from(&vortex).per_frame();
        assert!(
            (learnt - expected).abs() < 1e-9,
            "{learnt} against {expected}"
        );
        let straight: Vec<Vec<Sample>> = [5.0, 10.0, 20.0, 40.0]
            .iter()
            .map(|&step| circle(1e-6, step, 8))
            .collect();
        assert!(learnt_from(&straight).per_frame() < 1e-5);
    }

    #[test]
    fn noise_that_does_not_grow_with_the_step_is_no_turn() {
        let mut turns = Turns::default();
        for k in 0..100 {
            let step_px = 1.0 + f64::from(k);
            turns.steps.push_back((step_px * step_px, 4.0));
        }
        assert_eq!(turns.per_frame(), 0.0);
    }

    #[test]
    fn too_few_steps_or_steps_all_alike_keep_the_default() {
        assert_eq!(Turns::default().per_frame(), TURN_PER_FRAME);
        let alike = learnt_from(&vec![circle(0.3, 20.0, 8); 5]);
        assert_eq!(alike.per_frame(), TURN_PER_FRAME);
    }
}
