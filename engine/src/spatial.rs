//! Spatial helpers the stages share: a grid of points for box and nearest-neighbour queries, a
//! sort by x for band queries, medians, cost normalisation and the assignment of candidates.
//! Each keeps a stage's cost proportional to what it looks at, not to every pair.

use std::cmp::Ordering;

use serde::{Deserialize, Serialize};

use crate::geometry::RectPoint;

/// Side of the cells that index image points, pixels: about the spacing of neighbouring particle
/// images, so a neighbourhood query visits a few cells.
pub(crate) const GRID_CELL_PX: f64 = 16.0;

/// How candidates are assigned once every cost is known.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Assignment {
    /// The method: each particle takes its own cheapest candidate. Where two claim the same
    /// candidate, the cheaper claim wins and the other particle goes unmatched.
    PerParticle,
    /// Globally cheapest pairs first, each candidate used once: a particle that loses its first
    /// choice still gets its next-best free candidate.
    OneToOne,
}

/// Picks pairs `(row, column)` from candidate `(cost, row, column)` triples, in the order of
/// [`cheapest_first`].
/// Dense seeding gives tens of candidates per row, and most lose to a cheaper claim on their
/// row or column: the candidates are taken in cheap batches, each batch sorted, and what the
/// batches left undecided sorted next, so a sort never pays for candidates no pick would see.
pub(crate) fn assign(
    mut candidates: Vec<(f64, usize, usize)>,
    rows: usize,
    columns: usize,
    mode: Assignment,
) -> Vec<(usize, usize)> {
    let batch = 2 * (rows + columns).max(1);
    let mut row_done = vec![false; rows];
    let mut column_done = vec![false; columns];
    let mut pairs = Vec::new();
    while !candidates.is_empty() {
        let rest = if candidates.len() > batch {
            candidates.select_nth_unstable_by(batch - 1, cheapest_first);
            candidates.split_off(batch)
        } else {
            Vec::new()
        };
        candidates.sort_unstable_by(cheapest_first);
        for &(_, r, c) in &candidates {
            pick((r, c), mode, (&mut row_done, &mut column_done), &mut pairs);
        }
        candidates = rest;
        // A candidate whose row is decided (or, one to one, whose column is taken) is never
        // picked: it need not be sorted.
        candidates.retain(|&(_, r, c)| {
            !row_done[r] && (mode == Assignment::PerParticle || !column_done[c])
        });
    }
    pairs.sort_unstable();
    pairs
}

/// The order candidates `(cost, row, column)` are taken in: cheapest first, ties by row, then
/// by column, so that the outcome does not depend on the order they were found in.
pub(crate) fn cheapest_first(a: &(f64, usize, usize), b: &(f64, usize, usize)) -> Ordering {
    a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2))
}

/// Takes candidate `(r, c)`, the cheapest left, as `mode` says: one to one where neither its
/// row nor its column is taken; per particle, as its row's own cheapest candidate, which goes
/// unmatched where a cheaper claim took the column.
fn pick(
    (r, c): (usize, usize),
    mode: Assignment,
    (row_done, column_done): (&mut [bool], &mut [bool]),
    pairs: &mut Vec<(usize, usize)>,
) {
    if row_done[r] {
        return;
    }
    match mode {
        Assignment::OneToOne => {
            if column_done[c] {
                return;
            }
            row_done[r] = true;
            column_done[c] = true;
            pairs.push((r, c));
        }
        Assignment::PerParticle => {
            row_done[r] = true;
            if !column_done[c] {
                column_done[c] = true;
                pairs.push((r, c));
            }
        }
    }
}

/// The mean that normalises a cost term (D_ave, B_ave, U_ave); 1 when there is nothing to average,
/// so an empty frame never divides by zero.
pub(crate) fn normalising_mean(values: impl Iterator<Item = f64>) -> f64 {
    let (sum, n) = values.fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    if n == 0 || sum <= 0.0 {
        1.0
    } else {
        sum / n as f64
    }
}

/// The median of `values` (0 for none), which it reorders: a selection, not a sort, as the
/// scene's pool asks for many medians each frame.
pub(crate) fn median(values: &mut [f64]) -> f64 {
    let n = values.len();
    if n == 0 {
        return 0.0;
    }
    let (below, &mut upper, _) = values.select_nth_unstable_by(n / 2, f64::total_cmp);
    if n % 2 == 1 {
        upper
    } else {
        let lower = below
            .iter()
            .copied()
            .max_by(f64::total_cmp)
            .unwrap_or(upper);
        (lower + upper) / 2.0
    }
}

/// Points bucketed in square cells, so box and nearest-neighbour queries cost the cells they
/// touch rather than every point: a new track's first step asks both, for each of its candidate
/// steps, and a dense frame has a thousand new tracks.
pub(crate) struct PointGrid {
    cell_px: f64,
    min_x: f64,
    min_y: f64,
    columns: usize,
    rows: usize,
    /// Points of cell `c` are `points[starts[c]..starts[c + 1]]`, with their indices.
    starts: Vec<usize>,
    points: Vec<(RectPoint, usize)>,
}

impl PointGrid {
    pub(crate) fn new(points: impl Iterator<Item = (RectPoint, usize)>, cell_px: f64) -> Self {
        let points: Vec<(RectPoint, usize)> = points.collect();
        let (mut min_x, mut min_y, mut max_x, mut max_y) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
        if let Some((first, _)) = points.first() {
            (min_x, min_y, max_x, max_y) = (first.x, first.y, first.x, first.y);
        }
        for (p, _) in &points {
            min_x = min_x.min(p.x);
            min_y = min_y.min(p.y);
            max_x = max_x.max(p.x);
            max_y = max_y.max(p.y);
        }
        let columns = ((max_x - min_x) / cell_px) as usize + 1;
        let rows = ((max_y - min_y) / cell_px) as usize + 1;
        let mut grid = Self {
            cell_px,
            min_x,
            min_y,
            columns,
            rows,
            starts: vec![0; columns * rows + 1],
            points: Vec::with_capacity(points.len()),
        };
        let cells: Vec<usize> = points
            .iter()
            .map(|(p, _)| {
                let (column, row) = grid.cell_of(p.x, p.y);
                column + row * columns
            })
            .collect();
        for &c in &cells {
            grid.starts[c + 1] += 1;
        }
        for c in 0..columns * rows {
            grid.starts[c + 1] += grid.starts[c];
        }
        let mut order: Vec<usize> = (0..points.len()).collect();
        order.sort_by_key(|&i| (cells[i], i));
        grid.points = order.into_iter().map(|i| points[i]).collect();
        grid
    }

    /// Column and row of the cell holding (x, y), clamped to the grid.
    fn cell_of(&self, x: f64, y: f64) -> (usize, usize) {
        let column = ((x - self.min_x) / self.cell_px).floor().max(0.0) as usize;
        let row = ((y - self.min_y) / self.cell_px).floor().max(0.0) as usize;
        (column.min(self.columns - 1), row.min(self.rows - 1))
    }

    /// Points in the cells overlapping the box `x +- half`, `y +- half` (a superset of the box).
    pub(crate) fn near(
        &self,
        x: f64,
        y: f64,
        half: f64,
    ) -> impl Iterator<Item = &(RectPoint, usize)> {
        let (c0, r0) = self.cell_of(x - half, y - half);
        let (c1, r1) = self.cell_of(x + half, y + half);
        (r0..=r1).flat_map(move |r| {
            let row = r * self.columns;
            self.points[self.starts[row + c0]..self.starts[row + c1 + 1]].iter()
        })
    }

    pub(crate) fn any_in_box(&self, x: f64, y: f64, half: f64) -> bool {
        self.near(x, y, half)
            .any(|(p, _)| (p.x - x).abs() <= half && (p.y - y).abs() <= half)
    }

    /// Up to `k` points nearest to (x, y), except index `skip`; nearest first.
    pub(crate) fn nearest(&self, x: f64, y: f64, k: usize, skip: usize) -> Vec<RectPoint> {
        self.nearest_indexed(x, y, k, skip)
            .into_iter()
            .map(|(p, _)| p)
            .collect()
    }

    /// Up to `k` points nearest to (x, y) with their indices, except index `skip`; nearest
    /// first. Exact: every point within the search radius is seen before the radius is trusted.
    pub(crate) fn nearest_indexed(
        &self,
        x: f64,
        y: f64,
        k: usize,
        skip: usize,
    ) -> Vec<(RectPoint, usize)> {
        let mut found = Vec::with_capacity(4 * k);
        self.nearest_unordered(x, y, k, skip, &mut found);
        found.sort_unstable_by(nearest_first);
        found.into_iter().map(|(_, p)| p).collect()
    }

    /// As [`Self::nearest_indexed`], in no particular order, into `found` (cleared first) with
    /// each one's squared distance: for a caller that needs only which points they are.
    pub(crate) fn nearest_unordered(
        &self,
        x: f64,
        y: f64,
        k: usize,
        skip: usize,
        found: &mut Vec<(f64, (RectPoint, usize))>,
    ) {
        // Start at a radius that holds about twice `k` points at the grid's mean density: a
        // sparse grid would otherwise be scanned again at every radius up to the one it needs.
        let area = (self.columns * self.rows) as f64 * self.cell_px * self.cell_px;
        let expected = (2.0 * k as f64 * area
            / (std::f64::consts::PI * self.points.len().max(1) as f64))
            .sqrt();
        let mut half = self.cell_px.max(expected);
        loop {
            // By squared distance: the same order, without a square root per point.
            found.clear();
            for &(p, i) in self.near(x, y, half) {
                let d_sq = (p.x - x).powi(2) + (p.y - y).powi(2);
                if i != skip && d_sq <= half * half {
                    found.push((d_sq, (p, i)));
                }
            }
            let everything = half > self.cell_px * (self.columns + self.rows) as f64;
            if found.len() >= k || everything {
                // Only which are the k nearest matters here (ties by index).
                if found.len() > k {
                    found.select_nth_unstable_by(k, nearest_first);
                    found.truncate(k);
                }
                return;
            }
            half *= 2.0;
        }
    }
}

/// Nearest first by squared distance, ties by index.
fn nearest_first(
    a: &(f64, (RectPoint, usize)),
    b: &(f64, (RectPoint, usize)),
) -> std::cmp::Ordering {
    a.0.total_cmp(&b.0).then(a.1 .1.cmp(&b.1 .1))
}

/// The fewest successes, at least 2, with `binomial_tail(n, v, p) < chance`; `None` if even `n`
/// is not that unlikely.
pub(crate) fn votes_needed(n: usize, p: f64, chance: f64) -> Option<usize> {
    binomial_tails(n, p)
        .enumerate()
        .take(n + 1)
        .skip(2)
        .find(|&(_, tail)| tail < chance)
        .map(|(at_least, _)| at_least)
}

/// P(X >= at_least) for X ~ Binomial(n, p).
pub(crate) fn binomial_tail(n: usize, at_least: usize, p: f64) -> f64 {
    binomial_tails(n, p).nth(at_least.min(n + 1)).unwrap_or(0.0)
}

/// P(X >= 0), P(X >= 1), ..., P(X >= n + 1) for X ~ Binomial(n, p): one minus the probability
/// terms summed from below, so every tail is computed the same way wherever it is asked for.
fn binomial_tails(n: usize, p: f64) -> impl Iterator<Item = f64> {
    let mut term = (1.0 - p).powi(n as i32);
    let mut below = 0.0;
    std::iter::once(1.0).chain((0..=n).map(move |i| {
        below += term;
        term *= (n - i) as f64 / (i + 1) as f64 * p / (1.0 - p).max(f64::MIN_POSITIVE);
        (1.0 - below).max(0.0)
    }))
}

/// Point indices sorted by x, so a box query costs a binary search plus its hits.
pub(crate) struct SortedByX {
    order: Vec<(f64, usize)>,
}

impl SortedByX {
    pub(crate) fn new(points: impl Iterator<Item = RectPoint>) -> Self {
        let mut order: Vec<(f64, usize)> = points.enumerate().map(|(i, p)| (p.x, i)).collect();
        order.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        Self { order }
    }

    pub(crate) fn within(&self, min_x: f64, max_x: f64) -> impl Iterator<Item = usize> + '_ {
        let start = self.order.partition_point(|(x, _)| *x < min_x);
        self.order[start..]
            .iter()
            .take_while(move |(x, _)| *x <= max_x)
            .map(|(_, i)| *i)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn binomial_tail_matches_direct_sums() {
        assert!((binomial_tail(8, 0, 0.3) - 1.0).abs() < 1e-12);
        assert!((binomial_tail(2, 2, 0.5) - 0.25).abs() < 1e-12);
        assert!((binomial_tail(3, 2, 0.5) - 0.5).abs() < 1e-12);
        assert!(binomial_tail(8, 5, 0.01) < 1e-7);
    }

    #[test]
    fn votes_needed_is_the_fewest_that_chance_explains_too_rarely() {
        for n in 2..=8 {
            for p in [1e-4, 0.01, 0.05, 0.1, 0.2, 0.4, 0.7] {
                let direct = (2..=n).find(|&v| binomial_tail(n, v, p) < 1e-3);
                assert_eq!(votes_needed(n, p, 1e-3), direct, "n {n}, p {p}");
            }
        }
        assert_eq!(votes_needed(8, 0.7, 1e-3), None);
    }

    #[test]
    fn median_of_odd_even_and_no_values() {
        assert_eq!(median(&mut [3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&mut [4.0, 1.0, 3.0, 2.0]), 2.5);
        assert_eq!(median(&mut [5.0, 5.0, -1.0, 7.0, 5.0, 0.5]), 5.0);
        assert_eq!(median(&mut []), 0.0);
    }

    /// Greedy assignment over every candidate sorted at once, as the batches must reproduce.
    fn assign_sorted_at_once(
        mut candidates: Vec<(f64, usize, usize)>,
        rows: usize,
        columns: usize,
        mode: Assignment,
    ) -> Vec<(usize, usize)> {
        candidates.sort_by(cheapest_first);
        let (mut row_done, mut column_done) = (vec![false; rows], vec![false; columns]);
        let mut pairs = Vec::new();
        for (_, r, c) in candidates {
            pick((r, c), mode, (&mut row_done, &mut column_done), &mut pairs);
        }
        pairs.sort_unstable();
        pairs
    }

    #[test]
    fn batches_pick_what_one_sort_of_every_candidate_picks() {
        let mut state = 12345_u64;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            state >> 33
        };
        let (rows, columns) = (300, 280);
        // Many candidates per row, with tied costs, so that most rounds leave some undecided.
        let candidates: Vec<(f64, usize, usize)> = (0..20 * rows)
            .map(|_| {
                let cost = (next() % 1000) as f64 * 0.01;
                (cost, next() as usize % rows, next() as usize % columns)
            })
            .collect();
        for mode in [Assignment::OneToOne, Assignment::PerParticle] {
            let expected = assign_sorted_at_once(candidates.clone(), rows, columns, mode);
            assert!(expected.len() > rows / 2);
            assert_eq!(assign(candidates.clone(), rows, columns, mode), expected);
        }
    }

    #[test]
    fn per_particle_loser_goes_unmatched_one_to_one_gets_next_best() {
        let candidates = vec![(0.1, 0, 0), (0.2, 1, 0), (0.5, 1, 1)];
        assert_eq!(
            assign(candidates.clone(), 2, 2, Assignment::PerParticle),
            vec![(0, 0)]
        );
        assert_eq!(
            assign(candidates, 2, 2, Assignment::OneToOne),
            vec![(0, 0), (1, 1)]
        );
    }
}
