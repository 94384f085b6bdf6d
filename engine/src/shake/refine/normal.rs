//! One Gauss-Newton iteration's normal equations, member by member: each member visits only
//! the pixels of its own box (found by row in the window, which runs row by row), and a pixel
//! two members reach couples them. Every cell of `J^T J` and `J^T r` still sums its pixels in
//! the window's order, so the sums are the ones a pixel-by-pixel pass gives.

use std::ops::Range;

use nalgebra::{DMatrix, DVector};

use super::{logistic_table, Floor, FloorBlock, Free, InFit, Member, FLOOR_TERMS};
use crate::geometry::PixelPoint;

/// A fit's samples by row: each row's y and the range of its samples (a window runs row by
/// row, x increasing).
pub(super) struct Rows(Vec<(f64, Range<usize>)>);

impl Rows {
    pub(super) fn of(samples: &[(f64, f64, f64)]) -> Self {
        let mut rows: Vec<(f64, Range<usize>)> = Vec::new();
        for (i, s) in samples.iter().enumerate() {
            match rows.last_mut() {
                Some((y, range)) if *y == s.1 => range.end = i + 1,
                _ => rows.push((s.1, i..i + 1)),
            }
        }
        Self(rows)
    }

    /// The runs of samples within `half` of `c` along both axes.
    fn within<'a>(
        &'a self,
        samples: &'a [(f64, f64, f64)],
        c: PixelPoint,
        half: f64,
    ) -> impl Iterator<Item = Range<usize>> + 'a {
        let first = self.0.partition_point(|(y, _)| *y < c.y - half);
        self.0[first..]
            .iter()
            .take_while(move |(y, _)| *y <= c.y + half)
            .map(move |(_, range)| {
                let row = &samples[range.clone()];
                let from = row.partition_point(|s| s.0 < c.x - half);
                let to = row.partition_point(|s| s.0 <= c.x + half);
                range.start + from..range.start + to
            })
    }
}

/// One member's pixels within its reach: each sample's index and the member's Jacobian values
/// there (x, y, amplitude, then radius and edge where free; zero where a derivative is left
/// out), `len` of them from unknown `first`.
#[derive(Default)]
struct Hits {
    first: usize,
    len: usize,
    idx: Vec<usize>,
    offsets: Vec<(f64, f64, f64)>,
    values: Vec<[f64; 5]>,
}

/// A fit's normal equations, rebuilt at every iteration in buffers kept across them.
#[derive(Default)]
pub(super) struct Normal {
    model: Vec<f64>,
    residuals: Vec<f64>,
    hits: Vec<Hits>,
    upper: Vec<f64>,
    jtr: Vec<f64>,
}

impl Normal {
    /// `J^T J`, `J^T r` and the sum of squared residuals of the model (`floor` plus the
    /// members' discs but those `gone`) over `samples` (by `rows`); per member the unknowns are
    /// x, y, amplitude (and radius, edge).
    pub(super) fn build(
        &mut self,
        (samples, rows): (&[(f64, f64, f64)], &Rows),
        (floor, floor_block): (&Floor, &FloorBlock),
        (members, gone): (&[Member], &[bool]),
        free: Free,
    ) -> (DMatrix<f64>, DVector<f64>, f64) {
        let per = free.per_member();
        let n = FLOOR_TERMS + per * members.len();
        self.model.clear();
        self.model
            .extend(samples.iter().map(|&(x, y, _)| floor.at((x, y))));
        self.hits.resize_with(members.len(), Hits::default);
        let live = members.iter().enumerate().filter(|(k, _)| !gone[*k]);
        for (h, (k, m)) in self.hits.iter_mut().zip(live) {
            let in_fit = InFit::new(m, FLOOR_TERMS + per * k, free);
            h.fill(&in_fit, (samples, rows), free, &mut self.model);
        }
        let live = members.len() - gone.iter().filter(|g| **g).count();
        let hits = &self.hits[..live];
        self.residuals.clear();
        self.residuals
            .extend(samples.iter().zip(&self.model).map(|(s, m)| s.2 - m));
        let cost = self.residuals.iter().fold(0.0, |c, r| c + r * r);
        // Upper triangle only, accumulated flat; mirrored once at the end.
        let (upper, jtr) = (&mut self.upper, &mut self.jtr);
        upper.clear();
        upper.resize(n * n, 0.0);
        jtr.clear();
        jtr.resize(n, 0.0);
        for (&(x, y, _), &residual) in samples.iter().zip(&self.residuals) {
            let d = [1.0, x - floor.centre.0, y - floor.centre.1];
            for (t, di) in jtr.iter_mut().zip(d) {
                *t += residual * di;
            }
        }
        for (a, h) in hits.iter().enumerate() {
            member_terms(h, (samples, &self.residuals), floor, (upper, jtr), n);
            for b in &hits[a + 1..] {
                cross_terms(h, b, upper, n);
            }
        }
        for (i, line) in floor_block.iter().enumerate() {
            upper[i * n..i * n + FLOOR_TERMS].copy_from_slice(line);
        }
        let jtj = DMatrix::from_fn(n, n, |i, j| {
            let v = upper[i.min(j) * n + i.max(j)];
            // Levenberg's touch of damping keeps a group whose members nearly coincide
            // solvable.
            if i == j {
                v * (1.0 + 1e-3) + 1e-9
            } else {
                v
            }
        });
        (jtj, DVector::from_column_slice(jtr), cost)
    }
}

impl Hits {
    /// A member's pixels and Jacobian values, its light added to `model`: first the pixels
    /// within its reach, then their values in one pass over them.
    fn fill(
        &mut self,
        m: &InFit,
        (samples, rows): (&[(f64, f64, f64)], &Rows),
        free: Free,
        model: &mut [f64],
    ) {
        self.first = m.first;
        self.len = m.unknowns(free);
        self.idx.clear();
        self.offsets.clear();
        // Widened by a hair so that rounding never leaves out a pixel within the reach.
        let half = m.reach_sq.sqrt() + 1e-9;
        for run in rows.within(samples, m.at, half) {
            for i in run {
                let (x, y, _) = samples[i];
                let (dx, dy) = (x - m.at.x, y - m.at.y);
                let r_sq = dx * dx + dy * dy;
                if r_sq <= m.reach_sq {
                    self.idx.push(i);
                    self.offsets.push((dx, dy, r_sq));
                }
            }
        }
        let table = logistic_table();
        self.values.clear();
        self.values.extend(
            self.offsets
                .iter()
                .map(|&(dx, dy, r_sq)| m.values(table, (dx, dy, r_sq.sqrt()), free)),
        );
        for (&i, v) in self.idx.iter().zip(&self.values) {
            model[i] += m.amplitude * v[2];
        }
    }
}

/// A member's own share of the normal equations: its block, the floor's rows against it, and
/// its `J^T r`. Only this member adds to these cells, so they are summed apart (in the same
/// order) and added once.
fn member_terms(
    h: &Hits,
    (samples, residuals): (&[(f64, f64, f64)], &[f64]),
    floor: &Floor,
    (upper, jtr): (&mut [f64], &mut [f64]),
    n: usize,
) {
    match h.len {
        3 => member_sums::<3>(h, (samples, residuals), floor, (upper, jtr), n),
        4 => member_sums::<4>(h, (samples, residuals), floor, (upper, jtr), n),
        _ => member_sums::<5>(h, (samples, residuals), floor, (upper, jtr), n),
    }
}

/// [`member_terms`] for a member of `L` unknowns.
fn member_sums<const L: usize>(
    h: &Hits,
    (samples, residuals): (&[(f64, f64, f64)], &[f64]),
    floor: &Floor,
    (upper, jtr): (&mut [f64], &mut [f64]),
    n: usize,
) {
    let mut by_floor = [[0.0; L]; FLOOR_TERMS];
    let mut own = [[0.0; L]; L];
    let mut by_residual = [0.0; L];
    for (&i, v) in h.idx.iter().zip(&h.values) {
        let (x, y, _) = samples[i];
        let d = [1.0, x - floor.centre.0, y - floor.centre.1];
        for (line, df) in by_floor.iter_mut().zip(d) {
            for p in 0..L {
                line[p] += df * v[p];
            }
        }
        let residual = residuals[i];
        for p in 0..L {
            by_residual[p] += residual * v[p];
            for q in p..L {
                own[p][q] += v[p] * v[q];
            }
        }
    }
    let first = h.first;
    for (f, line) in by_floor.iter().enumerate() {
        add_to(&mut upper[f * n + first..f * n + first + L], line);
    }
    add_to(&mut jtr[first..first + L], &by_residual);
    for p in 0..L {
        let row = first + p;
        add_to(&mut upper[row * n + row..row * n + first + L], &own[p][p..]);
    }
}

/// Adds `sums` to `cells`, cell by cell.
fn add_to(cells: &mut [f64], sums: &[f64]) {
    for (cell, sum) in cells.iter_mut().zip(sums) {
        *cell += sum;
    }
}

/// Two members' coupling (`a` before `b` among the unknowns) on the pixels both reach.
fn cross_terms(a: &Hits, b: &Hits, upper: &mut [f64], n: usize) {
    let (mut i, mut j) = (0, 0);
    while i < a.idx.len() && j < b.idx.len() {
        match a.idx[i].cmp(&b.idx[j]) {
            std::cmp::Ordering::Less => i += 1,
            std::cmp::Ordering::Greater => j += 1,
            std::cmp::Ordering::Equal => {
                let (va, vb) = (&a.values[i], &b.values[j]);
                for (p, &vp) in va[..a.len].iter().enumerate() {
                    let row = a.first + p;
                    let line = &mut upper[row * n + b.first..row * n + b.first + b.len];
                    for (cell, &vq) in line.iter_mut().zip(vb) {
                        *cell += vp * vq;
                    }
                }
                i += 1;
                j += 1;
            }
        }
    }
}
