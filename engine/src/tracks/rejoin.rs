//! Broken 3D tracks rejoined ([`TrackConfig::rejoin_frames`]): a new stereo pair that lies where
//! an orphaned 3D track's recent path predicts it continues that track; a lone sample joins
//! through the one before it on a constant-velocity path; and a left track that changed partner
//! keeps its track where the depth agrees. A track too young for a path of its own is carried
//! by the flow its neighbours took into this frame ([`super::flow`]).

use nalgebra::Point3;

use super::flow::Flow;
use super::turn::Turns;
use super::{Limits, Orphan, Pair, Sample, Track3d, TrackConfig, PATH_SAMPLES};
use crate::geometry::{RectPoint, Rectification};
use crate::spatial::{cheapest_first, PointGrid, GRID_CELL_PX};
use crate::velocity::fit::{fit_line, fit_quadratic};

/// A rejoin: the orphan a new pair continues and, for a one-sample orphan, the one-sample orphan
/// of the frame before that completes the path.
pub(super) type Join = (usize, Option<usize>);

/// Where an orphan (or a pair of lone ones) predicts its particle this frame.
struct Prediction {
    orphan: usize,
    before: Option<usize>,
    world: Point3<f64>,
    /// In the left image, rectified.
    image: RectPoint,
    /// How far off the pair may lie: across the line of sight (rectified pixels) and along it
    /// (depth-noise sigmas).
    tolerance: [f64; 2],
}

/// The geometry and tolerances rejoining is judged by.
struct Judge<'a> {
    config: &'a TrackConfig,
    limits: &'a Limits,
    rect: &'a Rectification,
    /// How far per pixel of its step a path turns in a frame, learnt ([`super::turn`]).
    turn_per_frame: f64,
}

/// For each new pair (`births`), the orphan it continues, if any: the continuation whose
/// prediction the pair meets best, within the rejoin tolerances (one-to-one, closest first).
/// A young orphan (one or two samples, the last in the frame before) is carried by the `flow`
/// around it instead of its own path, where the flow is known there.
pub(super) fn rejoin(
    (config, limits, turns): (&TrackConfig, &Limits, &Turns),
    rect: &Rectification,
    flow: Option<&Flow>,
    births: &[Pair],
    orphans: &[(Orphan, Track3d)],
    t_s: f64,
) -> Vec<Option<Join>> {
    if config.rejoin_frames == 0 || births.is_empty() || orphans.is_empty() {
        return vec![None; births.len()];
    }
    let judge = Judge {
        config,
        limits,
        rect,
        turn_per_frame: turns.per_frame(),
    };
    let seq = births[0].sample.seq;
    let mut predictions = flow.map_or_else(Vec::new, |f| judge.carried(f, orphans, (seq, t_s)));
    let mut carried = vec![false; orphans.len()];
    for p in &predictions {
        carried[p.orphan] = true;
    }
    predictions.extend(judge.predictions(orphans, &carried, t_s));
    let mut candidates = judge.predicted_candidates(births, &predictions);
    judge.replaced_candidates(births, orphans, &carried, &mut predictions, &mut candidates);
    assign(candidates, &predictions, births.len(), orphans.len())
}

/// The track a join continues, taken out of `orphans`, with the earlier lone sample it joined
/// through leading it (the three are one particle).
pub(super) fn take_joined(
    orphans: &mut [Option<(Orphan, Track3d)>],
    (o, before): Join,
) -> Option<Track3d> {
    let (_, mut track) = orphans[o].take()?;
    if let Some((_, earlier)) = before.and_then(|a| orphans[a].take()) {
        for s in earlier.samples.into_iter().rev() {
            track.samples.push_front(s);
        }
    }
    Some(track)
}

impl Judge<'_> {
    /// What each orphan the flow did not carry (`carried`) predicts: its path where it has
    /// one, else (a lone sample) the path it makes with each lone sample of the frame before it.
    fn predictions(
        &self,
        orphans: &[(Orphan, Track3d)],
        carried: &[bool],
        t_s: f64,
    ) -> Vec<Prediction> {
        let lone_grid = PointGrid::new(
            orphans
                .iter()
                .enumerate()
                .filter_map(|(o, (_, t))| match t.samples.as_slices().0 {
                    [only] if t.samples.len() == 1 => Some((only.left_rect, o)),
                    _ => None,
                }),
            self.limits.max_displacement_px.max(GRID_CELL_PX),
        );
        let mut predictions = Vec::new();
        for (o, (_, track)) in orphans.iter().enumerate() {
            if carried[o] {
                continue;
            }
            if let Some((world, image)) = predicted_position(track, t_s) {
                let last = track.samples.back().map(|s| s.left_rect);
                let step_px = last.map_or(0.0, |l| (image.x - l.x).hypot(image.y - l.y));
                predictions.push(Prediction {
                    orphan: o,
                    before: None,
                    world,
                    image,
                    tolerance: self.path_tolerance(step_px),
                });
            } else if let Some(b) = track.samples.back() {
                self.lone_paths(o, b, orphans, &lone_grid, t_s, &mut predictions);
            }
        }
        predictions
    }

    /// Where the `flow` carries each young orphan (seen fewer than [`PATH_SAMPLES`] times, the
    /// last time in the frame before `seq`): too young for a path of its own.
    fn carried(
        &self,
        flow: &Flow,
        orphans: &[(Orphan, Track3d)],
        (seq, t_s): (u64, f64),
    ) -> Vec<Prediction> {
        orphans
            .iter()
            .enumerate()
            .filter_map(|(o, (_, track))| {
                let last = track.samples.back()?;
                if track.samples.len() >= PATH_SAMPLES || last.seq + 1 != seq {
                    return None;
                }
                let carried = flow.carry(last, t_s)?;
                Some(Prediction {
                    orphan: o,
                    before: None,
                    world: carried.world,
                    image: carried.image,
                    tolerance: [carried.across_px, carried.along_sigmas],
                })
            })
            .collect()
    }

    /// Two lone samples in consecutive frames (`b`, of orphan `o`, and one before it) predict a
    /// third at constant velocity.
    fn lone_paths(
        &self,
        o: usize,
        b: &Sample,
        orphans: &[(Orphan, Track3d)],
        lone_grid: &PointGrid,
        t_s: f64,
        predictions: &mut Vec<Prediction>,
    ) {
        let reach = self.limits.max_displacement_px;
        for (a_rect, a) in lone_grid.near(b.left_rect.x, b.left_rect.y, reach) {
            let Some(sample_a) = orphans[*a].1.samples.back() else {
                continue;
            };
            if sample_a.seq + 1 != b.seq
                || (b.left_rect.x - a_rect.x).hypot(b.left_rect.y - a_rect.y) > reach
            {
                continue;
            }
            let ahead = (t_s - b.t_s) / (b.t_s - sample_a.t_s);
            let world = b.point_in_world + (b.point_in_world - sample_a.point_in_world) * ahead;
            let image = RectPoint {
                x: b.left_rect.x + (b.left_rect.x - a_rect.x) * ahead,
                y: b.left_rect.y + (b.left_rect.y - a_rect.y) * ahead,
            };
            let step_px = (b.left_rect.x - a_rect.x).hypot(b.left_rect.y - a_rect.y);
            predictions.push(Prediction {
                orphan: o,
                before: Some(*a),
                world,
                image,
                tolerance: self.path_tolerance(step_px),
            });
        }
    }

    /// The tolerances of a prediction from a track's own path, whose per-frame image step was
    /// `step_px`: it misses by about the change in velocity over a frame, which grows with the
    /// step (a vortex turns its particles by a fixed angle per frame).
    fn path_tolerance(&self, step_px: f64) -> [f64; 2] {
        [
            self.config
                .rejoin_tolerance_px
                .max(self.turn_per_frame * step_px),
            self.config.rejoin_tolerance_sigmas,
        ]
    }

    /// `sigmas` of depth noise along the line of sight at `depth_m`, metres.
    fn along_m(&self, sigmas: f64, depth_m: f64) -> f64 {
        sigmas
            * self
                .rect
                .depth_sigma_m(depth_m, self.limits.disparity_sigma_px)
    }

    /// The births within each prediction's tolerances, as `(cost, birth, prediction)`.
    fn predicted_candidates(
        &self,
        births: &[Pair],
        predictions: &[Prediction],
    ) -> Vec<(f64, usize, usize)> {
        let focal_px = self.rect.focal_px;
        let birth_grid = PointGrid::new(
            births
                .iter()
                .enumerate()
                .map(|(i, b)| (b.sample.left_rect, i)),
            GRID_CELL_PX,
        );
        let cost = |sample: &Sample, predicted: &Point3<f64>, across_px: f64, along_m: f64| {
            let (along, across_sq) =
                sample.along_and_across_sq(&(sample.point_in_world - predicted));
            (across_sq.sqrt() * focal_px / (sample.depth_m * across_px)).powi(2)
                + (along / along_m).powi(2)
        };
        let mut candidates = Vec::new();
        for (h, p) in predictions.iter().enumerate() {
            let [across_px, along_sigmas] = p.tolerance;
            for (_, b) in birth_grid.near(p.image.x, p.image.y, 2.0 * across_px) {
                let sample = &births[*b].sample;
                let along_m = self.along_m(along_sigmas, sample.depth_m);
                let c = cost(sample, &p.world, across_px, along_m);
                if c <= 1.0 {
                    candidates.push((c, *b, h));
                }
            }
        }
        candidates
    }

    /// A one-sample track has no path to predict from; but where its left track went on (only
    /// the partner changed), the left camera vouches for the continuity across the line of
    /// sight, and the depth may have changed by no more than the particle moved across it.
    fn replaced_candidates(
        &self,
        births: &[Pair],
        orphans: &[(Orphan, Track3d)],
        carried: &[bool],
        predictions: &mut Vec<Prediction>,
        candidates: &mut Vec<(f64, usize, usize)>,
    ) {
        for (o, (kind, track)) in orphans.iter().enumerate() {
            if carried[o] {
                continue;
            }
            let (Orphan::Replaced(left_track), [last]) = (kind, track.samples.as_slices().0) else {
                continue;
            };
            let Some(b) = births
                .iter()
                .position(|birth| birth.left_track == *left_track)
            else {
                continue;
            };
            let sample = &births[b].sample;
            let moved_m = (sample.left_rect.x - last.left_rect.x)
                .hypot(sample.left_rect.y - last.left_rect.y)
                * sample.depth_m
                / self.rect.focal_px;
            let (along, _) =
                sample.along_and_across_sq(&(sample.point_in_world - last.point_in_world));
            let along_m = self.along_m(self.config.rejoin_tolerance_sigmas, sample.depth_m);
            let c = (along.abs() / (along_m + moved_m)).powi(2);
            if c <= 1.0 {
                predictions.push(Prediction {
                    orphan: o,
                    before: None,
                    world: last.point_in_world,
                    image: last.left_rect,
                    tolerance: self.path_tolerance(0.0),
                });
                candidates.push((c, b, predictions.len() - 1));
            }
        }
    }
}

/// One-to-one, cheapest first: each birth and each orphan (and the lone sample a join goes
/// through) is used once.
fn assign(
    mut candidates: Vec<(f64, usize, usize)>,
    predictions: &[Prediction],
    births: usize,
    orphans: usize,
) -> Vec<Option<Join>> {
    candidates.sort_by(cheapest_first);
    let mut rejoined = vec![None; births];
    let mut taken = vec![false; orphans];
    for (_, b, h) in candidates {
        let (o, before) = (predictions[h].orphan, predictions[h].before);
        if rejoined[b].is_some() || taken[o] || before.is_some_and(|a| taken[a]) {
            continue;
        }
        rejoined[b] = Some((o, before));
        taken[o] = true;
        if let Some(a) = before {
            taken[a] = true;
        }
    }
    rejoined
}

/// Where a track's last few samples put it at `t_s`, in the world and in the left image: a
/// quadratic through up to five of them, a line through two; `None` for a single sample.
fn predicted_position(track: &Track3d, t_s: f64) -> Option<(Point3<f64>, RectPoint)> {
    let recent = track.samples.iter().rev().take(5);
    let world: Vec<(f64, Point3<f64>)> =
        recent.clone().map(|s| (s.t_s, s.point_in_world)).collect();
    let image: Vec<(f64, Point3<f64>)> = recent
        .map(|s| (s.t_s, Point3::new(s.left_rect.x, s.left_rect.y, 0.0)))
        .collect();
    let fit = |points: &[(f64, Point3<f64>)]| match points.len() {
        0 | 1 => None,
        2 => fit_line(points, t_s),
        _ => fit_quadratic(points, t_s),
    };
    let world = fit(&world)?.position;
    let image = fit(&image)?.position;
    Some((
        world,
        RectPoint {
            x: image.x,
            y: image.y,
        },
    ))
}
