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
    /// component, under this fraction of their median speed. Where vectors sample the flow too
    /// sparsely to resolve it, neighbours differ for real and the test would drop good vectors
    /// (asked of one component at a time, eight neighbours of an unresolved field agree on one
    /// by chance often enough to matter).
    pub coherence: f64,
}

/// For each vector (position, velocity), whether it strays from its neighbours by the test:
/// a wrong stereo pair or a track that swapped particles gives a velocity its neighbours do not
/// share, however smooth its own path. Deterministic whatever the input order of equidistant
/// points' ties (broken by index); fewer than `neighbours + 1` vectors are not tested.
pub fn neighbour_outliers(
    vectors: &[(Point3<f64>, Vector3<f64>)],
    test: &NeighbourTest,
) -> Vec<bool> {
    let k = test.neighbours;
    let mut outliers = vec![false; vectors.len()];
    if k == 0 || vectors.len() <= k {
        return outliers;
    }
    let mut by_x: Vec<usize> = (0..vectors.len()).collect();
    by_x.sort_by(|&a, &b| vectors[a].0.x.total_cmp(&vectors[b].0.x).then(a.cmp(&b)));
    let mut nearest: Vec<(f64, usize)> = Vec::with_capacity(k + 1);
    let mut component = vec![0.0; k];
    for (rank, &i) in by_x.iter().enumerate() {
        let p = vectors[i].0;
        nearest.clear();
        let consider = |j: usize, nearest: &mut Vec<(f64, usize)>| {
            let d2 = (vectors[j].0 - p).norm_squared();
            let key = (d2, j);
            if nearest.len() == k && !lexically_less(key, nearest[k - 1]) {
                return;
            }
            let at = nearest.partition_point(|&e| lexically_less(e, key));
            nearest.insert(at, key);
            nearest.truncate(k);
        };
        // Walk outwards in x until the x gap alone exceeds the k-th distance found.
        let (mut left, mut right) = (rank, rank + 1);
        loop {
            let bound = if nearest.len() == k {
                nearest[k - 1].0
            } else {
                f64::INFINITY
            };
            let gap = |q: usize| (vectors[by_x[q]].0.x - p.x).powi(2);
            let go_left = left > 0 && gap(left - 1) <= bound;
            let go_right = right < by_x.len() && gap(right) <= bound;
            if !go_left && !go_right {
                break;
            }
            if go_left {
                left -= 1;
                consider(by_x[left], &mut nearest);
            }
            if go_right {
                consider(by_x[right], &mut nearest);
                right += 1;
            }
        }
        let mut centre = Vector3::zeros();
        let mut spread = Vector3::zeros();
        for c in 0..3 {
            for (slot, &(_, j)) in component.iter_mut().zip(&nearest) {
                *slot = vectors[j].1[c];
            }
            centre[c] = median(&mut component);
            for (slot, &(_, j)) in component.iter_mut().zip(&nearest) {
                *slot = (vectors[j].1[c] - centre[c]).abs();
            }
            spread[c] = median(&mut component);
        }
        let speed = centre.norm();
        let velocity = vectors[i].1;
        let coherent = spread.iter().all(|&s| s < test.coherence * speed);
        outliers[i] = coherent
            && (0..3).any(|c| {
                (velocity[c] - centre[c]).abs()
                    > test.threshold * (spread[c] + test.noise_fraction * speed)
            });
    }
    outliers
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
    /// a deterministic pattern in -1..1 per component.
    fn grid_field(wobble: f64) -> Vec<(Point3<f64>, Vector3<f64>)> {
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
                    + wobble * Vector3::new(pattern(i, 0), pattern(i, 1), pattern(i, 2));
                (p, v)
            })
            .collect()
    }

    #[test]
    fn a_vector_its_neighbours_do_not_share_is_an_outlier() {
        // Noise of 0.5 % of the speed, and one vector 10 % off in w (a wrong stereo pair).
        let mut field = grid_field(0.007);
        assert!(neighbour_outliers(&field, &TEST).iter().all(|&o| !o));
        field[20].1.z -= 0.14;
        let flagged: Vec<usize> = neighbour_outliers(&field, &TEST)
            .iter()
            .enumerate()
            .filter_map(|(i, &o)| o.then_some(i))
            .collect();
        assert_eq!(flagged, [20]);
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
    fn where_neighbours_disagree_nothing_is_judged() {
        // Neighbours 30 % apart: the flow is not resolved at this spacing, so a vector 40 %
        // off its neighbours' median is not called an outlier.
        let mut field = grid_field(0.3);
        field[20].1.z -= 0.4;
        assert!(neighbour_outliers(&field, &TEST).iter().all(|&o| !o));
    }
}
