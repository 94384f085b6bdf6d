//! Young tracks vouched for by their neighbours. A track too young to be trusted on its own
//! samples predicts itself once its motion agrees with that of the mature tracks around it: a
//! ghost (a wrong stereo pair) can persist like a particle where the flow is smooth, but at its
//! wrong depth it does not move as its neighbours do. Only mature tracks vouch: at the start of
//! a run in a room, young ghosts of what stands still outnumber the particles. How closely a
//! young track's motion may be expected to agree is learnt from the mature tracks themselves,
//! each judged on its newest few samples as a young track is.
//!
//! Depth noise grows with the square of depth and noise across the line of sight with depth,
//! so a track's disagreement is measured in those units, along and across its line of sight.

use nalgebra::{Point3, Vector3};
use rayon::prelude::*;

use crate::geometry::RectPoint;
use crate::spatial::{median, PointGrid, GRID_CELL_PX};
use crate::tracks::{Sample, Track3d};
use crate::velocity::fit::fit_line;

use super::{newest, LINE_SAMPLES};

/// The mature tracks whose motion a track is compared with: its nearest in the image.
const NEIGHBOURS: usize = 8;
/// The fewest samples a track is judged on, and its motion taken as a neighbour's.
pub(super) const YOUNG_SAMPLES: usize = 3;
/// A young track agrees with its neighbours where, along and across its line of sight, it
/// strays from their motion by at most this many times the tracks' median stray.
const AGREEMENT: f64 = 4.0;

/// The motion of the mature tracks, by where each was last seen (left image, rectified), and how
/// far a track's newest samples typically stray from it.
pub(super) struct Neighbours {
    grid: PointGrid,
    /// The rectified images' focal length, pixels.
    focal_px: f64,
    velocities: Vec<Vector3<f64>>,
    /// Their newest samples' depths, metres.
    depths: Vec<f64>,
    /// Median stray along and across the line of sight, per depth squared and per depth.
    scatter: Option<[f64; 2]>,
}

impl Neighbours {
    /// The motion of those of `tracks` with at least `mature` samples, indexed by their order.
    pub(super) fn of(tracks: &[&Track3d], mature: usize, focal_px: f64) -> Self {
        // Each track's motion and stray on its own: both cores where they hold tracks enough,
        // in the tracks' order.
        let motions: Vec<_> = tracks
            .par_iter()
            .with_min_len(super::TRACKS_PER_TASK)
            .map(|track| {
                (track.samples.len() >= mature)
                    .then(|| {
                        let v = velocity(track, LINE_SAMPLES)?;
                        let v_young = velocity(track, YOUNG_SAMPLES)?;
                        Some((track.samples.back()?, v, v_young))
                    })
                    .flatten()
            })
            .collect();
        let mut seen: Vec<(usize, &Sample, Vector3<f64>)> = Vec::new();
        let mut velocities = Vec::with_capacity(motions.len());
        let mut depths = Vec::with_capacity(motions.len());
        for (i, motion) in motions.into_iter().enumerate() {
            // Indexed by the tracks' order; only the mature ones are ever looked up.
            velocities.push(motion.map_or_else(Vector3::zeros, |(_, v, _)| v));
            depths.push(motion.map_or(0.0, |(s, _, _)| s.depth_m));
            if let Some((last, _, v_young)) = motion {
                seen.push((i, last, v_young));
            }
        }
        let mut neighbours = Self {
            grid: PointGrid::new(seen.iter().map(|&(i, s, _)| (s.left_rect, i)), GRID_CELL_PX),
            focal_px,
            velocities,
            depths,
            scatter: None,
        };
        let strays: Vec<[f64; 2]> = seen
            .par_iter()
            .with_min_len(super::TRACKS_PER_TASK)
            .filter_map(|&(i, last, v)| {
                Some(stray(last, v - neighbours.flow_at(last.left_rect, i)?))
            })
            .collect();
        neighbours.scatter = (strays.len() >= NEIGHBOURS).then(|| {
            let mut along: Vec<f64> = strays.iter().map(|s| s[0]).collect();
            let mut across: Vec<f64> = strays.iter().map(|s| s[1]).collect();
            [median(&mut along), median(&mut across)]
        });
        neighbours
    }

    /// Whether `track` (the `own`-th of those the neighbours were built from) moves as the
    /// tracks around it do.
    pub(super) fn vouch_for(&self, track: &Track3d, own: usize) -> bool {
        let (Some(scatter), Some(last), Some(v)) = (
            self.scatter,
            track.samples.back(),
            velocity(track, track.samples.len()),
        ) else {
            return false;
        };
        self.flow_at(last.left_rect, own).is_some_and(|flow| {
            let [along, across] = stray(last, v - flow);
            along <= AGREEMENT * scatter[0] && across <= AGREEMENT * scatter[1]
        })
    }

    /// Where a track too young for a motion of its own (the `own`-th) is carried at `t_s` by
    /// the flow around it: its newest sample moved at its neighbours' median velocity. Only
    /// where the flow is known (enough mature tracks to judge by), where it predicts the mature
    /// tracks themselves to within `reach_px` in the image over that time (in a vortex a
    /// particle's neighbours move unlike it: a carry searched no wider than a particle image
    /// finds another particle), and where the track lies among its neighbours in depth: a
    /// young ghost in front of or behind every track around it is where no flow has been seen,
    /// and a flow carried there would move its image as no particle's.
    pub(super) fn carry(
        &self,
        track: &Track3d,
        own: usize,
        t_s: f64,
        reach_px: f64,
    ) -> Option<Point3<f64>> {
        let last = track.samples.back()?;
        let [_, across] = self.scatter?;
        if across * self.focal_px * (t_s - last.t_s) > reach_px {
            return None;
        }
        let near = self.nearest(last.left_rect, own)?;
        let depths = near.iter().map(|&i| self.depths[i]);
        let nearest = depths.clone().fold(f64::INFINITY, f64::min);
        let farthest = depths.fold(f64::NEG_INFINITY, f64::max);
        (nearest..=farthest)
            .contains(&last.depth_m)
            .then(|| last.point_in_world + self.median_velocity(&near) * (t_s - last.t_s))
    }

    /// The median velocity (per component) of the tracks nearest `p` but the `skip`-th; `None`
    /// where there are too few.
    fn flow_at(&self, p: RectPoint, skip: usize) -> Option<Vector3<f64>> {
        self.nearest(p, skip)
            .map(|near| self.median_velocity(&near))
    }

    /// The [`NEIGHBOURS`] tracks nearest `p` but the `skip`-th, by index, in no particular
    /// order (what is made of them does not depend on it); `None` where there are fewer.
    fn nearest(&self, p: RectPoint, skip: usize) -> Option<[usize; NEIGHBOURS]> {
        let mut found = Vec::with_capacity(4 * NEIGHBOURS);
        self.grid
            .nearest_unordered(p.x, p.y, NEIGHBOURS, skip, &mut found);
        (found.len() >= NEIGHBOURS).then(|| std::array::from_fn(|n| found[n].1 .1))
    }

    /// The median velocity (per component) of the tracks `near`.
    fn median_velocity(&self, near: &[usize]) -> Vector3<f64> {
        let component = |c: usize| {
            let mut values = [0.0; NEIGHBOURS];
            for (v, &i) in values.iter_mut().zip(near) {
                *v = self.velocities[i][c];
            }
            median(&mut values[..near.len().min(NEIGHBOURS)])
        };
        Vector3::new(component(0), component(1), component(2))
    }
}

/// How far a velocity `offset` strays, along the line of sight of the track's `last` sample per
/// depth squared and across it per depth: the units its noise is the same in at every depth.
fn stray(last: &Sample, offset: Vector3<f64>) -> [f64; 2] {
    let (along, across_sq) = last.along_and_across_sq(&offset);
    let depth = last.depth_m.max(f64::EPSILON);
    [along.abs() / (depth * depth), across_sq.sqrt() / depth]
}

/// The velocity of a line through the track's newest `n` samples (at least [`YOUNG_SAMPLES`]).
fn velocity(track: &Track3d, n: usize) -> Option<Vector3<f64>> {
    if track.samples.len() < YOUNG_SAMPLES {
        return None;
    }
    let samples = newest(&track.samples, n);
    let t_s = samples.last()?.0;
    fit_line(&samples, t_s).map(|f| f.velocity)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::detect::Separation;
    use nalgebra::Point3;
    use std::collections::VecDeque;

    /// The tracks' image scale (their left image points are their positions times it) and how
    /// far from a carried prediction its particle is looked for, pixels.
    const FOCAL_PX: f64 = 1000.0;
    const REACH_PX: f64 = 4.0;

    /// A track of `frames` samples moving at `velocity` from `start`, with a little noise (up to
    /// `wobble` metres) along its line of sight.
    fn track(start: Point3<f64>, velocity: Vector3<f64>, frames: u64, wobble: f64) -> Track3d {
        let samples = (1..=frames)
            .map(|seq| {
                let t_s = seq as f64 * 0.1;
                let noise = wobble * [0.0, 1.0, -1.0, 0.5][seq as usize % 4];
                Sample {
                    seq,
                    frame_index: seq,
                    t_s,
                    point_in_world: start + velocity * t_s + Vector3::z() * noise,
                    depth_m: start.z,
                    separation: Separation::Clear,
                    left_rect: RectPoint {
                        x: start.x * 1000.0,
                        y: start.y * 1000.0,
                    },
                    camera_in_world: Point3::origin(),
                    seen_from: None,
                }
            })
            .collect::<VecDeque<_>>();
        Track3d {
            samples,
            ..Track3d::new(1, 1)
        }
    }

    /// A flow of 0.1 m/s along x: a grid of tracks, each wobbling by its own amount.
    fn flow() -> Vec<Track3d> {
        (0..25)
            .map(|i| {
                let start = Point3::new(0.01 * (i % 5) as f64, 0.01 * (i / 5) as f64, 0.5);
                let wobble = 1e-5 * (1 + i % 4) as f64;
                track(start, Vector3::x() * 0.1, 10, wobble)
            })
            .collect()
    }

    #[test]
    fn a_young_track_moving_with_its_neighbours_is_vouched_for_and_a_ghost_is_not() {
        let mut tracks = flow();
        let at = Point3::new(0.02, 0.02, 0.5);
        tracks.push(track(at, Vector3::x() * 0.1, 3, 1e-5));
        // A ghost at the wrong depth: its image moves with the flow, but not its 3D motion.
        tracks.push(track(at, Vector3::new(0.07, 0.0, -0.02), 3, 1e-5));
        let neighbours = Neighbours::of(&tracks.iter().collect::<Vec<_>>(), 10, FOCAL_PX);
        let n = tracks.len();
        assert!(neighbours.vouch_for(&tracks[n - 2], n - 2));
        assert!(!neighbours.vouch_for(&tracks[n - 1], n - 1));
    }

    #[test]
    fn a_new_pair_among_its_neighbours_is_carried_by_their_flow_and_one_behind_them_is_not() {
        let mut tracks = flow();
        tracks.push(track(
            Point3::new(0.02, 0.02, 0.5),
            Vector3::zeros(),
            1,
            0.0,
        ));
        // The same image position at twice the depth: behind every track around it.
        let mut behind = track(Point3::new(0.02, 0.02, 1.0), Vector3::zeros(), 1, 0.0);
        behind.samples[0].left_rect = tracks[tracks.len() - 1].samples[0].left_rect;
        tracks.push(behind);
        let neighbours = Neighbours::of(&tracks.iter().collect::<Vec<_>>(), 10, FOCAL_PX);
        let n = tracks.len();
        let carried = neighbours
            .carry(&tracks[n - 2], n - 2, 0.3, REACH_PX)
            .expect("carried");
        // Its one sample was at t = 0.1 s; the flow moves it 0.1 m/s along x for 0.2 s.
        assert!(
            (carried - Point3::new(0.04, 0.02, 0.5)).norm() < 1e-3,
            "{carried}"
        );
        assert!(neighbours
            .carry(&tracks[n - 1], n - 1, 0.3, REACH_PX)
            .is_none());
    }

    #[test]
    fn without_enough_neighbours_nothing_is_vouched_for() {
        let mut tracks: Vec<Track3d> = flow().into_iter().take(NEIGHBOURS - 1).collect();
        tracks.push(track(
            Point3::new(0.0, 0.0, 0.5),
            Vector3::x() * 0.1,
            3,
            1e-5,
        ));
        let neighbours = Neighbours::of(&tracks.iter().collect::<Vec<_>>(), 10, FOCAL_PX);
        let n = tracks.len();
        assert!(!neighbours.vouch_for(&tracks[n - 1], n - 1));
        assert!(neighbours
            .carry(&tracks[n - 1], n - 1, 0.4, REACH_PX)
            .is_none());
    }

    #[test]
    fn where_neighbours_move_unlike_each_other_a_new_pair_is_not_carried() {
        // A vortex at 9 rad/s about the grid's centre: neighbours 1 cm apart differ by 9 cm/s,
        // so over 0.2 s their flow misses a particle by tens of pixels.
        let centre = Point3::new(0.02, 0.02, 0.5);
        let mut tracks: Vec<Track3d> = (0..25)
            .map(|i| {
                let start = Point3::new(0.01 * (i % 5) as f64, 0.01 * (i / 5) as f64, 0.5);
                let r = start - centre;
                track(start, Vector3::new(-r.y, r.x, 0.0) * 9.0, 10, 0.0)
            })
            .collect();
        tracks.push(track(
            Point3::new(0.025, 0.02, 0.5),
            Vector3::zeros(),
            1,
            0.0,
        ));
        let neighbours = Neighbours::of(&tracks.iter().collect::<Vec<_>>(), 10, FOCAL_PX);
        let n = tracks.len();
        assert!(neighbours
            .carry(&tracks[n - 1], n - 1, 0.3, REACH_PX)
            .is_none());
    }
}
