//! The flow around a young track: where the particles around it went in this frame. A new
//! stereo pair has no motion of its own, and the per-camera chain links it to the next frame
//! only where it moved less than the linking box; in a fast flow (a vortex, wind) its 3D
//! neighbours know better. Each particle's step from the frame before into this one (known, or
//! found by [`super::consensus`]) is a sample of the flow over exactly this frame interval (head
//! motion included, as the world and the images moved alike for all of them), at where it
//! started.
//!
//! The flow at a point is an affine fit to the steps of the particles nearest it in space, so a
//! vortex (a flow linear in position) is followed exactly, on either side of the point. How far
//! the flow misses is learnt the same way: each step against the fit of its neighbours without
//! it, along and across its line of sight (depth noise is largest along it).

use nalgebra::{Matrix4, Point3, SMatrix, Vector3, Vector4};

use super::Sample;
use crate::geometry::{RectPoint, Rectification};
use crate::spatial::{median, PointGrid, GRID_CELL_PX};

/// The teaching tracks an affine fit is made of: enough to outnumber a wrong link or two.
const NEIGHBOURS: usize = 8;
/// The fewest teaching tracks a fit is trusted with: the affine model has four parameters.
const MIN_NEIGHBOURS: usize = 6;
/// A teaching track whose step strays from the first fit by more than this many times the
/// median stray is a wrong link or a ghost, and is left out of the second.
const OUTLIER_MEDIANS: f64 = 3.0;
/// Keeps the gradient's normal equations regular where the neighbours lie in a plane or a line
/// (a thin sheet of particles): a fraction of their spread along each axis.
const RIDGE: f64 = 1e-3;
/// Teaching tracks the miss is learnt from, at most (evenly spread among them): the median
/// settles long before a dense flow's thousands.
const MISS_TEACHERS: usize = 256;
/// The miss across the line of sight is two-dimensional: the square root of its median
/// squared length is 1.18 of its per-axis sigma, so 2.5 medians are three sigmas.
const ACROSS_MEDIANS: f64 = 2.5;
/// Along it the miss is one-dimensional: its median absolute value is 0.674 sigmas, so 4.45
/// medians are three sigmas.
const ALONG_MEDIANS: f64 = 4.45;
/// No tolerance across the line of sight is narrower: centroid noise of both samples.
const MIN_ACROSS_PX: f64 = 1.0;
/// Nor along it, in depth-noise sigmas.
const MIN_ALONG_SIGMAS: f64 = 3.0;

/// Velocity in the world (metres per second) and in the left image (rectified pixels per
/// second).
type Motion = SMatrix<f64, 1, 5>;

/// The steps of the tracks continued into this frame, by where they started.
pub(super) struct Flow {
    grid: PointGrid,
    /// Each teaching track's start in the world.
    starts: Vec<Point3<f64>>,
    /// Its motion over the step.
    motions: Vec<Motion>,
    /// Its start in the left image.
    starts_image: Vec<RectPoint>,
    /// How long its step took, seconds.
    steps_s: Vec<f64>,
    /// Its newest sample's line of sight and depth, for its miss.
    ends: Vec<Sample>,
    /// Median miss of the flow across the line of sight (rectified pixels) and along it
    /// (depth-noise sigmas); `None` before there are teaching tracks enough.
    miss: Option<[f64; 2]>,
    /// Median size of the flow's gradient (Frobenius norm) over a step: how much two particles'
    /// steps differ per metre between them.
    gradient: Option<f64>,
}

/// Where the flow carries a particle, and how far off it may be found.
pub(super) struct Carried {
    pub(super) world: Point3<f64>,
    /// In the left image, rectified.
    pub(super) image: RectPoint,
    /// Tolerance across the line of sight, rectified pixels.
    pub(super) across_px: f64,
    /// Tolerance along it, depth-noise sigmas.
    pub(super) along_sigmas: f64,
}

impl Flow {
    /// The flow of the particles' `steps` into this frame (each a sample of the frame before
    /// and one of this frame), with the miss learnt from them (`rect` and the depth model's
    /// `disparity_sigma_px` convert it); `spacing_px` is the median distance between
    /// neighbouring particle images.
    pub(super) fn of<'a>(
        steps: impl Iterator<Item = (&'a Sample, &'a Sample)>,
        spacing_px: f64,
        rect: &Rectification,
        disparity_sigma_px: f64,
    ) -> Self {
        let mut starts = Vec::new();
        let mut motions = Vec::new();
        let mut starts_image = Vec::new();
        let mut steps_s = Vec::new();
        let mut ends = Vec::new();
        for (a, b) in steps {
            let dt = b.t_s - a.t_s;
            if dt <= 0.0 {
                continue;
            }
            let world = (b.point_in_world - a.point_in_world) / dt;
            let image = [
                (b.left_rect.x - a.left_rect.x) / dt,
                (b.left_rect.y - a.left_rect.y) / dt,
            ];
            starts.push(a.point_in_world);
            starts_image.push(a.left_rect);
            steps_s.push(dt);
            motions.push(Motion::from_row_slice(&[
                world.x, world.y, world.z, image[0], image[1],
            ]));
            ends.push(b.clone());
        }
        let mut flow = Self {
            grid: PointGrid::new(starts_image.iter().copied().zip(0..), GRID_CELL_PX),
            starts,
            motions,
            starts_image,
            steps_s,
            ends,
            miss: None,
            gradient: None,
        };
        // A flow that misses by half the spacing of particle images or more would carry a
        // particle to its neighbour as often as to itself: it carries none.
        let learnt = flow.learn_miss(rect, disparity_sigma_px);
        flow.gradient = learnt.map(|[_, _, gradient]| gradient);
        flow.miss = learnt
            .map(|[across, along, _]| [across, along])
            .filter(|[across, _]| ACROSS_MEDIANS * across < 0.5 * spacing_px);
        flow
    }

    /// Where the flow carries a particle last seen at `last` by time `t_s`; `None` where too few
    /// tracks surround it or the miss is not learnt yet.
    pub(super) fn carry(&self, last: &Sample, t_s: f64) -> Option<Carried> {
        let [across, along] = self.miss?;
        let near = nearest_in_space(
            &self.grid,
            (last.left_rect, &last.point_in_world),
            &self.starts,
            NEIGHBOURS,
            usize::MAX,
        );
        // Only among its neighbours in depth: a ghost pair in front of or behind every particle
        // around it is where no flow was seen, and the fit would be extrapolated there.
        let among = |value: f64, of: &dyn Fn(usize) -> f64| {
            let (low, high) = near
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &i| {
                    (l.min(of(i)), h.max(of(i)))
                });
            (low..=high).contains(&value)
        };
        if !among(last.depth_m, &|i| self.ends[i].depth_m) {
            return None;
        }
        let motion = self.fit(&last.point_in_world, near)?.row(0).into_owned();
        let dt = t_s - last.t_s;
        Some(Carried {
            world: last.point_in_world + Vector3::new(motion[0], motion[1], motion[2]) * dt,
            image: RectPoint {
                x: last.left_rect.x + motion[3] * dt,
                y: last.left_rect.y + motion[4] * dt,
            },
            across_px: (ACROSS_MEDIANS * across).max(MIN_ACROSS_PX),
            along_sigmas: (ALONG_MEDIANS * along).max(MIN_ALONG_SIGMAS),
        })
    }

    /// How much two particles' steps differ per metre between them, typically.
    pub(super) fn gradient(&self) -> Option<f64> {
        self.gradient
    }

    /// Median miss of each of up to [`MISS_TEACHERS`] teaching tracks against the fit of its
    /// neighbours without it: across its line of sight in pixels, along it in depth sigmas.
    fn learn_miss(&self, rect: &Rectification, disparity_sigma_px: f64) -> Option<[f64; 3]> {
        let n = self.starts.len();
        let stride = n.div_ceil(MISS_TEACHERS).max(1);
        let mut across = Vec::new();
        let mut along = Vec::new();
        let mut gradients = Vec::new();
        for i in (0..n).step_by(stride) {
            let end = &self.ends[i];
            let near = nearest_in_space(
                &self.grid,
                (self.starts_image[i], &self.starts[i]),
                &self.starts,
                NEIGHBOURS,
                i,
            );
            let Some(fit) = self.fit(&self.starts[i], near) else {
                continue;
            };
            let motion = fit.row(0);
            let dt = self.steps_s[i];
            gradients.push(fit.fixed_view::<3, 3>(1, 0).norm() * dt);
            let miss = Vector3::new(
                self.motions[i][0] - motion[0],
                self.motions[i][1] - motion[1],
                self.motions[i][2] - motion[2],
            ) * dt;
            let (a, across_sq) = end.along_and_across_sq(&miss);
            let depth = end.depth_m.max(f64::EPSILON);
            across.push(across_sq.sqrt() * rect.focal_px / depth);
            along.push(a.abs() / rect.depth_sigma_m(depth, disparity_sigma_px));
        }
        (across.len() >= MIN_NEIGHBOURS).then(|| {
            [
                median(&mut across),
                median(&mut along),
                median(&mut gradients),
            ]
        })
    }

    /// The motion at `p` of an affine fit to the teaching tracks `near` it, refitted without
    /// those that stray far from the first fit.
    fn fit(&self, p: &Point3<f64>, mut near: Vec<usize>) -> Option<SMatrix<f64, 4, 5>> {
        if near.len() < MIN_NEIGHBOURS {
            return None;
        }
        near.sort_unstable();
        let first = self.affine(p, &near)?;
        let strays: Vec<f64> = near.iter().map(|&i| self.stray(p, i, &first)).collect();
        let limit = OUTLIER_MEDIANS * median(&mut strays.clone());
        let kept: Vec<usize> = near
            .iter()
            .zip(&strays)
            .filter(|(_, &s)| s <= limit)
            .map(|(&i, _)| i)
            .collect();
        if kept.len() == near.len() || kept.len() < MIN_NEIGHBOURS {
            return Some(first);
        }
        self.affine(p, &kept)
    }

    /// How far teaching track `i`'s world motion strays from an affine `fit` about `p`.
    fn stray(&self, p: &Point3<f64>, i: usize, fit: &SMatrix<f64, 4, 5>) -> f64 {
        let d = self.starts[i] - p;
        let row = Vector4::new(1.0, d.x, d.y, d.z).transpose() * fit;
        (0..3)
            .map(|c| (row[c] - self.motions[i][c]).powi(2))
            .sum::<f64>()
            .sqrt()
    }

    /// Least-squares affine motion about `p` of the teaching tracks `near`: its first row is
    /// the motion at `p`, the others its gradient along the world axes.
    fn affine(&self, p: &Point3<f64>, near: &[usize]) -> Option<SMatrix<f64, 4, 5>> {
        let mut normal = Matrix4::zeros();
        let mut rhs = SMatrix::<f64, 4, 5>::zeros();
        for &i in near {
            let d = self.starts[i] - p;
            let row = Vector4::new(1.0, d.x, d.y, d.z);
            normal += row * row.transpose();
            rhs += row * self.motions[i];
        }
        let n = near.len() as f64;
        for axis in 1..4 {
            normal[(axis, axis)] += RIDGE * normal[(axis, axis)].max(f64::EPSILON * n);
        }
        Some(normal.cholesky()?.solve(&rhs))
    }
}

/// Searched in the image for neighbours in space: particles near in space are near in the
/// image, but particles near in the image may lie far apart in depth.
const IMAGE_NEIGHBOURS_PER_NEIGHBOUR: usize = 4;

/// The `k` points of `positions` nearest `p` in space but the `skip`-th, among those nearest
/// its `image` point in `grid` (which indexes `positions` by their image points), in no
/// particular order.
pub(super) fn nearest_in_space(
    grid: &PointGrid,
    (image, p): (RectPoint, &Point3<f64>),
    positions: &[Point3<f64>],
    k: usize,
    skip: usize,
) -> Vec<usize> {
    let mut found = Vec::with_capacity(4 * IMAGE_NEIGHBOURS_PER_NEIGHBOUR * k);
    grid.nearest_unordered(
        image.x,
        image.y,
        IMAGE_NEIGHBOURS_PER_NEIGHBOUR * k,
        skip,
        &mut found,
    );
    let mut by_space: Vec<(f64, usize)> = found
        .iter()
        .map(|(_, (_, i))| ((positions[*i] - p).norm_squared(), *i))
        .collect();
    if by_space.len() > k {
        by_space.select_nth_unstable_by(k, |a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        by_space.truncate(k);
    }
    by_space.into_iter().map(|(_, i)| i).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::detect::Separation;
    use crate::synth::{Scenario, ScenarioSpec};
    use crate::tracks::Track3d;
    use nalgebra::Rotation3;

    fn sample(seq: u64, p: Point3<f64>) -> Sample {
        Sample {
            seq,
            frame_index: seq,
            t_s: seq as f64 / 30.0,
            point_in_world: p,
            depth_m: p.z,
            separation: Separation::Clear,
            left_rect: RectPoint {
                x: 400.0 * p.x / p.z,
                y: 400.0 * p.y / p.z,
            },
            camera_in_world: Point3::origin(),
            seen_from: None,
        }
    }

    /// Tracks on a grid turning about the viewing axis through (0, 0, 0.5) at `turn` radians
    /// per frame, seen in frames 1 and 2.
    fn vortex(turn: f64) -> (Vec<Track3d>, impl Fn(Point3<f64>) -> Point3<f64>) {
        let centre = Point3::new(0.0, 0.0, 0.5);
        let spin = Rotation3::from_axis_angle(&Vector3::z_axis(), turn);
        let moved = move |p: Point3<f64>| centre + spin * (p - centre);
        let mut tracks = Vec::new();
        for i in -4..=4 {
            for j in -4..=4 {
                let p = Point3::new(0.02 * f64::from(i), 0.02 * f64::from(j), 0.5);
                let mut t = Track3d::new(tracks.len() as u64, 0);
                t.samples.push_back(sample(1, p));
                t.samples.push_back(sample(2, moved(p)));
                tracks.push(t);
            }
        }
        (tracks, moved)
    }

    fn flow_of(tracks: &[Track3d]) -> Flow {
        Flow::of(
            tracks.iter().map(|t| (&t.samples[0], &t.samples[1])),
            100.0,
            &rect(),
            0.1,
        )
    }

    fn rect() -> Rectification {
        Rectification::new(&ScenarioSpec::new(Scenario::Flume).rig).expect("rectifies")
    }

    #[test]
    fn a_vortex_carries_a_new_particle_along_its_turn() {
        let (tracks, moved) = vortex(0.2);
        let flow = flow_of(&tracks);
        // A particle off the grid, seen in frame 2, is carried where the vortex turns it.
        let p = Point3::new(0.031, -0.047, 0.5);
        let carried = flow.carry(&sample(2, p), 3.0 / 30.0).expect("carried");
        // Within micrometres: the ridge that keeps a plane of neighbours regular shortens the
        // gradient by a thousandth.
        assert!(
            (carried.world - moved(p)).norm() < 1e-5,
            "{} against {}",
            carried.world,
            moved(p)
        );
        // Carried more than a centimetre, along the turn.
        assert!((moved(p) - p).norm() > 0.01);
    }

    #[test]
    fn a_wrong_link_among_the_neighbours_is_outvoted() {
        let (mut tracks, moved) = vortex(0.2);
        let p = Point3::new(0.011, 0.009, 0.5);
        // The teaching track nearest the particle linked to another particle 3 cm away.
        let nearest = tracks
            .iter_mut()
            .min_by(|a, b| {
                let d = |t: &Track3d| (t.samples[0].point_in_world - p).norm();
                d(a).total_cmp(&d(b))
            })
            .expect("tracks");
        let wrong = nearest.samples[1].point_in_world + Vector3::new(0.03, 0.0, 0.0);
        nearest.samples[1] = sample(2, wrong);
        let flow = flow_of(&tracks);
        let carried = flow.carry(&sample(2, p), 3.0 / 30.0).expect("carried");
        assert!((carried.world - moved(p)).norm() < 1e-5);
    }

    #[test]
    fn the_miss_is_learnt_from_how_well_neighbours_predict_each_other() {
        let (tracks, _) = vortex(0.2);
        let flow = flow_of(&tracks);
        let miss = flow.miss.expect("learnt");
        assert!(miss[0] < 0.01 && miss[1] < 0.01, "{miss:?}");
        // The steps of a vortex turning 0.2 radians a frame differ by R - I per metre between
        // particles: a Frobenius norm of 2 sqrt(2) sin(0.1).
        let gradient = flow.gradient().expect("learnt");
        let expected = 2.0 * 2f64.sqrt() * 0.1f64.sin();
        assert!(
            (gradient - expected).abs() < 1e-3,
            "{gradient} against {expected}"
        );
        // Floors keep a perfect flow's tolerance at centroid noise.
        let carried = flow
            .carry(&sample(2, Point3::new(0.0, 0.0, 0.5)), 0.1)
            .expect("carried");
        assert_eq!(
            (carried.across_px, carried.along_sigmas),
            (MIN_ACROSS_PX, MIN_ALONG_SIGMAS)
        );
        // A flow that misses by half the spacing of the particle images carries nothing.
        let (mut noisy, _) = vortex(0.2);
        for (k, t) in noisy.iter_mut().enumerate() {
            let wobble = 0.004 * if k % 2 == 0 { 1.0 } else { -1.0 };
            let p = t.samples[1].point_in_world + Vector3::new(wobble, -wobble, 0.0);
            t.samples[1] = sample(2, p);
        }
        let steps = || noisy.iter().map(|t| (&t.samples[0], &t.samples[1]));
        let spacing_px = 400.0 * 0.02 / 0.5;
        assert!(Flow::of(steps(), 100.0, &rect(), 0.1).miss.is_some());
        assert!(Flow::of(steps(), spacing_px, &rect(), 0.1).miss.is_none());
        // Too few tracks learn nothing and carry nothing.
        let few = flow_of(&tracks[..4]);
        assert!(few.miss.is_none());
        assert!(few
            .carry(&sample(2, Point3::new(0.0, 0.0, 0.5)), 0.1)
            .is_none());
    }
}
