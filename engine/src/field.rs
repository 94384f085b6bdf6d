//! The Eulerian field: velocity vectors binned on a grid anchored in the world frame, so a
//! session's samples accumulate where they were measured however the head moved.
//!
//! Per cell: the sample count, the mean velocity, the standard deviation of each component (the
//! flow's fluctuation plus measurement noise) and the standard error of the mean. Consecutive
//! vectors of one track are far from independent (they share most of their fit window), so the
//! standard error counts tracks, not samples: `std / sqrt(tracks)`.

use std::collections::{BTreeMap, VecDeque};

use nalgebra::{Point3, Vector3};

use crate::VelocityVector;

/// One velocity sample as the grid keeps it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FieldSample {
    /// Time of the vector, seconds.
    pub t_s: f64,
    /// The 3D track it belongs to.
    pub track_id: u64,
    /// Position, world frame, metres.
    pub position: Point3<f64>,
    /// Velocity, world frame, m/s.
    pub velocity: Vector3<f64>,
}

impl From<&VelocityVector> for FieldSample {
    fn from(v: &VelocityVector) -> Self {
        Self {
            t_s: v.t_s,
            track_id: v.track_id,
            position: v.position_in_world,
            velocity: v.velocity_in_world,
        }
    }
}

/// Why a field cannot be set up.
#[derive(Debug, Clone, thiserror::Error, PartialEq)]
pub enum FieldError {
    /// The cell size is not a positive number of metres.
    #[error("field cell size {0} m: must be a positive finite length")]
    Cell(f64),
    /// The averaging window is not a positive number of seconds.
    #[error("field time window {0} s: must be positive and finite")]
    Window(f64),
}

/// Integer cell coordinates: cell `i` spans `[i, i + 1) * cell_m` along each axis.
pub type CellIndex = [i64; 3];

/// A cell's statistics.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CellSummary {
    /// The cell's index on the grid.
    pub index: CellIndex,
    /// The cell's centre, world frame, metres.
    pub centre: Point3<f64>,
    /// Vectors binned into it.
    pub samples: usize,
    /// Distinct tracks among the samples.
    pub tracks: usize,
    /// Their mean velocity, m/s.
    pub mean: Vector3<f64>,
    /// Sample standard deviation per component (0 for a single sample).
    pub std: Vector3<f64>,
    /// Standard error of the mean per component: `std / sqrt(tracks)`.
    pub sem: Vector3<f64>,
}

/// The names of a cell's numbers, in the order of [`CellSummary::values`]: `field.csv`'s header
/// and the rows of a `field` message.
pub const FIELD_COLUMNS: [&str; 14] = [
    "x", "y", "z", "n", "u", "v", "w", "std_u", "std_v", "std_w", "sem_u", "sem_v", "sem_w",
    "tracks",
];

impl CellSummary {
    /// The cell's numbers in [`FIELD_COLUMNS`] order.
    pub fn values(&self) -> [f64; 14] {
        let (p, m, s, e) = (self.centre, self.mean, self.std, self.sem);
        [
            p.x,
            p.y,
            p.z,
            self.samples as f64,
            m.x,
            m.y,
            m.z,
            s.x,
            s.y,
            s.z,
            e.x,
            e.y,
            e.z,
            self.tracks as f64,
        ]
    }
}

/// Sums of one cell's samples, kept about a reference velocity (the cell's first sample) so the
/// variance does not lose its digits to a large mean.
#[derive(Debug, Clone)]
struct Cell {
    reference: Vector3<f64>,
    count: usize,
    sum: Vector3<f64>,
    sum_sq: Vector3<f64>,
    /// Samples per track.
    tracks: BTreeMap<u64, usize>,
}

impl Cell {
    fn new(reference: Vector3<f64>) -> Self {
        Self {
            reference,
            count: 0,
            sum: Vector3::zeros(),
            sum_sq: Vector3::zeros(),
            tracks: BTreeMap::new(),
        }
    }

    fn add(&mut self, s: &FieldSample, sign: f64) {
        let d = s.velocity - self.reference;
        self.sum += d * sign;
        self.sum_sq += d.component_mul(&d) * sign;
        if sign > 0.0 {
            self.count += 1;
            *self.tracks.entry(s.track_id).or_default() += 1;
        } else {
            self.count -= 1;
            if let Some(n) = self.tracks.get_mut(&s.track_id) {
                *n -= 1;
                if *n == 0 {
                    self.tracks.remove(&s.track_id);
                }
            }
        }
    }

    fn summary(&self, index: CellIndex, cell_m: f64) -> CellSummary {
        let n = self.count as f64;
        let mean_offset = self.sum / n;
        let std = if self.count > 1 {
            ((self.sum_sq - self.sum.component_mul(&mean_offset)) / (n - 1.0))
                .map(|v| v.max(0.0).sqrt())
        } else {
            Vector3::zeros()
        };
        let tracks = self.tracks.len().max(1);
        CellSummary {
            index,
            centre: Point3::from(Vector3::from_fn(|c, _| (index[c] as f64 + 0.5) * cell_m)),
            samples: self.count,
            tracks: self.tracks.len(),
            mean: self.reference + mean_offset,
            std,
            sem: std / (tracks as f64).sqrt(),
        }
    }
}

/// The accumulating grid.
#[derive(Debug, Clone)]
pub struct FieldGrid {
    cell_m: f64,
    window_s: Option<f64>,
    cells: BTreeMap<CellIndex, Cell>,
    /// With a time window: every sample in it, oldest first, to forget them in order.
    kept: VecDeque<(CellIndex, FieldSample)>,
    /// Samples added since the last reset (forgotten ones included).
    added: u64,
}

impl FieldGrid {
    /// A grid of cubic cells of side `cell_m`; with `window_s`, samples older than that (by
    /// their own time, against the newest sample's) are forgotten.
    pub fn new(cell_m: f64, window_s: Option<f64>) -> Result<Self, FieldError> {
        if !(cell_m.is_finite() && cell_m > 0.0) {
            return Err(FieldError::Cell(cell_m));
        }
        if let Some(w) = window_s {
            if !(w.is_finite() && w > 0.0) {
                return Err(FieldError::Window(w));
            }
        }
        Ok(Self {
            cell_m,
            window_s,
            cells: BTreeMap::new(),
            kept: VecDeque::new(),
            added: 0,
        })
    }

    /// Side of a cell, metres.
    pub fn cell_m(&self) -> f64 {
        self.cell_m
    }

    /// How far back samples count, seconds (`None`: all of them).
    pub fn window_s(&self) -> Option<f64> {
        self.window_s
    }

    /// Samples added since the grid began or was last reset.
    pub fn samples_added(&self) -> u64 {
        self.added
    }

    /// The cell holding `p`, if it is on the grid.
    pub fn index_of(&self, p: &Point3<f64>) -> Option<CellIndex> {
        let index = [0, 1, 2].map(|c| (p[c] / self.cell_m).floor());
        // Beyond i64's range (or not finite) is no place in a room.
        index
            .iter()
            .all(|i| i.is_finite() && i.abs() < 1e15)
            .then(|| index.map(|i| i as i64))
    }

    /// Adds a sample; one with a non-finite position or velocity is ignored.
    pub fn add(&mut self, sample: FieldSample) {
        if !sample.velocity.iter().all(|v| v.is_finite()) {
            return;
        }
        let Some(index) = self.index_of(&sample.position) else {
            return;
        };
        self.cells
            .entry(index)
            .or_insert_with(|| Cell::new(sample.velocity))
            .add(&sample, 1.0);
        self.added += 1;
        if let Some(window) = self.window_s {
            self.kept.push_back((index, sample));
            let oldest_kept = sample.t_s - window;
            while let Some((index, old)) = self.kept.front().copied() {
                if old.t_s >= oldest_kept {
                    break;
                }
                self.kept.pop_front();
                self.forget(index, &old);
            }
        }
    }

    /// Bins `vectors`.
    pub fn add_vectors<'a>(&mut self, vectors: impl IntoIterator<Item = &'a VelocityVector>) {
        for v in vectors {
            self.add(FieldSample::from(v));
        }
    }

    fn forget(&mut self, index: CellIndex, sample: &FieldSample) {
        if let Some(cell) = self.cells.get_mut(&index) {
            cell.add(sample, -1.0);
            if cell.count == 0 {
                self.cells.remove(&index);
            }
        }
    }

    /// Forgets every sample.
    pub fn reset(&mut self) {
        self.cells.clear();
        self.kept.clear();
        self.added = 0;
    }

    /// Cells with at least one sample, in index order (by x index, then y, then z).
    pub fn cells(&self) -> impl Iterator<Item = CellSummary> + '_ {
        self.cells
            .iter()
            .map(|(index, cell)| cell.summary(*index, self.cell_m))
    }

    /// Cells with samples.
    pub fn len(&self) -> usize {
        self.cells.len()
    }

    /// Whether no cell has samples.
    pub fn is_empty(&self) -> bool {
        self.cells.is_empty()
    }
}

/// A field over a stream of vectors whose measurement volume is not known in advance (a live
/// session): with no cell size given, the first `SIZING_VECTORS` vectors wait, then size the
/// grid (`default_cell_m`) and go into it.
#[derive(Debug, Clone, Default)]
pub struct StreamField {
    window_s: Option<f64>,
    grid: Option<FieldGrid>,
    pending: Vec<FieldSample>,
}

impl StreamField {
    /// Vectors that size the default grid: enough to see the measurement volume.
    pub const SIZING_VECTORS: usize = 500;

    /// A field of cells `cell_m` wide (learnt from the first vectors when `None`), averaging over `window_s`.
    pub fn new(cell_m: Option<f64>, window_s: Option<f64>) -> Result<Self, FieldError> {
        let grid = cell_m.map(|c| FieldGrid::new(c, window_s)).transpose()?;
        if grid.is_none() {
            // Checked now, not when the grid is sized.
            FieldGrid::new(1.0, window_s)?;
        }
        Ok(Self {
            window_s,
            grid,
            pending: Vec::new(),
        })
    }

    /// Bins a frame's vectors (after the cell size is learnt).
    pub fn add_vectors(&mut self, vectors: &[VelocityVector]) {
        if let Some(grid) = &mut self.grid {
            grid.add_vectors(vectors);
            return;
        }
        self.pending.extend(vectors.iter().map(FieldSample::from));
        if self.pending.len() < Self::SIZING_VECTORS {
            return;
        }
        let positions: Vec<Point3<f64>> = self.pending.iter().map(|s| s.position).collect();
        let Some(mut grid) =
            default_cell_m(&positions).and_then(|c| FieldGrid::new(c, self.window_s).ok())
        else {
            return;
        };
        for s in self.pending.drain(..) {
            grid.add(s);
        }
        self.grid = Some(grid);
    }

    /// Forgets every sample (the cell size, once known, stays).
    pub fn reset(&mut self) {
        if let Some(grid) = &mut self.grid {
            grid.reset();
        }
        self.pending.clear();
    }

    /// The grid, once sized.
    pub fn grid(&self) -> Option<&FieldGrid> {
        self.grid.as_ref()
    }
}

/// A cell size for vectors at `positions`: about a tenth of the measurement volume's largest
/// extent (its 5th to 95th percentile, so a few strays do not stretch it), rounded to 1, 2 or 5
/// times a power of ten. `None` without positions to judge from.
pub fn default_cell_m(positions: &[Point3<f64>]) -> Option<f64> {
    if positions.len() < 2 {
        return None;
    }
    let extent = (0..3)
        .map(|c| {
            let mut values: Vec<f64> = positions
                .iter()
                .map(|p| p[c])
                .filter(|v| v.is_finite())
                .collect();
            values.sort_by(f64::total_cmp);
            if values.len() < 2 {
                return 0.0;
            }
            let at = |q: f64| values[((values.len() - 1) as f64 * q).round() as usize];
            at(0.95) - at(0.05)
        })
        .fold(0.0, f64::max);
    /// Cells across the volume's largest extent, about.
    const CELLS_ACROSS: f64 = 10.0;
    (extent > 0.0).then(|| nice_length(extent / CELLS_ACROSS))
}

/// `length` rounded to the nearest of 1, 2 or 5 times a power of ten (on a log scale).
fn nice_length(length: f64) -> f64 {
    let decade = 10f64.powf(length.log10().floor());
    let mantissa = length / decade;
    let nice = [1.0, 2.0, 5.0, 10.0]
        .into_iter()
        .min_by(|a: &f64, b: &f64| {
            (mantissa.ln() - a.ln())
                .abs()
                .total_cmp(&(mantissa.ln() - b.ln()).abs())
        })
        .unwrap_or(1.0);
    nice * decade
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(t_s: f64, track_id: u64, x: f64, u: f64) -> FieldSample {
        FieldSample {
            t_s,
            track_id,
            position: Point3::new(x, 0.01, 0.01),
            velocity: Vector3::new(u, 0.0, 0.0),
        }
    }

    #[test]
    fn cells_hold_count_mean_std_and_a_standard_error_by_track() {
        let mut grid = FieldGrid::new(0.1, None).expect("grid");
        for (i, u) in [1.0, 2.0, 3.0, 4.0].into_iter().enumerate() {
            grid.add(sample(i as f64, (i / 2) as u64, 0.05, u));
        }
        grid.add(sample(0.0, 9, 0.15, 7.0));
        let cells: Vec<CellSummary> = grid.cells().collect();
        assert_eq!(cells.len(), 2);
        let c = &cells[0];
        assert_eq!(c.index, [0, 0, 0]);
        assert!((c.centre - Point3::new(0.05, 0.05, 0.05)).norm() < 1e-12);
        assert_eq!((c.samples, c.tracks), (4, 2));
        assert!((c.mean.x - 2.5).abs() < 1e-12);
        // Sample standard deviation of 1, 2, 3, 4.
        let std = (5.0f64 / 3.0).sqrt();
        assert!((c.std.x - std).abs() < 1e-12);
        assert!((c.sem.x - std / 2f64.sqrt()).abs() < 1e-12);
        assert_eq!(c.std.y, 0.0);
        assert_eq!((cells[1].samples, cells[1].std.x), (1, 0.0));
    }

    #[test]
    fn negative_positions_fall_in_their_own_cells() {
        let grid = FieldGrid::new(0.1, None).expect("grid");
        assert_eq!(
            grid.index_of(&Point3::new(-0.05, 0.0, 0.25)),
            Some([-1, 0, 2])
        );
        assert_eq!(grid.index_of(&Point3::new(f64::NAN, 0.0, 0.0)), None);
    }

    #[test]
    fn a_time_window_forgets_old_samples_and_a_reset_everything() {
        let mut grid = FieldGrid::new(0.1, Some(1.0)).expect("grid");
        grid.add(sample(0.0, 1, 0.05, 10.0));
        grid.add(sample(0.5, 2, 0.05, 1.0));
        grid.add(sample(0.6, 3, 0.35, 1.0));
        grid.add(sample(1.2, 2, 0.05, 3.0));
        let cells: Vec<CellSummary> = grid.cells().collect();
        assert_eq!(cells.len(), 2);
        assert_eq!((cells[0].samples, cells[0].tracks), (2, 1));
        assert!((cells[0].mean.x - 2.0).abs() < 1e-12);
        // The 0.35 cell empties and goes.
        grid.add(sample(1.7, 2, 0.05, 2.0));
        assert_eq!(grid.len(), 1);
        assert_eq!(grid.samples_added(), 5);
        grid.reset();
        assert!(grid.is_empty());
        assert_eq!(grid.samples_added(), 0);
    }

    #[test]
    fn bad_settings_and_bad_samples_are_refused() {
        assert_eq!(FieldGrid::new(0.0, None).err(), Some(FieldError::Cell(0.0)));
        assert!(FieldGrid::new(f64::INFINITY, None).is_err());
        assert_eq!(
            FieldGrid::new(0.1, Some(-1.0)).err(),
            Some(FieldError::Window(-1.0))
        );
        let mut grid = FieldGrid::new(0.1, None).expect("grid");
        grid.add(sample(0.0, 1, 0.05, f64::NAN));
        assert!(grid.is_empty());
    }

    #[test]
    fn the_default_cell_is_a_round_tenth_of_the_volume() {
        let positions: Vec<Point3<f64>> = (0..=100)
            .map(|i| Point3::new(i as f64 * 0.004, 0.0, 1.0 + i as f64 * 0.001))
            .collect();
        // 5th to 95th percentile of x: 0.36 m; a tenth, 0.036, rounds to 0.05 (log scale).
        let close = |a: f64, b: f64| (a - b).abs() < 1e-12 * b;
        assert!(default_cell_m(&positions).is_some_and(|c| close(c, 0.05)));
        assert_eq!(default_cell_m(&positions[..1]), None);
        assert!(close(nice_length(0.0013), 0.001));
        assert!(close(nice_length(0.016), 0.02));
        assert!(close(nice_length(0.34), 0.5));
        // A stray far away moves no percentile; a tie on the log scale goes to the smaller.
        let mut strayed = positions.clone();
        strayed[50] = Point3::new(40.0, 0.0, 1.0);
        assert!(default_cell_m(&strayed).is_some_and(|c| close(c, 0.05)));
        assert!(close(nice_length(0.01 * 2f64.sqrt() * (1.0 - 1e-15)), 0.01));
    }

    #[test]
    fn a_streamed_field_learns_its_cell_once_and_a_reset_keeps_it() {
        let vector = |i: usize| VelocityVector {
            frame_index: i as u64,
            t_s: i as f64 / 30.0,
            track_id: i as u64,
            position_in_world: Point3::new((i % 100) as f64 * 0.004, 0.0, 1.0),
            velocity_in_world: Vector3::new(0.1, 0.0, 0.0),
            rms_residual_m: 0.0,
            velocity_sigma: Vector3::zeros(),
            position_sigma: Vector3::zeros(),
        };
        let mut field = StreamField::new(None, None).expect("field");
        let first: Vec<VelocityVector> = (0..StreamField::SIZING_VECTORS - 1).map(vector).collect();
        field.add_vectors(&first);
        assert!(field.grid().is_none(), "not sized before 500 vectors");
        field.add_vectors(&[vector(499)]);
        let cell = field.grid().map(FieldGrid::cell_m).expect("sized at 500");
        assert!((cell - 0.05).abs() < 1e-12, "{cell}");
        field.reset();
        let wide: Vec<VelocityVector> = (0..600)
            .map(|i| VelocityVector {
                position_in_world: Point3::new(i as f64, 0.0, 1.0),
                ..vector(i)
            })
            .collect();
        field.add_vectors(&wide);
        assert_eq!(field.grid().map(FieldGrid::cell_m), Some(cell));
        assert_eq!(field.grid().map(FieldGrid::samples_added), Some(600));
    }
}
