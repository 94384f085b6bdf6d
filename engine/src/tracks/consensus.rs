//! The steps particles took into this frame: a track with a path of its own took a known one;
//! the others' are found by neighbour consensus in 3D, as in a fast flow the per-camera links
//! and a young track's own guesses are wrong more often than right, but a particle's neighbours
//! move nearly as it does.
//! Of the steps a particle of the frame before could have taken (to a particle of this frame
//! within the linking reach), the one its nearest neighbours could also have taken, most
//! closely, is its step, if chance explains their votes less than once in a thousand.
//!
//! Neighbours' steps differ by the flow's gradient times their distance; a flow whose steps
//! differ by half the particles' spacing or more is not resolved by them (no tracking could
//! follow it), so a neighbour votes for a step where it has one within half its distance of it,
//! or within twice the gradient the last frame's flow showed times that distance where that is
//! less (and the depth noise of both). A wide tolerance also catches unrelated particles: votes
//! are weighed against how likely the neighbour's own candidates fall there by chance.

use nalgebra::{Point3, Vector3};

use super::flow::nearest_in_space;
use super::{left_image_grid, Sample};
use crate::geometry::Rectification;
use crate::spatial::{votes_needed, PointGrid};

/// Neighbours that vote on a particle's step.
const NEIGHBOURS: usize = 8;
/// A neighbour's step may differ from the particle's by this fraction of their distance.
const GRADIENT: f64 = 0.5;
/// Where the flow's gradient was seen in the frame before, a neighbour's step may differ by
/// this many times its median (the gradient varies through a flow), up to [`GRADIENT`].
const GRADIENT_MEDIANS: f64 = 2.0;
/// Votes are accepted where chance explains them less often than this.
const CHANCE: f64 = 1e-3;
/// Candidate steps a particle is judged on: its nearest in 3D.
const CANDIDATES: usize = 12;
/// Depth-noise sigmas added to the tolerance.
const DEPTH_SIGMAS: f64 = 3.0;

/// One particle's candidate steps (the particle of this frame and the step to it), and its
/// reach in the world.
struct Candidates {
    steps: Vec<(usize, Vector3<f64>)>,
    reach_m: f64,
}

/// The step (index into `after`) each of `before` took: the `known` one (a settled track's), or
/// else by consensus, where one is clear: `(before, after)` pairs (`after_grid` indexes `after`
/// by their left image points). Candidates lie within `reach_px` in the left image
/// (rectification `rect`, depth model `disparity_sigma_px`).
pub(super) fn steps(
    (before, known): (&[&Sample], &[Option<usize>]),
    (after, after_grid): (&[&Sample], &PointGrid),
    (reach_px, gradient): (f64, Option<f64>),
    rect: &Rectification,
    disparity_sigma_px: f64,
) -> Vec<(usize, usize)> {
    if before.len() <= NEIGHBOURS || after.is_empty() {
        return Vec::new();
    }
    let before_grid = left_image_grid(before);
    let after_positions: Vec<Point3<f64>> = after.iter().map(|s| s.point_in_world).collect();
    let candidates: Vec<Candidates> = before
        .iter()
        .zip(known)
        .map(|(a, known)| match known {
            Some(j) => Candidates {
                steps: vec![(*j, after[*j].point_in_world - a.point_in_world)],
                reach_m: reach_m(a, reach_px, rect),
            },
            None => candidates_of(a, (after_grid, &after_positions), after, reach_px, rect),
        })
        .collect();
    let positions: Vec<Point3<f64>> = before.iter().map(|s| s.point_in_world).collect();
    let gradient_allowed = gradient.map_or(GRADIENT, |g| (GRADIENT_MEDIANS * g).min(GRADIENT));
    let mut steps = Vec::new();
    for (i, a) in before.iter().enumerate() {
        if let Some(j) = known[i] {
            steps.push((i, j));
            continue;
        }
        let near = nearest_in_space(
            &before_grid,
            (a.left_rect, &a.point_in_world),
            &positions,
            NEIGHBOURS,
            i,
        );
        let noise = |s: &Sample| DEPTH_SIGMAS * rect.depth_sigma_m(s.depth_m, disparity_sigma_px);
        let tolerances: Vec<f64> = near
            .iter()
            .map(|&k| {
                gradient_allowed * (before[k].point_in_world - a.point_in_world).norm()
                    + noise(a)
                    + noise(before[k])
            })
            .collect();
        let Some(needed) = votes_needed_among(&near, &tolerances, &candidates) else {
            continue;
        };
        let best = candidates[i]
            .steps
            .iter()
            .filter_map(|&(j, step)| {
                let agreement = agreement_on(step, (&near, &tolerances), &candidates, needed)?;
                Some((agreement, j))
            })
            .max_by(|x, y| x.0.total_cmp(&y.0).then(y.1.cmp(&x.1)));
        if let Some((_, j)) = best {
            steps.push((i, j));
        }
    }
    steps
}

/// The [`CANDIDATES`] particles of `after` nearest `a` in 3D (among those nearest it in the
/// image, `grid` indexing `after` by their image points, `positions` theirs in the world) that
/// lie within `reach_px` of it in the left image, with the steps to them.
fn candidates_of(
    a: &Sample,
    (grid, positions): (&PointGrid, &[Point3<f64>]),
    after: &[&Sample],
    reach_px: f64,
    rect: &Rectification,
) -> Candidates {
    let near = nearest_in_space(
        grid,
        (a.left_rect, &a.point_in_world),
        positions,
        CANDIDATES,
        usize::MAX,
    );
    let reach_m = reach_m(a, reach_px, rect);
    let steps = near
        .into_iter()
        .filter(|&j| after[j].left_rect.distance_sq(a.left_rect) <= reach_px * reach_px)
        .map(|j| (j, after[j].point_in_world - a.point_in_world))
        .filter(|(_, step)| step.norm_squared() <= reach_m * reach_m)
        .collect();
    Candidates { steps, reach_m }
}

/// The linking reach at `a`'s depth, metres.
fn reach_m(a: &Sample, reach_px: f64, rect: &Rectification) -> f64 {
    reach_px * a.depth_m / rect.focal_px
}

/// The votes of the neighbours `near` (each within its `tolerance`) that beat chance once in
/// a thousand; `None` where even all of them would not.
fn votes_needed_among(
    near: &[usize],
    tolerances: &[f64],
    candidates: &[Candidates],
) -> Option<usize> {
    // A neighbour's candidates lie anywhere within its reach: the chance that one of them lies
    // within the tolerance of a step. Where more than its candidates lie there this understates
    // the chance; the flow fitted to the steps leaves out those that disagree with their
    // neighbours, and trusts itself only where it misses little.
    let p_sum: f64 = near
        .iter()
        .zip(tolerances)
        .map(|(&k, &tolerance)| {
            let theirs = &candidates[k];
            let fraction = (tolerance / theirs.reach_m.max(f64::EPSILON))
                .powi(3)
                .min(1.0);
            1.0 - (1.0 - fraction).powi(theirs.steps.len() as i32)
        })
        .sum();
    let n = near.len();
    votes_needed(n, p_sum / n.max(1) as f64, CHANCE)
}

/// How closely the neighbours (`near`, each within its `tolerance`) agree on `step`: summed
/// over those that vote for it, one less the squared miss of their closest step in units of the
/// tolerance (neighbours that could have taken exactly that step weigh most); `None` where
/// fewer than `needed` vote for it.
fn agreement_on(
    step: Vector3<f64>,
    (near, tolerances): (&[usize], &[f64]),
    candidates: &[Candidates],
    needed: usize,
) -> Option<f64> {
    let (mut votes, mut misses) = (0, 0);
    let mut agreement = 0.0;
    for (&k, &tolerance) in near.iter().zip(tolerances) {
        let closest_sq = candidates[k]
            .steps
            .iter()
            .map(|(_, s)| (s - step).norm_squared())
            .fold(f64::INFINITY, f64::min);
        if closest_sq <= tolerance * tolerance {
            votes += 1;
            agreement += 1.0 - closest_sq / (tolerance * tolerance);
        } else {
            misses += 1;
            // Too few neighbours are left to outvote chance.
            if near.len() - misses < needed {
                return None;
            }
        }
    }
    (votes >= needed).then_some(agreement)
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;
    use crate::detect::Separation;
    use crate::synth::{Scenario, ScenarioSpec};
    use nalgebra::Rotation3;

    fn sample(seq: u64, p: Point3<f64>, rect: &Rectification) -> Sample {
        let (left, _) = rect.project(&p).expect("in view");
        Sample {
            seq,
            frame_index: seq,
            t_s: seq as f64 / 30.0,
            point_in_world: p,
            depth_m: p.z,
            separation: Separation::Clear,
            left_rect: left,
            camera_in_world: Point3::origin(),
            seen_from: None,
        }
    }

    /// 81 particles scattered through a slab 27 cm wide and 3 cm deep (about 3 cm apart),
    /// turning about the viewing axis by 0.3 radians per frame, so the rim moves as far as
    /// the spacing: (before, after), the same order.
    pub(in crate::tracks) fn vortex(rect: &Rectification) -> (Vec<Sample>, Vec<Sample>) {
        let centre = Point3::new(0.0, 0.0, 0.5);
        let spin = Rotation3::from_axis_angle(&Vector3::z_axis(), 0.3);
        let mut state = 12_345u64;
        let mut uniform = move || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut before = Vec::new();
        let mut after = Vec::new();
        for _ in 0..81 {
            let p = Point3::new(
                0.27 * (uniform() - 0.5),
                0.27 * (uniform() - 0.5),
                0.5 + 0.03 * uniform(),
            );
            before.push(sample(1, p, rect));
            after.push(sample(2, centre + spin * (p - centre), rect));
        }
        (before, after)
    }

    #[test]
    fn neighbours_agree_on_the_steps_of_a_vortex_as_fast_as_its_spacing() {
        let rect = Rectification::new(&ScenarioSpec::new(Scenario::Flume).rig).expect("rectifies");
        let (before, after) = vortex(&rect);
        let (b, a): (Vec<&Sample>, Vec<&Sample>) =
            (before.iter().collect(), after.iter().collect());
        let steps = unknown_steps(&b, &a, &rect);
        let right = steps.iter().filter(|(i, j)| i == j).count();
        assert!(right >= 75, "{right} of {} right", before.len());
        assert_eq!(right, steps.len(), "no wrong step: {steps:?}");
        // The nearest particle of the next frame is often another one.
        let nearest_right = b
            .iter()
            .enumerate()
            .filter(|(i, s)| {
                let d = |j: usize| (a[j].point_in_world - s.point_in_world).norm();
                (0..a.len()).min_by(|&x, &y| d(x).total_cmp(&d(y))) == Some(*i)
            })
            .count();
        assert!(nearest_right < 60, "{nearest_right}");
    }

    #[test]
    fn without_neighbours_enough_no_step_is_taken() {
        let rect = Rectification::new(&ScenarioSpec::new(Scenario::Flume).rig).expect("rectifies");
        let (before, after) = vortex(&rect);
        let b: Vec<&Sample> = before.iter().take(NEIGHBOURS).collect();
        let a: Vec<&Sample> = after.iter().collect();
        assert!(unknown_steps(&b, &a, &rect).is_empty());
    }

    /// The steps from `before` to `after` by consensus alone (no step known), within 100 px.
    fn unknown_steps(
        before: &[&Sample],
        after: &[&Sample],
        rect: &Rectification,
    ) -> Vec<(usize, usize)> {
        let grid = left_image_grid(after);
        steps(
            (before, &vec![None; before.len()]),
            (after, &grid),
            (100.0, None),
            rect,
            0.1,
        )
    }
}
