//! Vectors that stray from their neighbours: universal outlier detection (Westerweel & Scarano
//! 2005) on scattered vectors.

use nalgebra::{Point3, Vector3};

use crate::spatial::median;

/// How a frame's vectors are checked against their neighbours (universal outlier detection,
/// Westerweel & Scarano 2005, on scattered vectors).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NeighbourTest {
    /// Nearest vectors (in space, same frame) each one is compared with.
    pub neighbours: usize,
    /// How many of their median deviations a component may stray from their median.
    pub threshold: f64,
    /// Deviation always allowed, as a fraction of the neighbours' median speed: the noise
    /// floor, so vectors of a flow that is uniform to within the noise are not judged by the
    /// noise alone.
    pub noise_fraction: f64,
    /// A vector is tested only where its neighbours agree: their median deviation, in every
    /// component, under this fraction of their median speed plus what their own noise spreads
    /// that component by (their stated sigmas: far particles' depth noise is many times the
    /// frame's typical one). Where vectors sample the flow too sparsely to resolve it,
    /// neighbours differ for real and the test would drop good vectors (asked of one component
    /// at a time, eight neighbours of an unresolved field agree on one by chance often enough
    /// to matter). Noise is not flow: depth noise alone spreads the out-of-plane component
    /// of slow flow beyond a fraction of its speed, and would otherwise shelter a vector far
    /// off in every component.
    pub coherence: f64,
}

/// For each vector (position, velocity, its stated 1-sigma error per component), whether it
/// strays from its neighbours by the test:
/// a wrong stereo pair or a track that swapped particles gives a velocity its neighbours do not
/// share, however smooth its own path. Where the neighbours do not agree well enough to be
/// asked component by component, a vector is still an outlier where it is off their median by
/// more than the threshold times their speed, their spread and its own stated error together. Deterministic whatever the input order of equidistant
/// points' ties (broken by index); fewer than `neighbours + 1` vectors are not tested.
pub fn neighbour_outliers(
    vectors: &[(Point3<f64>, Vector3<f64>, Vector3<f64>)],
    test: &NeighbourTest,
) -> Vec<bool> {
    let k = test.neighbours;
    let mut outliers = vec![false; vectors.len()];
    if k == 0 || vectors.len() <= k {
        return outliers;
    }
    let positions: Vec<Point3<f64>> = vectors.iter().map(|v| v.0).collect();
    let grid = Grid3::new(&positions);
    let mut nearest: Vec<(f64, usize)> = Vec::with_capacity(k + 1);
    let mut component = vec![0.0; k];
    for (i, &(_, velocity, sigma)) in vectors.iter().enumerate() {
        grid.nearest(&positions, i, k, &mut nearest);
        let mut centre = Vector3::zeros();
        let mut spread = Vector3::zeros();
        for c in 0..3 {
            fill(&mut component, &nearest, |j| vectors[j].1[c]);
            centre[c] = median(&mut component);
            fill(&mut component, &nearest, |j| {
                (vectors[j].1[c] - centre[c]).abs()
            });
            spread[c] = median(&mut component);
        }
        let speed = centre.norm();
        // The spread the neighbours' own noise gives them (the median absolute deviation of a
        // normal variable with their median stated sigma), asked only where it matters.
        let mut noise = |c: usize| {
            fill(&mut component, &nearest, |j| vectors[j].2[c]);
            0.6745 * median(&mut component)
        };
        let floor = test.coherence * speed;
        let coherent = (0..3).all(|c| spread[c] < floor || spread[c] < floor + noise(c));
        let strays = coherent
            && (0..3).any(|c| {
                (velocity[c] - centre[c]).abs()
                    > test.threshold * (spread[c] + test.noise_fraction * speed)
            });
        // Wherever the neighbours stand, agreeing or not, a vector off their median by more
        // than the threshold times all the motion they show (their speed and spread) and its
        // own stated error is none of theirs: a track that took a ghost's samples into its
        // window, metres per second in a flow of centimetres.
        let wild =
            (velocity - centre).norm() > test.threshold * (speed + spread.norm() + sigma.norm());
        outliers[i] = strays || wild;
    }
    outliers
}

/// `slots` filled with `value` of each of the `nearest` (distance, index) in turn.
fn fill(slots: &mut [f64], nearest: &[(f64, usize)], value: impl Fn(usize) -> f64) {
    for (slot, &(_, j)) in slots.iter_mut().zip(nearest) {
        *slot = value(j);
    }
}

/// Points binned in a regular grid of cubes over the box holding all but their outermost,
/// about one point per cube, for k-nearest searches that look only at the cubes around a
/// point.
struct Grid3 {
    origin: Point3<f64>,
    cell: f64,
    dims: [usize; 3],
    /// Per cube (x fastest), where its points start in `order`; one more entry at the end.
    start: Vec<usize>,
    /// Point indices, cube by cube.
    order: Vec<usize>,
}

impl Grid3 {
    fn new(points: &[Point3<f64>]) -> Self {
        // The box holds all but the outermost points along each axis (a ghost metres away
        // would otherwise leave the cloud in one cube); those beyond it go to its edge cubes.
        let (lo, hi) = (
            quantiles(points, OUTSIDE_FRACTION),
            quantiles(points, 1.0 - OUTSIDE_FRACTION),
        );
        let extent = hi - lo;
        let n = points.len().max(1);
        // The finest cube that gives no more cubes than points (a flat or thin cloud's
        // thin sides take one cube).
        let dims_for = |cell: f64| extent.map(|e| ((e / cell) as usize).saturating_add(1));
        let widest = extent.max().max(f64::MIN_POSITIVE);
        let mut cell = widest;
        for m in 2..=n {
            let finer = widest / m as f64;
            let d = dims_for(finer);
            if d.iter()
                .try_fold(1usize, |a, &b| a.checked_mul(b))
                .is_none_or(|c| c > n)
            {
                break;
            }
            cell = finer;
        }
        let d = dims_for(cell);
        let dims = [d.x, d.y, d.z];
        let cube_of = |p: &Point3<f64>| {
            let c = |a: usize| cube_along(p[a] - lo[a], cell, dims[a]);
            c(0) + dims[0] * (c(1) + dims[1] * c(2))
        };
        let mut start = vec![0; dims.iter().product::<usize>() + 1];
        for p in points {
            start[cube_of(p) + 1] += 1;
        }
        for c in 1..start.len() {
            start[c] += start[c - 1];
        }
        let mut fill = start.clone();
        let mut order = vec![0; points.len()];
        for (i, p) in points.iter().enumerate() {
            let c = cube_of(p);
            order[fill[c]] = i;
            fill[c] += 1;
        }
        Self {
            origin: lo,
            cell,
            dims,
            start,
            order,
        }
    }

    /// The `k` points nearest to point `i` (itself left out) into `nearest`, as (squared
    /// distance, index), ties broken by index: the cubes around `i`'s in growing shells, until
    /// no cube further out can hold a point nearer than the k-th found.
    fn nearest(&self, points: &[Point3<f64>], i: usize, k: usize, nearest: &mut Vec<(f64, usize)>) {
        nearest.clear();
        let p = points[i];
        let home: [usize; 3] =
            std::array::from_fn(|a| cube_along(p[a] - self.origin[a], self.cell, self.dims[a]));
        for r in 0.. {
            let lo: [usize; 3] = std::array::from_fn(|a| home[a].saturating_sub(r));
            let hi: [usize; 3] = std::array::from_fn(|a| (home[a] + r).min(self.dims[a] - 1));
            for z in lo[2]..=hi[2] {
                for y in lo[1]..=hi[1] {
                    for x in lo[0]..=hi[0] {
                        let shell = [x, y, z]
                            .iter()
                            .zip(&home)
                            .any(|(&c, &h)| c.abs_diff(h) == r);
                        if shell {
                            let c = x + self.dims[0] * (y + self.dims[1] * z);
                            for &j in &self.order[self.start[c]..self.start[c + 1]] {
                                if j != i {
                                    consider(nearest, k, ((points[j] - p).norm_squared(), j));
                                }
                            }
                        }
                    }
                }
            }
            // The nearest a point outside the searched block can be (none beyond the grid; a
            // point beyond the box sits in an edge cube, further out than its cube starts).
            let clear = (0..3)
                .flat_map(|a| {
                    let below =
                        (lo[a] > 0).then(|| p[a] - (self.origin[a] + lo[a] as f64 * self.cell));
                    let above = (hi[a] + 1 < self.dims[a])
                        .then(|| self.origin[a] + (hi[a] + 1) as f64 * self.cell - p[a]);
                    [below, above]
                })
                .flatten()
                .fold(f64::INFINITY, f64::min);
            let full = nearest.len() == k;
            if clear == f64::INFINITY || (full && nearest[k - 1].0 < clear * clear) {
                break;
            }
        }
    }
}

/// Points outside the grid's box along each axis, at most, at each end.
const OUTSIDE_FRACTION: f64 = 0.01;

/// Per axis, the `q` quantile of `points`' coordinates.
fn quantiles(points: &[Point3<f64>], q: f64) -> Point3<f64> {
    let mut along: Vec<f64> = Vec::with_capacity(points.len());
    Point3::from(std::array::from_fn(|a| {
        along.clear();
        along.extend(points.iter().map(|p| p[a]));
        let at = ((along.len().max(1) - 1) as f64 * q).round() as usize;
        along
            .select_nth_unstable_by(at, f64::total_cmp)
            .1
            .to_owned()
    }))
}

/// The cube, of `dims` along an axis of cubes `cell` wide, a coordinate `offset` from the
/// box's start falls in (those beyond the box in the edge cubes).
fn cube_along(offset: f64, cell: f64, dims: usize) -> usize {
    ((offset.max(0.0) / cell) as usize).min(dims - 1)
}

/// Puts `key` (squared distance, index) among the `k` nearest so far, kept sorted.
fn consider(nearest: &mut Vec<(f64, usize)>, k: usize, key: (f64, usize)) {
    if nearest.len() == k && !lexically_less(key, nearest[k - 1]) {
        return;
    }
    let at = nearest.partition_point(|&e| lexically_less(e, key));
    nearest.insert(at, key);
    nearest.truncate(k);
}

fn lexically_less(a: (f64, usize), b: (f64, usize)) -> bool {
    a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).is_lt()
}

#[cfg(test)]
mod tests {
    use super::*;

    const TEST: NeighbourTest = NeighbourTest {
        neighbours: 8,
        threshold: 4.0,
        noise_fraction: 0.02,
        coherence: 0.05,
    };

    /// Vectors on a 6 x 6 x 2 grid (2 cm spacing) of velocity `(1, 0, -1)` plus `wobble` times
    /// a deterministic pattern in -1..1 per component, each stated with 1-sigma errors of
    /// `sigma`.
    fn field_with(
        wobble: Vector3<f64>,
        sigma: Vector3<f64>,
    ) -> Vec<(Point3<f64>, Vector3<f64>, Vector3<f64>)> {
        let pattern = |i: usize, c: usize| {
            let mut x = ((i * 3 + c) as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15);
            x ^= x >> 31;
            x = x.wrapping_mul(0xBF58_476D_1CE4_E5B9);
            x ^= x >> 27;
            (x % 2001) as f64 / 1000.0 - 1.0
        };
        (0..72)
            .map(|i| {
                let p = Point3::new((i % 6) as f64, (i / 6 % 6) as f64, (i / 36) as f64) * 0.02;
                let v = Vector3::new(1.0, 0.0, -1.0)
                    + wobble.component_mul(&Vector3::new(
                        pattern(i, 0),
                        pattern(i, 1),
                        pattern(i, 2),
                    ));
                (p, v, sigma)
            })
            .collect()
    }

    /// [`field_with`] with the same wobble in every component, stated with a sigma of half
    /// of it.
    fn grid_field(wobble: f64) -> Vec<(Point3<f64>, Vector3<f64>, Vector3<f64>)> {
        field_with(Vector3::repeat(wobble), Vector3::repeat(0.5 * wobble))
    }

    fn flagged(field: &[(Point3<f64>, Vector3<f64>, Vector3<f64>)]) -> Vec<usize> {
        neighbour_outliers(field, &TEST)
            .iter()
            .enumerate()
            .filter_map(|(i, &o)| o.then_some(i))
            .collect()
    }

    #[test]
    fn a_vector_its_neighbours_do_not_share_is_an_outlier() {
        // Noise of 0.5 % of the speed, and one vector 10 % off in w (a wrong stereo pair).
        let mut field = grid_field(0.007);
        assert!(neighbour_outliers(&field, &TEST).iter().all(|&o| !o));
        field[20].1.z -= 0.14;
        assert_eq!(flagged(&field), [20]);
        // The same answer whatever the order the vectors come in.
        let reversed: Vec<_> = field.iter().rev().copied().collect();
        let mut back = neighbour_outliers(&reversed, &TEST);
        back.reverse();
        assert_eq!(back, neighbour_outliers(&field, &TEST));
        // Off, or with too few vectors to have the neighbours asked for: nothing is tested.
        let off = NeighbourTest {
            neighbours: 0,
            ..TEST
        };
        assert!(neighbour_outliers(&field, &off).iter().all(|&o| !o));
        assert!(neighbour_outliers(&field[15..23], &TEST)
            .iter()
            .all(|&o| !o));
    }

    #[test]
    fn the_grid_finds_the_nearest_points_as_a_search_of_all_would() {
        // A cloud, a flat sheet, a line with repeated points (ties broken by index), and a
        // cloud with points far outside it.
        let mut state = 7u64;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let cloud: Vec<Point3<f64>> = (0..300)
            .map(|_| Point3::new(next(), 0.2 * next(), 3.0 * next()))
            .collect();
        let sheet: Vec<Point3<f64>> = (0..200)
            .map(|i| Point3::new(next(), next(), 0.0) + Vector3::x() * f64::from(i % 3 == 0))
            .collect();
        let line: Vec<Point3<f64>> = (0..50)
            .map(|i| Point3::new(f64::from(i / 2), 0.0, 0.0))
            .collect();
        // The cloud again with a few points far outside it (ghosts metres away).
        let mut scattered = cloud.clone();
        scattered.extend((0..4).map(|i| Point3::new(50.0 * f64::from(i) - 70.0, 3.0, -9.0)));
        for points in [cloud, sheet, line, scattered] {
            let grid = Grid3::new(&points);
            let mut found = Vec::new();
            for i in 0..points.len() {
                grid.nearest(&points, i, 8, &mut found);
                let mut all: Vec<(f64, usize)> = (0..points.len())
                    .filter(|&j| j != i)
                    .map(|j| ((points[j] - points[i]).norm_squared(), j))
                    .collect();
                all.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
                assert_eq!(found, all[..8], "point {i}");
            }
        }
    }

    #[test]
    fn where_neighbours_disagree_nothing_is_judged() {
        // Neighbours 30 % apart, each stated to 1 %: the flow is not resolved at this spacing,
        // so a vector 40 % off its neighbours' median is not called an outlier.
        let mut field = field_with(Vector3::repeat(0.3), Vector3::repeat(0.01));
        field[20].1.z -= 0.4;
        assert!(flagged(&field).is_empty());
    }

    #[test]
    fn a_wild_vector_is_an_outlier_among_neighbours_that_disagree() {
        // Neighbours 30 % apart as above (not asked component by component); a vector off
        // their median by ten times their speed, with a small stated error (a track whose
        // window took a ghost's samples), is found; stated as that uncertain, it is not.
        let mut field = field_with(Vector3::repeat(0.3), Vector3::repeat(0.01));
        field[20].1 += Vector3::new(10.0, 6.0, -5.0);
        assert_eq!(flagged(&field), [20]);
        field[20].2 = Vector3::repeat(4.0);
        assert!(flagged(&field).is_empty());
    }

    #[test]
    fn noisier_neighbours_than_most_still_judge_a_vector() {
        // Most vectors measured to 0.5 %; one corner of the volume (far from the cameras) with
        // w spread by up to 16 % by its depth noise, and stated so. A vector there 30 % off in u
        // is found: its neighbours agree to within their own noise, if not the frame's.
        let mut field = field_with(Vector3::repeat(0.005), Vector3::repeat(0.003));
        let far = |i: usize| i % 6 >= 3 && i / 6 % 6 >= 3;
        for (i, (_, v, sigma)) in field.iter_mut().enumerate().filter(|(i, _)| far(*i)) {
            v.z += 0.16 * (((i * 7) % 11) as f64 / 5.0 - 1.0);
            sigma.z = 0.15;
        }
        assert!(flagged(&field).is_empty());
        field[28].1.x += 0.3;
        assert_eq!(flagged(&field), [28]);
    }

    #[test]
    fn noise_in_one_component_does_not_shelter_a_vector_off_in_another() {
        // Slow flow seen from afar: u and v to 0.5 %, w spread by its depth noise over 10 %
        // of the speed (and stated so). One vector 30 % off in u, a track that swapped
        // particles, is still found; without it, nothing is.
        let mut field = field_with(
            Vector3::new(0.005, 0.005, 0.2),
            Vector3::new(0.003, 0.003, 0.15),
        );
        assert!(flagged(&field).is_empty());
        field[20].1.x += 0.3;
        assert_eq!(flagged(&field), [20]);
    }
}
