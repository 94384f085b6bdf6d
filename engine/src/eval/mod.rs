//! Scoring a `tracks.csv` against `truth.csv`.
//!
//! In every frame each track row is paired with at most one truth particle and vice versa,
//! nearest pairs first, within `radius_m` of the truth position. Only frames that the tracks file
//! covers (its first to last frame) count, so the `M` frames at either end that a centred window
//! cannot reach do not lower the yield.

use std::collections::{BTreeMap, BTreeSet};
use std::fmt;

use nalgebra::{Point3, Vector3};
use serde::Serialize;

use crate::field::FieldSample;
use crate::spatial::cheapest_first;
use crate::synth::TruthRow;
use crate::VelocityVector;

mod budget;
pub use budget::{loss_budget, Fate, Loss, LossBudget, Observation};

/// A measured vector as `tracks.csv` holds it (one row), what scoring reads.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackRow {
    /// The frame the vector describes.
    pub frame: u64,
    /// That frame's time, seconds.
    pub t_s: f64,
    /// The 3D track it belongs to.
    pub track_id: u64,
    /// Position, world frame, metres.
    pub position: Point3<f64>,
    /// Velocity, world frame, metres per second.
    pub velocity: Vector3<f64>,
    /// 1-sigma errors (velocity, position); `None` in files written before vectors carried them.
    pub sigma: Option<(Vector3<f64>, Vector3<f64>)>,
}

impl From<&VelocityVector> for TrackRow {
    fn from(v: &VelocityVector) -> Self {
        Self {
            frame: v.frame_index,
            t_s: v.t_s,
            track_id: v.track_id,
            position: v.position_in_world,
            velocity: v.velocity_in_world,
            sigma: Some((v.velocity_sigma, v.position_sigma)),
        }
    }
}

impl From<&TrackRow> for FieldSample {
    fn from(r: &TrackRow) -> Self {
        Self {
            t_s: r.t_s,
            track_id: r.track_id,
            position: r.position,
            velocity: r.velocity,
        }
    }
}

/// How tracks are scored against truth.
#[derive(Debug, Clone, Copy)]
pub struct EvalOptions {
    /// A track row farther than this from every truth particle is a ghost, metres.
    pub radius_m: f64,
    /// A vector whose error exceeds this fraction of the mean speed is an outlier.
    pub outlier_fraction: f64,
    /// Depth bins the velocity error is broken down into.
    pub depth_bins: usize,
    /// M of the velocity window: a truth particle-frame is *measurable* when the particle exists
    /// from M frames before to M frames after it (a centred estimate is impossible otherwise).
    pub window_frames: u64,
}

impl Default for EvalOptions {
    fn default() -> Self {
        Self {
            radius_m: 0.02,
            outlier_fraction: 0.2,
            depth_bins: 5,
            window_frames: 0,
        }
    }
}

/// Three components of a figure (x, y, z; or u, v, w).
#[derive(Debug, Clone, Copy, Serialize, Default, PartialEq)]
pub struct Xyz {
    /// x (or u).
    pub x: f64,
    /// y (or v).
    pub y: f64,
    /// z (or w).
    pub z: f64,
}

impl From<Vector3<f64>> for Xyz {
    fn from(v: Vector3<f64>) -> Self {
        Self {
            x: v.x,
            y: v.y,
            z: v.z,
        }
    }
}

/// The RMS velocity error of the vectors within a range of world z.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct DepthBin {
    /// The bin's range of world z, metres.
    pub z_min: f64,
    /// See `z_min`.
    pub z_max: f64,
    /// Associated rows in the bin.
    pub rows: usize,
    /// Their RMS velocity error per component, m/s.
    pub rms_velocity_error: Xyz,
}

/// How a tracks file scores against its truth.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Report {
    /// Association radius, metres.
    pub radius_m: f64,
    /// First frame the tracks cover.
    pub first_frame: u64,
    /// Last frame the tracks cover.
    pub last_frame: u64,
    /// Vectors scored.
    pub track_rows: usize,
    /// Distinct tracks among them.
    pub tracks: usize,
    /// Truth particle-frames in the frames covered.
    pub truth_rows: usize,
    /// Vectors associated with a truth particle.
    pub associated_rows: usize,
    /// Associated rows / track rows.
    pub association_rate: f64,
    /// Rows with no truth particle within the radius / track rows.
    pub ghost_rate: f64,
    /// Rows whose only nearby truth particles were claimed by closer rows / track rows.
    pub duplicate_rate: f64,
    /// Associated truth particle-frames / truth particle-frames.
    pub yield_fraction: f64,
    /// M: the window half-width a particle must live through to be measurable.
    pub window_frames: u64,
    /// Truth particle-frames whose particle lives through the whole +-M window.
    pub measurable_rows: usize,
    /// Associated measurable particle-frames / measurable particle-frames.
    pub measurable_yield: f64,
    /// Truth particles associated at least once / truth particles present.
    pub particle_coverage: f64,
    /// Mean |velocity| of the truth over associated rows, m/s.
    pub mean_speed_m_per_s: f64,
    /// RMS position error per component, metres.
    pub rms_position_error_m: Xyz,
    /// RMS velocity error per component, m/s.
    pub rms_velocity_error_m_per_s: Xyz,
    /// RMS velocity error / mean speed, per component.
    pub relative_rms_velocity_error: Xyz,
    /// A vector is an outlier when its error exceeds this fraction of the mean speed.
    pub outlier_fraction_threshold: f64,
    /// Outliers / associated rows.
    pub outlier_rate: f64,
    /// Rows agreeing with their track's most frequent truth particle / associated rows.
    pub track_purity: f64,
    /// RMS velocity error by depth.
    pub by_depth: Vec<DepthBin>,
    /// How well the vectors' stated uncertainties cover their errors; `None` for a tracks file
    /// without them.
    pub uncertainty: Option<Coverage>,
}

/// Per component, the fraction of associated vectors whose error lies within 1 and 2 of their
/// stated sigmas (a Gaussian error with the right sigma gives 68.3 % and 95.4 %).
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Coverage {
    /// Associated vectors that carry sigmas.
    pub rows: usize,
    /// Within 1 sigma, per velocity component.
    pub velocity_within_1_sigma: Xyz,
    /// Within 2 sigma, per velocity component.
    pub velocity_within_2_sigma: Xyz,
    /// Within 1 sigma, per position component.
    pub position_within_1_sigma: Xyz,
    /// Within 2 sigma, per position component.
    pub position_within_2_sigma: Xyz,
    /// Median stated velocity sigma per component: how large the uncertainties are.
    pub median_velocity_sigma_m_per_s: Xyz,
}

fn coverage(associations: &[Association]) -> Option<Coverage> {
    let with_sigma: Vec<(&Association, Vector3<f64>, Vector3<f64>)> = associations
        .iter()
        .filter_map(|a| a.row.sigma.map(|(v, p)| (a, v, p)))
        .collect();
    if with_sigma.is_empty() {
        return None;
    }
    let n = with_sigma.len() as f64;
    type Row<'a> = (&'a Association, Vector3<f64>, Vector3<f64>);
    // A row's error and stated sigma, of the velocity or of the position.
    type Pick = fn(&Row) -> (Vector3<f64>, Vector3<f64>);
    let within = |k: f64, pick: Pick| {
        let mut count = Vector3::zeros();
        for row in &with_sigma {
            let (error, sigma) = pick(row);
            for c in 0..3 {
                if error[c].abs() <= k * sigma[c] {
                    count[c] += 1.0;
                }
            }
        }
        Xyz::from(count / n)
    };
    let velocity: Pick = |(a, sv, _)| (a.row.velocity - a.truth.velocity, *sv);
    let position: Pick = |(a, _, sp)| (a.row.position - a.truth.position, *sp);
    let median_sigma = Vector3::from_fn(|c, _| {
        let mut values: Vec<f64> = with_sigma.iter().map(|(_, sv, _)| sv[c]).collect();
        crate::spatial::median(&mut values)
    });
    Some(Coverage {
        rows: with_sigma.len(),
        velocity_within_1_sigma: within(1.0, velocity),
        velocity_within_2_sigma: within(2.0, velocity),
        position_within_1_sigma: within(1.0, position),
        position_within_2_sigma: within(2.0, position),
        median_velocity_sigma_m_per_s: Xyz::from(median_sigma),
    })
}

/// Why a tracks file cannot be scored.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum EvalError {
    /// The tracks file holds no vectors.
    #[error("no velocity vectors to score (a centred estimate needs a particle seen through 2M+1 frames)")]
    NoTracks,
    /// The truth has no rows in the frames the tracks cover.
    #[error("no truth rows in frames {first}..={last} covered by the tracks")]
    NoTruth {
        /// First frame the tracks cover.
        first: u64,
        /// Last frame the tracks cover.
        last: u64,
    },
}

struct Association {
    row: TrackRow,
    truth: TruthRow,
}

fn rms(sum_sq: Vector3<f64>, n: usize) -> Xyz {
    if n == 0 {
        return Xyz::default();
    }
    Xyz::from(sum_sq.map(|v| (v / n as f64).sqrt()))
}

/// Scores `tracks` against `truth`: association, ghosts and duplicates, yields, errors, purity,
/// errors by depth and how well the stated sigmas cover the errors.
pub fn evaluate(
    truth: &[TruthRow],
    tracks: &[TrackRow],
    options: &EvalOptions,
) -> Result<Report, EvalError> {
    let first = tracks
        .iter()
        .map(|t| t.frame)
        .min()
        .ok_or(EvalError::NoTracks)?;
    let last = tracks
        .iter()
        .map(|t| t.frame)
        .max()
        .ok_or(EvalError::NoTracks)?;
    let truth_by_frame = by_frame(truth.iter().filter(|t| (first..=last).contains(&t.frame)));
    let truth_rows: usize = truth_by_frame.values().map(Vec::len).sum();
    if truth_rows == 0 {
        return Err(EvalError::NoTruth { first, last });
    }
    let measurable = Measurable::new(truth, options.window_frames);
    let measurable_rows = truth_by_frame
        .values()
        .flatten()
        .filter(|t| measurable.contains(t))
        .count();
    let matched = associate(tracks, &truth_by_frame, options.radius_m);
    let n = matched.associations.len();
    let measurable_associated = matched
        .associations
        .iter()
        .filter(|a| measurable.contains(&a.truth))
        .count();
    let errors = Errors::of(&matched.associations, options.outlier_fraction);
    let present: BTreeSet<u64> = truth_by_frame.values().flatten().map(|t| t.pid).collect();
    let covered: BTreeSet<u64> = matched.associations.iter().map(|a| a.truth.pid).collect();
    let track_rows = tracks.len();
    Ok(Report {
        radius_m: options.radius_m,
        first_frame: first,
        last_frame: last,
        track_rows,
        tracks: tracks
            .iter()
            .map(|t| t.track_id)
            .collect::<BTreeSet<_>>()
            .len(),
        truth_rows,
        associated_rows: n,
        association_rate: fraction(n, track_rows),
        ghost_rate: fraction(matched.ghosts, track_rows),
        duplicate_rate: fraction(matched.duplicates, track_rows),
        yield_fraction: fraction(n, truth_rows),
        window_frames: options.window_frames,
        measurable_rows,
        measurable_yield: fraction(measurable_associated, measurable_rows),
        particle_coverage: fraction(covered.len(), present.len()),
        mean_speed_m_per_s: errors.mean_speed,
        rms_position_error_m: errors.rms_position,
        rms_velocity_error_m_per_s: errors.rms_velocity,
        relative_rms_velocity_error: errors.relative(),
        outlier_fraction_threshold: options.outlier_fraction,
        outlier_rate: fraction(errors.outliers, n),
        track_purity: fraction(dominant_rows(&matched.associations), n),
        by_depth: by_depth(&matched.associations, options.depth_bins),
        uncertainty: coverage(&matched.associations),
    })
}

/// Truth rows grouped by frame.
fn by_frame<'a>(truth: impl Iterator<Item = &'a TruthRow>) -> BTreeMap<u64, Vec<TruthRow>> {
    let mut by_frame: BTreeMap<u64, Vec<TruthRow>> = BTreeMap::new();
    for t in truth {
        by_frame.entry(t.frame).or_default().push(*t);
    }
    by_frame
}

fn fraction(a: usize, b: usize) -> f64 {
    if b == 0 {
        0.0
    } else {
        a as f64 / b as f64
    }
}

/// Which truth particle-frames a centred velocity can describe: their particle lives through the
/// whole +-M window around them and, where the truth says which images show it, both images show
/// it in every frame of the window.
pub(crate) struct Measurable {
    lifetimes: BTreeMap<u64, (u64, u64)>,
    /// Per particle whose truth states visibility, the frames both images show it.
    seen_in_both: BTreeMap<u64, BTreeSet<u64>>,
    window_frames: u64,
}

impl Measurable {
    pub(crate) fn new(truth: &[TruthRow], window_frames: u64) -> Self {
        let mut lifetimes: BTreeMap<u64, (u64, u64)> = BTreeMap::new();
        let mut seen_in_both: BTreeMap<u64, BTreeSet<u64>> = BTreeMap::new();
        for t in truth {
            let life = lifetimes.entry(t.pid).or_insert((t.frame, t.frame));
            life.0 = life.0.min(t.frame);
            life.1 = life.1.max(t.frame);
            if let Some(visible) = t.visible {
                let frames = seen_in_both.entry(t.pid).or_default();
                if visible == [true, true] {
                    frames.insert(t.frame);
                }
            }
        }
        Self {
            lifetimes,
            seen_in_both,
            window_frames,
        }
    }

    pub(crate) fn contains(&self, t: &TruthRow) -> bool {
        let m = self.window_frames;
        let lives = self.lifetimes.get(&t.pid).is_some_and(|&(first, last)| {
            t.frame >= first.saturating_add(m) && t.frame.saturating_add(m) <= last
        });
        lives
            && self
                .seen_in_both
                .get(&t.pid)
                .is_none_or(|frames| (t.frame - m..=t.frame + m).all(|f| frames.contains(&f)))
    }
}

/// What the association of track rows with truth particles found.
struct Matched {
    associations: Vec<Association>,
    /// Rows with no truth particle within the radius.
    ghosts: usize,
    /// Rows whose only nearby truth particles were claimed by closer rows.
    duplicates: usize,
}

/// In every frame, each track row paired with at most one truth particle and vice versa,
/// nearest pairs first, within `radius_m`.
fn associate(
    tracks: &[TrackRow],
    truth_by_frame: &BTreeMap<u64, Vec<TruthRow>>,
    radius_m: f64,
) -> Matched {
    let mut rows_by_frame: BTreeMap<u64, Vec<TrackRow>> = BTreeMap::new();
    for r in tracks {
        rows_by_frame.entry(r.frame).or_default().push(*r);
    }
    let mut matched = Matched {
        associations: Vec::new(),
        ghosts: 0,
        duplicates: 0,
    };
    let empty = Vec::new();
    for (frame, rows) in &rows_by_frame {
        let candidates = truth_by_frame.get(frame).unwrap_or(&empty);
        let mut pairs = Vec::new();
        for (ri, r) in rows.iter().enumerate() {
            let mut near = false;
            for (ti, t) in candidates.iter().enumerate() {
                let d = (r.position - t.position).norm();
                if d <= radius_m {
                    pairs.push((d, ri, ti));
                    near = true;
                }
            }
            matched.ghosts += usize::from(!near);
        }
        pairs.sort_by(cheapest_first);
        let mut row_done = vec![false; rows.len()];
        let mut truth_done = vec![false; candidates.len()];
        for (_, ri, ti) in pairs {
            if !row_done[ri] && !truth_done[ti] {
                row_done[ri] = true;
                truth_done[ti] = true;
                matched.associations.push(Association {
                    row: rows[ri],
                    truth: candidates[ti],
                });
            }
        }
        matched.duplicates += rows.len() - row_done.iter().filter(|d| **d).count();
    }
    matched.duplicates -= matched.ghosts;
    matched
}

/// The associated rows' errors against the truth.
struct Errors {
    mean_speed: f64,
    rms_position: Xyz,
    rms_velocity: Xyz,
    /// Rows whose velocity error exceeds the outlier fraction of the mean speed.
    outliers: usize,
}

impl Errors {
    fn of(associations: &[Association], outlier_fraction: f64) -> Self {
        let n = associations.len();
        let mean_speed = if n == 0 {
            0.0
        } else {
            associations
                .iter()
                .map(|a| a.truth.velocity.norm())
                .sum::<f64>()
                / n as f64
        };
        let mut position_sq = Vector3::zeros();
        let mut velocity_sq = Vector3::zeros();
        let mut outliers = 0;
        for a in associations {
            position_sq += (a.row.position - a.truth.position).map(|v| v * v);
            let dv = a.row.velocity - a.truth.velocity;
            velocity_sq += dv.map(|v| v * v);
            outliers += usize::from(dv.norm() > outlier_fraction * mean_speed);
        }
        Self {
            mean_speed,
            rms_position: rms(position_sq, n),
            rms_velocity: rms(velocity_sq, n),
            outliers,
        }
    }

    /// The RMS velocity error relative to the mean speed, per component.
    fn relative(&self) -> Xyz {
        let relative = |v: f64| {
            if self.mean_speed > 0.0 {
                v / self.mean_speed
            } else {
                f64::NAN
            }
        };
        Xyz {
            x: relative(self.rms_velocity.x),
            y: relative(self.rms_velocity.y),
            z: relative(self.rms_velocity.z),
        }
    }
}

/// Rows that agree with their track's most frequent truth particle.
fn dominant_rows(associations: &[Association]) -> usize {
    let mut pid_counts: BTreeMap<u64, BTreeMap<u64, usize>> = BTreeMap::new();
    for a in associations {
        *pid_counts
            .entry(a.row.track_id)
            .or_default()
            .entry(a.truth.pid)
            .or_default() += 1;
    }
    pid_counts
        .values()
        .map(|c| c.values().copied().max().unwrap_or(0))
        .sum()
}

/// The RMS velocity error in `bins` equal bins of the truth's world z.
fn by_depth(associations: &[Association], bins: usize) -> Vec<DepthBin> {
    if associations.is_empty() || bins == 0 {
        return Vec::new();
    }
    let z = || associations.iter().map(|a| a.truth.position.z);
    let (z_min, z_max) = (z().fold(f64::MAX, f64::min), z().fold(f64::MIN, f64::max));
    let width = ((z_max - z_min) / bins as f64).max(1e-12);
    let mut sums = vec![(Vector3::zeros(), 0usize); bins];
    for a in associations {
        let bin = (((a.truth.position.z - z_min) / width) as usize).min(bins - 1);
        sums[bin].0 += (a.row.velocity - a.truth.velocity).map(|v| v * v);
        sums[bin].1 += 1;
    }
    sums.into_iter()
        .enumerate()
        .map(|(i, (sq, count))| DepthBin {
            z_min: z_min + i as f64 * width,
            z_max: z_min + (i + 1) as f64 * width,
            rows: count,
            rms_velocity_error: rms(sq, count),
        })
        .collect()
}

impl fmt::Display for Report {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.write_rates(f)?;
        self.write_errors(f)?;
        if let Some(c) = &self.uncertainty {
            c.write(f)?;
        }
        Ok(())
    }
}

/// A fraction as a percentage with two decimals.
fn pct(v: f64) -> String {
    format!("{:.2} %", 100.0 * v)
}

impl Report {
    /// What was found of what: association, ghosts, duplicates, yields, coverage, purity.
    fn write_rates(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "frames {}..={}, {} vectors on {} tracks, {} truth particle-frames",
            self.first_frame, self.last_frame, self.track_rows, self.tracks, self.truth_rows
        )?;
        writeln!(
            f,
            "association rate   {}  (within {} m of a truth particle, one-to-one)",
            pct(self.association_rate),
            self.radius_m
        )?;
        writeln!(f, "ghost rate         {}", pct(self.ghost_rate))?;
        writeln!(f, "duplicate rate     {}", pct(self.duplicate_rate))?;
        writeln!(
            f,
            "yield              {}  (truth particle-frames with a vector)",
            pct(self.yield_fraction)
        )?;
        writeln!(
            f,
            "measurable yield   {}  (of the {} particle-frames whose particle lives +-{} frames around them)",
            pct(self.measurable_yield),
            self.measurable_rows,
            self.window_frames
        )?;
        writeln!(
            f,
            "particle coverage  {}  (particles with at least one vector)",
            pct(self.particle_coverage)
        )?;
        writeln!(f, "track purity       {}", pct(self.track_purity))
    }

    /// How far off the vectors are: mean speed, RMS errors, outliers, errors by depth.
    fn write_errors(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let xyz = |v: &Xyz, scale: f64, unit: &str| {
            format!(
                "x {:.4} {unit}  y {:.4} {unit}  z {:.4} {unit}",
                v.x * scale,
                v.y * scale,
                v.z * scale
            )
        };
        writeln!(f, "mean speed         {:.4} m/s", self.mean_speed_m_per_s)?;
        writeln!(
            f,
            "RMS position error {}",
            xyz(&self.rms_position_error_m, 1000.0, "mm")
        )?;
        writeln!(
            f,
            "RMS velocity error {}",
            xyz(&self.rms_velocity_error_m_per_s, 1.0, "m/s")
        )?;
        let r = &self.relative_rms_velocity_error;
        writeln!(
            f,
            "  relative to mean speed: u {}  v {}  w {}",
            pct(r.x),
            pct(r.y),
            pct(r.z)
        )?;
        writeln!(
            f,
            "outlier rate       {}  (error > {} x mean speed)",
            pct(self.outlier_rate),
            self.outlier_fraction_threshold
        )?;
        writeln!(f, "RMS velocity error by depth (world z):")?;
        for b in &self.by_depth {
            let e = &b.rms_velocity_error;
            writeln!(
                f,
                "  z {:.3}..{:.3} m  {:>6} rows  u {:.4}  v {:.4}  w {:.4} m/s",
                b.z_min, b.z_max, b.rows, e.x, e.y, e.z
            )?;
        }
        Ok(())
    }
}

impl Coverage {
    fn write(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "stated uncertainty ({} vectors; Gaussian: 68.3 % within 1 sigma, 95.4 % within 2)",
            self.rows
        )?;
        let velocity = ["u", "v", "w"];
        let position = ["x", "y", "z"];
        for (what, [a, b, d], v) in [
            (
                "velocity within 1 sigma",
                velocity,
                &self.velocity_within_1_sigma,
            ),
            (
                "velocity within 2 sigma",
                velocity,
                &self.velocity_within_2_sigma,
            ),
            (
                "position within 1 sigma",
                position,
                &self.position_within_1_sigma,
            ),
            (
                "position within 2 sigma",
                position,
                &self.position_within_2_sigma,
            ),
        ] {
            writeln!(
                f,
                "  {what}  {a} {}  {b} {}  {d} {}",
                pct(v.x),
                pct(v.y),
                pct(v.z)
            )?;
        }
        let s = &self.median_velocity_sigma_m_per_s;
        writeln!(
            f,
            "  median velocity sigma    u {:.5}  v {:.5}  w {:.5} m/s",
            s.x, s.y, s.z
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Point3;

    fn truth(frame: u64, pid: u64, x: f64) -> TruthRow {
        TruthRow {
            frame,
            t_s: frame as f64,
            pid,
            position: Point3::new(x, 0.0, 1.0),
            velocity: Vector3::new(1.0, 0.0, 0.0),
            visible: None,
        }
    }

    fn row(frame: u64, track_id: u64, x: f64, u: f64) -> TrackRow {
        TrackRow {
            frame,
            t_s: frame as f64,
            track_id,
            position: Point3::new(x, 0.0, 1.0),
            velocity: Vector3::new(u, 0.0, 0.0),
            sigma: None,
        }
    }

    #[test]
    fn counts_ghosts_duplicates_yield_and_errors() {
        let truth = vec![
            truth(0, 1, 0.0),
            truth(0, 2, 1.0),
            truth(1, 1, 0.1),
            truth(1, 2, 1.1),
            truth(5, 1, 0.0),
        ];
        let tracks = vec![
            row(0, 7, 0.001, 1.1), // associated, error 0.1
            row(0, 8, 0.003, 1.0), // duplicate of pid 1
            row(1, 7, 0.1, 0.9),   // associated, error -0.1
            row(1, 9, 0.5, 1.0),   // ghost
        ];
        let r = evaluate(&truth, &tracks, &EvalOptions::default()).expect("scored");
        assert_eq!((r.first_frame, r.last_frame, r.truth_rows), (0, 1, 4));
        assert_eq!(r.associated_rows, 2);
        assert!((r.ghost_rate - 0.25).abs() < 1e-12);
        assert!((r.duplicate_rate - 0.25).abs() < 1e-12);
        assert!((r.yield_fraction - 0.5).abs() < 1e-12);
        assert!((r.rms_velocity_error_m_per_s.x - 0.1).abs() < 1e-12);
        assert!((r.relative_rms_velocity_error.x - 0.1).abs() < 1e-12);
        assert!((r.track_purity - 1.0).abs() < 1e-12);
        assert!((r.particle_coverage - 0.5).abs() < 1e-12);
        assert_eq!(r.measurable_rows, 4);
        let windowed = evaluate(
            &truth,
            &tracks,
            &EvalOptions {
                window_frames: 1,
                ..Default::default()
            },
        )
        .expect("scored");
        // pid 1 lives in frames 0, 1 and 5 (lifetime 0..=5): frame 1 is measurable, frame 0 not;
        // pid 2 lives in frames 0..=1 only: never measurable with M = 1.
        assert_eq!(windowed.measurable_rows, 1);
        assert!((windowed.measurable_yield - 1.0).abs() < 1e-12);
        let huge = evaluate(
            &truth,
            &tracks,
            &EvalOptions {
                window_frames: u64::MAX,
                ..Default::default()
            },
        )
        .expect("scored");
        assert_eq!(
            huge.measurable_rows, 0,
            "no particle lives through an endless window"
        );
    }

    #[test]
    fn empty_inputs_are_errors_not_zeros() {
        assert_eq!(
            evaluate(&[], &[], &EvalOptions::default()),
            Err(EvalError::NoTracks)
        );
        assert_eq!(
            evaluate(&[], &[row(3, 1, 0.0, 0.0)], &EvalOptions::default()),
            Err(EvalError::NoTruth { first: 3, last: 3 })
        );
    }
}
