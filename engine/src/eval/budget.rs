//! The loss budget of a run: where each measurable truth particle-frame was lost, stage by stage,
//! and how many of those losses had a touching neighbour or a streak.
//!
//! A truth particle-frame is followed to the point the pipeline made of it: a 3D point (or a
//! partial sample, where a track went on with one image hiding its particle) whose two images
//! lie near the particle's, each point claimed by at most one truth particle, nearest first.
//! Where it has one, its fate is decided by the 3D track that point belongs to over the +-M
//! window and whether a vector describes it. Where it has none, the per-frame chain's stages
//! tell where it was lost: the detection it became in each image (each detection claimed by at
//! most one truth particle, nearest first), whether that detection continued a per-camera
//! track, and the stereo pair it entered. A particle its track found and fitted without a
//! detection of its own is found, not lost.

use std::collections::{BTreeMap, BTreeSet};
use std::fmt;

use nalgebra::Isometry3;
use serde::Serialize;

use super::{associate, EvalOptions, Measurable, TrackRow};
use crate::geometry::{PixelPoint, StereoRig};
use crate::pipeline::{FrameOutput, MatchedPoint};
use crate::spatial::{assign, median, Assignment};
use crate::synth::TruthRow;

/// What the pipeline made of one frame, as far as the loss budget needs it.
#[derive(Debug, Clone, PartialEq)]
pub struct Observation {
    /// The frame's index.
    pub frame: u64,
    /// The headset's pose (`None`: world = rig).
    pub world_from_rig: Option<Isometry3<f64>>,
    /// Left and right detections: centroid, raw pixels, and equivalent diameter.
    pub detections: [Vec<(PixelPoint, f64)>; 2],
    /// Per detection, whether it continues a per-camera track.
    pub continued: [Vec<bool>; 2],
    /// The stereo-matched particles.
    pub points: Vec<MatchedPoint>,
    /// Particles one image hid whose tracks went on with a partial sample.
    pub partial: Vec<MatchedPoint>,
}

impl Observation {
    /// The observation of a frame's output; `world_from_rig` is the pose it was pushed with.
    pub fn of(output: &FrameOutput, world_from_rig: Option<Isometry3<f64>>) -> Self {
        let centroids = |d: &[crate::Detection]| {
            d.iter()
                .map(|d| (d.centroid, d.diameter_px))
                .collect::<Vec<_>>()
        };
        Self {
            frame: output.frame_index,
            world_from_rig,
            detections: [
                centroids(&output.detections_left),
                centroids(&output.detections_right),
            ],
            continued: [
                output.continued_left.clone(),
                output.continued_right.clone(),
            ],
            points: output.points.clone(),
            partial: output.partial_points.clone(),
        }
    }
}

/// Where a measurable truth particle-frame was lost: the first stage it failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Fate {
    /// No detection of its own in the left image.
    UndetectedLeft,
    /// No detection of its own in the right image.
    UndetectedRight,
    /// No point of its own, and detected, but the left detection does not continue a track.
    UnlinkedLeft,
    /// Detected, but the right detection does not continue a track.
    UnlinkedRight,
    /// Linked in both, but no point near its images, and its left detection entered no stereo
    /// pair.
    Unmatched,
    /// No point near its images: its left detection was paired with another particle's right
    /// detection (or a clutter's).
    WrongPartner,
    /// A point near its images, but not of one 3D track through the whole +-M window.
    TrackBroken,
    /// Its 3D track spans the window, but no vector describes it (rejected or not fitted).
    NoVelocity,
    /// A vector describes it.
    Measured,
}

impl Fate {
    const ALL: [Fate; 9] = [
        Fate::UndetectedLeft,
        Fate::UndetectedRight,
        Fate::UnlinkedLeft,
        Fate::UnlinkedRight,
        Fate::Unmatched,
        Fate::WrongPartner,
        Fate::TrackBroken,
        Fate::NoVelocity,
        Fate::Measured,
    ];

    fn label(self) -> &'static str {
        match self {
            Fate::UndetectedLeft => "not detected, left",
            Fate::UndetectedRight => "not detected, right",
            Fate::UnlinkedLeft => "detected, not linked, left",
            Fate::UnlinkedRight => "detected, not linked, right",
            Fate::Unmatched => "linked, not matched",
            Fate::WrongPartner => "matched to the wrong partner",
            Fate::TrackBroken => "3D track broken in the window",
            Fate::NoVelocity => "no velocity (rejected or unfitted)",
            Fate::Measured => "measured",
        }
    }
}

/// One line of the budget.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Loss {
    /// The stage.
    pub fate: Fate,
    /// Measurable particle-frames with this fate.
    pub rows: usize,
    /// Their share of the measurable particle-frames.
    pub share: f64,
    /// The share of them with another particle's image within a particle diameter (either
    /// image).
    pub with_neighbour: f64,
    /// The share of them moving more than a particle diameter per frame in either image: motion
    /// blur stretches their images into streaks.
    pub streaked: f64,
}

/// Where a run lost its measurable truth.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LossBudget {
    /// M: a measurable particle-frame is seen by both images for the 2M + 1 frames around it.
    pub window_frames: u64,
    /// Measurable particle-frames followed.
    pub measurable: usize,
    /// The median equivalent diameter of the run's detections, pixels: the scale of "touching"
    /// and "streaked".
    pub particle_diameter_px: f64,
    /// A truth particle claims a detection whose centroid lies within this of its image, and a
    /// point whose two images do, pixels.
    pub detection_radius_px: f64,
    /// Every fate, in pipeline order.
    pub losses: Vec<Loss>,
}

/// A truth particle's images in one frame, and what became of them.
#[derive(Debug, Clone, Copy)]
struct Followed {
    /// Its images, raw pixels, where both cameras show it.
    px: Option<[PixelPoint; 2]>,
    /// The detections it claimed, per image.
    detection: [Option<usize>; 2],
    /// The 3D track of the point (or partial sample) it claimed.
    track: Option<u64>,
    touching: bool,
}

/// The loss budget of `observations` (one per frame pushed) and the `tracks` they gave, against
/// `truth`, for particle-frames measurable over `options.window_frames`.
pub fn loss_budget(
    truth: &[TruthRow],
    tracks: &[TrackRow],
    observations: &[Observation],
    rig: &StereoRig,
    options: &EvalOptions,
) -> LossBudget {
    let diameter = median_diameter(observations);
    let radius = (0.5 * diameter).max(1.5);
    let by_frame = super::by_frame(truth.iter());
    let mut followed: BTreeMap<(u64, u64), Followed> = BTreeMap::new();
    for o in observations {
        let Some(rows) = by_frame.get(&o.frame) else {
            continue;
        };
        follow_frame(o, rows, rig, radius, diameter, &mut followed);
    }
    let measured: BTreeSet<(u64, u64)> = associate(tracks, &by_frame, options.radius_m)
        .associations
        .iter()
        .map(|a| (a.truth.frame, a.truth.pid))
        .collect();
    let observed: BTreeMap<u64, &Observation> = observations.iter().map(|o| (o.frame, o)).collect();
    let measurable = Measurable::new(truth, options.window_frames);
    let fates = Fates {
        followed: &followed,
        measured: &measured,
        m: options.window_frames,
    };
    let mut tally: BTreeMap<Fate, (usize, usize, usize)> = BTreeMap::new();
    let mut n = 0;
    for t in truth {
        let (Some(f), Some(obs)) = (followed.get(&(t.frame, t.pid)), observed.get(&t.frame)) else {
            continue;
        };
        if f.px.is_none() || !measurable.contains(t) {
            continue;
        }
        n += 1;
        let entry = tally.entry(fates.of(t, f, obs)).or_default();
        entry.0 += 1;
        entry.1 += usize::from(f.touching);
        entry.2 += usize::from(streaked(t, &followed, diameter));
    }
    LossBudget {
        window_frames: options.window_frames,
        measurable: n,
        particle_diameter_px: diameter,
        detection_radius_px: radius,
        losses: Fate::ALL
            .iter()
            .map(|&fate| {
                let (rows, touching, streaks) = tally.get(&fate).copied().unwrap_or_default();
                Loss {
                    fate,
                    rows,
                    share: super::fraction(rows, n),
                    with_neighbour: super::fraction(touching, rows),
                    streaked: super::fraction(streaks, rows),
                }
            })
            .collect(),
    }
}

fn median_diameter(observations: &[Observation]) -> f64 {
    let mut d: Vec<f64> = observations
        .iter()
        .flat_map(|o| o.detections.iter().flatten().map(|&(_, d)| d))
        .collect();
    if d.is_empty() {
        return 3.0;
    }
    median(&mut d)
}

/// Projects one frame's truth into both images, marks touching images and gives each visible
/// particle the detections and the point (or partial sample) it claims (one-to-one, nearest
/// pairs first, within `radius`).
fn follow_frame(
    o: &Observation,
    rows: &[TruthRow],
    rig: &StereoRig,
    radius: f64,
    diameter: f64,
    followed: &mut BTreeMap<(u64, u64), Followed>,
) {
    let images = project(o, rows, rig);
    let detection = claim_detections(o, &images, radius);
    let track = claim_points(o, &images, radius);
    for (i, t) in rows.iter().enumerate() {
        let touching = images[i].is_some_and(|a| {
            images.iter().enumerate().any(|(j, b)| {
                j != i && b.is_some_and(|b| (0..2).any(|c| distance(a[c], b[c]) < diameter))
            })
        });
        followed.insert(
            (t.frame, t.pid),
            Followed {
                px: images[i],
                detection: [detection[0][i], detection[1][i]],
                track: track[i],
                touching,
            },
        );
    }
}

/// Each truth particle's images in the frame seen as `o`, where both cameras show it.
fn project(o: &Observation, rows: &[TruthRow], rig: &StereoRig) -> Vec<Option<[PixelPoint; 2]>> {
    let rig_from_world = o.world_from_rig.map(|p| p.inverse());
    rows.iter()
        .map(|t| {
            let p = rig_from_world.map_or(t.position, |r| r * t.position);
            let (l, r) = rig.project(&p);
            let shown = t.visible.unwrap_or([true, true]);
            match (l, r) {
                (Some(l), Some(r))
                    if shown == [true, true] && rig.contains(l) && rig.contains(r) =>
                {
                    Some([l, r])
                }
                _ => None,
            }
        })
        .collect()
}

/// Per camera, the detection each particle (its `images`) claims within `radius`.
fn claim_detections(
    o: &Observation,
    images: &[Option<[PixelPoint; 2]>],
    radius: f64,
) -> [Vec<Option<usize>>; 2] {
    let mut claimed = [vec![None; images.len()], vec![None; images.len()]];
    for (camera, claims) in claimed.iter_mut().enumerate() {
        let detections: Vec<[PixelPoint; 2]> =
            o.detections[camera].iter().map(|d| [d.0; 2]).collect();
        let near = |a: [PixelPoint; 2], b: [PixelPoint; 2]| {
            let d = distance(a[camera], b[camera]);
            (d <= radius).then_some(d)
        };
        claim_nearest(images, &detections, near, claims);
    }
    claimed
}

/// The track of the point or partial sample each particle (its `images`) claims: the one
/// whose two images both lie within `radius` of its own, nearest first.
fn claim_points(
    o: &Observation,
    images: &[Option<[PixelPoint; 2]>],
    radius: f64,
) -> Vec<Option<u64>> {
    let points: Vec<&MatchedPoint> = o.points.iter().chain(&o.partial).collect();
    let images_of: Vec<[PixelPoint; 2]> = points.iter().map(|p| [p.left_px, p.right_px]).collect();
    let near = |a: [PixelPoint; 2], b: [PixelPoint; 2]| {
        let (l, r) = (distance(a[0], b[0]), distance(a[1], b[1]));
        (l <= radius && r <= radius).then_some(l + r)
    };
    let mut claimed = vec![None; images.len()];
    claim_nearest(images, &images_of, near, &mut claimed);
    claimed
        .into_iter()
        .map(|p| p.map(|p: usize| points[p].track_id))
        .collect()
}

/// Each visible truth particle (its `images`) paired with at most one of `found` (images of
/// detections or points) and vice versa, nearest first by `near` (`None`: too far), into
/// `claims` (none claimed before).
fn claim_nearest(
    images: &[Option<[PixelPoint; 2]>],
    found: &[[PixelPoint; 2]],
    near: impl Fn([PixelPoint; 2], [PixelPoint; 2]) -> Option<f64>,
    claims: &mut [Option<usize>],
) {
    let mut pairs = Vec::new();
    for (ti, px) in images.iter().enumerate() {
        let Some(px) = px else { continue };
        for (di, &d) in found.iter().enumerate() {
            if let Some(dist) = near(*px, d) {
                pairs.push((dist, ti, di));
            }
        }
    }
    for (ti, di) in assign(pairs, images.len(), found.len(), Assignment::OneToOne) {
        claims[ti] = Some(di);
    }
}

fn distance(a: PixelPoint, b: PixelPoint) -> f64 {
    (a.x - b.x).hypot(a.y - b.y)
}

/// Whether the particle's image moves more than `diameter` to the next (or from the previous)
/// frame in either image.
fn streaked(t: &TruthRow, followed: &BTreeMap<(u64, u64), Followed>, diameter: f64) -> bool {
    let Some(here) = followed.get(&(t.frame, t.pid)).and_then(|f| f.px) else {
        return false;
    };
    let step = |frame: u64| followed.get(&(frame, t.pid)).and_then(|f| f.px);
    [step(t.frame + 1), t.frame.checked_sub(1).and_then(step)]
        .into_iter()
        .flatten()
        .any(|other| (0..2).any(|c| distance(here[c], other[c]) > diameter))
}

/// Decides the fate of measurable particle-frames.
struct Fates<'a> {
    followed: &'a BTreeMap<(u64, u64), Followed>,
    measured: &'a BTreeSet<(u64, u64)>,
    m: u64,
}

impl Fates<'_> {
    /// The fate of measurable `t`, followed as `f` in a frame the pipeline saw as `obs`.
    fn of(&self, t: &TruthRow, f: &Followed, obs: &Observation) -> Fate {
        // Detected in both images but not continuing a track there: the particle-frame starts
        // a track (or is left out), whatever point it became.
        if let [Some(dl), Some(dr)] = f.detection {
            if !obs.continued[0].get(dl).copied().unwrap_or(false) {
                return Fate::UnlinkedLeft;
            }
            if !obs.continued[1].get(dr).copied().unwrap_or(false) {
                return Fate::UnlinkedRight;
            }
        }
        let Some(track) = f.track else {
            return Self::lost(f, obs);
        };
        let window = t.frame.saturating_sub(self.m)..=t.frame + self.m;
        let whole = window
            .into_iter()
            .all(|g| self.followed.get(&(g, t.pid)).and_then(|f| f.track) == Some(track));
        if !whole {
            Fate::TrackBroken
        } else if self.measured.contains(&(t.frame, t.pid)) {
            Fate::Measured
        } else {
            Fate::NoVelocity
        }
    }

    /// Where a particle-frame that became no point was lost: not detected in an image, or its
    /// left detection paired with no right one, or with another's.
    fn lost(f: &Followed, obs: &Observation) -> Fate {
        let [Some(dl), Some(_)] = f.detection else {
            return if f.detection[0].is_none() {
                Fate::UndetectedLeft
            } else {
                Fate::UndetectedRight
            };
        };
        let l = obs.detections[0][dl].0;
        if obs.points.iter().any(|p| p.left_px == l) {
            Fate::WrongPartner
        } else {
            Fate::Unmatched
        }
    }
}

fn pct(v: f64) -> String {
    format!("{:.1} %", 100.0 * v)
}

impl fmt::Display for LossBudget {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "loss budget: {} measurable particle-frames (both images show them for the {} frames \
             around), each at the first stage it failed; particle images {:.1} px, a detection \
             or point claimed within {:.1} px of the particle's images",
            self.measurable,
            2 * self.window_frames + 1,
            self.particle_diameter_px,
            self.detection_radius_px
        )?;
        writeln!(
            f,
            "  {:<36} {:>8} {:>8}  {:>14} {:>9}",
            "stage", "rows", "share", "touching", "streaked"
        )?;
        for l in &self.losses {
            writeln!(
                f,
                "  {:<36} {:>8} {:>8}  {:>14} {:>9}",
                l.fate.label(),
                l.rows,
                pct(l.share),
                pct(l.with_neighbour),
                pct(l.streaked)
            )?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::parallel_rig;
    use nalgebra::{Point3, Vector3};

    /// One particle standing still at frames 0..=10, seen and matched on one 3D track in every
    /// frame, with a vector at frame 5; `edit` changes what the pipeline saw.
    fn budget_of(edit: impl Fn(&mut Vec<Observation>), vector: bool) -> LossBudget {
        let rig = parallel_rig(640, 480, 500.0, 0.1);
        let position = Point3::new(0.05, 0.02, 1.0);
        let (l, r) = rig.project(&position);
        let (l, r) = (l.expect("left"), r.expect("right"));
        let truth: Vec<TruthRow> = (0..=10)
            .map(|frame| TruthRow {
                frame,
                t_s: frame as f64 * 0.1,
                pid: 7,
                position,
                velocity: Vector3::zeros(),
                visible: Some([true, true]),
            })
            .collect();
        let mut observations: Vec<Observation> = (0..=10)
            .map(|frame| Observation {
                frame,
                world_from_rig: None,
                detections: [vec![(l, 3.0)], vec![(r, 3.0)]],
                continued: [vec![frame > 0], vec![frame > 0]],
                points: vec![MatchedPoint {
                    track_id: 1,
                    point_in_world: position,
                    left_px: l,
                    right_px: r,
                    depth_m: 1.0,
                }],
                partial: Vec::new(),
            })
            .collect();
        edit(&mut observations);
        let tracks: Vec<TrackRow> = vector
            .then(|| TrackRow {
                frame: 5,
                t_s: 0.5,
                track_id: 1,
                position,
                velocity: Vector3::zeros(),
                sigma: None,
            })
            .into_iter()
            .collect();
        let options = EvalOptions {
            window_frames: 5,
            ..Default::default()
        };
        loss_budget(&truth, &tracks, &observations, &rig, &options)
    }

    fn only_fate(b: &LossBudget) -> Fate {
        assert_eq!(b.measurable, 1, "{b}");
        let hit: Vec<&Loss> = b.losses.iter().filter(|l| l.rows > 0).collect();
        assert_eq!(hit.len(), 1, "{b}");
        hit[0].fate
    }

    #[test]
    fn each_particle_frame_goes_to_the_first_stage_it_failed() {
        assert_eq!(only_fate(&budget_of(|_| {}, true)), Fate::Measured);
        assert_eq!(only_fate(&budget_of(|_| {}, false)), Fate::NoVelocity);
        let moved = |o: &mut Vec<Observation>| {
            o[5].detections[1][0].0.x += 10.0;
            o[5].points[0].right_px.x += 10.0;
        };
        assert_eq!(only_fate(&budget_of(moved, true)), Fate::UndetectedRight);
        let unlinked = |o: &mut Vec<Observation>| o[5].continued[0][0] = false;
        assert_eq!(only_fate(&budget_of(unlinked, true)), Fate::UnlinkedLeft);
        let unmatched = |o: &mut Vec<Observation>| o[5].points.clear();
        assert_eq!(only_fate(&budget_of(unmatched, true)), Fate::Unmatched);
        let wrong = |o: &mut Vec<Observation>| o[5].points[0].right_px.x -= 30.0;
        assert_eq!(only_fate(&budget_of(wrong, true)), Fate::WrongPartner);
        let broken = |o: &mut Vec<Observation>| o[8].points[0].track_id = 2;
        assert_eq!(only_fate(&budget_of(broken, true)), Fate::TrackBroken);
    }

    #[test]
    fn a_particle_its_track_found_without_a_detection_or_partly_is_not_lost() {
        // Fitted in the right image where no detection of its own was: its point is there.
        let fitted = |o: &mut Vec<Observation>| o[5].detections[1].clear();
        assert_eq!(only_fate(&budget_of(fitted, true)), Fate::Measured);
        // Hidden in one image in a frame of the window: the track went on with a partial
        // sample, and is not broken.
        let partial = |o: &mut Vec<Observation>| {
            let p = o[8].points.remove(0);
            o[8].partial.push(p);
        };
        assert_eq!(only_fate(&budget_of(partial, true)), Fate::Measured);
        // A point of another track near the particle's images in one frame breaks it.
        let other = |o: &mut Vec<Observation>| {
            let mut p = o[8].points.remove(0);
            p.track_id = 2;
            o[8].partial.push(p);
        };
        assert_eq!(only_fate(&budget_of(other, true)), Fate::TrackBroken);
    }

    #[test]
    fn particles_hidden_from_an_image_are_not_measurable() {
        let b = budget_of(|_| {}, true);
        assert_eq!(b.measurable, 1);
        let rig = parallel_rig(640, 480, 500.0, 0.1);
        let mut truth: Vec<TruthRow> = (0..=10)
            .map(|frame| TruthRow {
                frame,
                t_s: frame as f64 * 0.1,
                pid: 7,
                position: Point3::new(0.05, 0.02, 1.0),
                velocity: Vector3::zeros(),
                visible: Some([true, true]),
            })
            .collect();
        truth[9].visible = Some([true, false]);
        let observations: Vec<Observation> = (0..=10)
            .map(|frame| Observation {
                frame,
                world_from_rig: None,
                detections: [Vec::new(), Vec::new()],
                continued: [Vec::new(), Vec::new()],
                points: Vec::new(),
                partial: Vec::new(),
            })
            .collect();
        let options = EvalOptions {
            window_frames: 5,
            ..Default::default()
        };
        let b = loss_budget(&truth, &[], &observations, &rig, &options);
        assert_eq!(b.measurable, 0, "{b}");
    }
}
