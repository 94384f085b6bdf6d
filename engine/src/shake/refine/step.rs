//! One Gauss-Newton step of one particle's fit: its floor (a level and its slopes across its
//! box), its centre and amplitude, and its radius and edge where they are free, against its
//! pixels with its neighbours' modelled images taken out. Every fit of the shake is made of
//! these steps: a lone particle's shape, learnt, and each particle of a sweep in turn.

use nalgebra::{SMatrix, SVector};

use super::{logistic_table, Floor, Free, InFit, Member, FLOOR_TERMS, RADIUS_RANGE};

/// A step's unknowns at most: the floor's, then x, y, amplitude, radius and edge.
const TERMS: usize = FLOOR_TERMS + 5;

/// A particle and the floor under it, as a fit leaves them.
#[derive(Debug, Clone, Copy)]
pub(super) struct Fit {
    pub(super) member: Member,
    pub(super) floor: Floor,
    /// The floor's block of the normal equations (its terms are the pixels' positions about
    /// the floor's centre, the same at every step): summed once, in pixel order.
    floor_block: [[f64; FLOOR_TERMS]; FLOOR_TERMS],
}

/// What one step did: how far it moved the centre (pixels, along x plus along y), the sum of
/// squared residuals the fit had before it, and the standard error of the centre those
/// residuals give (pixels, x and y together).
pub(super) struct Stepped {
    pub(super) moved_px: f64,
    pub(super) cost: f64,
    pub(super) centre_sigma_px: f64,
}

impl Fit {
    /// `member` on a flat floor under `samples` (their darkest level), the fit that steps
    /// against those samples start from.
    pub(super) fn new(member: Member, samples: &[(f64, f64, f64)]) -> Self {
        let floor = Floor::under(samples);
        let mut floor_block = [[0.0; FLOOR_TERMS]; FLOOR_TERMS];
        for &(x, y, _) in samples {
            let j = [1.0, x - floor.centre.0, y - floor.centre.1];
            for (a, &ja) in j.iter().enumerate() {
                for (b, &jb) in j[..=a].iter().enumerate() {
                    floor_block[a][b] += ja * jb;
                }
            }
        }
        Self {
            member,
            floor,
            floor_block,
        }
    }

    /// One step against `samples` (x, y, grey level) with `others`' light taken out, the
    /// radius and edge free as `free` says (a radius among neighbours kept within
    /// [`RADIUS_RANGE`] of `seed_radius_px`); `None` where the pixels do not pin the unknowns
    /// (too few of them, or a singular system).
    pub(super) fn step(
        &mut self,
        samples: &[(f64, f64, f64)],
        others: &[InFit],
        (free, seed_radius_px): (Free, f64),
    ) -> Option<Stepped> {
        let (step, cost, centre_sigma_px) = match free {
            Free::Shape => self.solve::<{ FLOOR_TERMS + 5 }>(samples, others, Free::Shape)?,
            Free::Radius => self.solve::<{ FLOOR_TERMS + 4 }>(samples, others, Free::Radius)?,
        };
        if step.iter().any(|v| !v.is_finite()) {
            return None;
        }
        self.floor.level += step[0];
        self.floor.slope.0 += step[1];
        self.floor.slope.1 += step[2];
        let m = &mut self.member;
        m.at.x += step[3];
        m.at.y += step[4];
        m.shape.amplitude += step[5];
        match free {
            Free::Shape => {
                m.shape.radius_px = (m.shape.radius_px + step[6]).max(0.0);
                m.shape.edge_px = (m.shape.edge_px + step[7]).clamp(0.05, 5.0);
            }
            Free::Radius => {
                let (low, high) = RADIUS_RANGE;
                m.shape.radius_px = (m.shape.radius_px + step[6])
                    .clamp(low * seed_radius_px, high * seed_radius_px);
            }
        }
        Some(Stepped {
            moved_px: step[3].abs() + step[4].abs(),
            cost,
            centre_sigma_px,
        })
    }

    /// The step (floor, x, y, amplitude, radius, then edge where `N` has room for it) and the
    /// sum of squared residuals over `samples` before it; `N` is the unknowns' count, so that
    /// the sums are no larger than the fit needs. Inlined where `free` is known, so that the
    /// pixel loop is made for it.
    #[inline(always)]
    fn solve<const N: usize>(
        &self,
        samples: &[(f64, f64, f64)],
        others: &[InFit],
        free: Free,
    ) -> Option<([f64; TERMS], f64, f64)> {
        if samples.len() <= 2 * N {
            return None;
        }
        let (jtj, jtr, cost) = self.normal_equations::<N>(samples, others, free);
        let jtj = SMatrix::<f64, N, N>::from_fn(|a, b| jtj[a.max(b)][a.min(b)]);
        let jtr = SVector::<f64, N>::from(jtr);
        let factor = jtj.cholesky()?;
        let solved = factor.solve(&jtr);
        let mut step = [0.0; TERMS];
        step[..N].copy_from_slice(solved.as_slice());
        // The centre's variances are the diagonal of the inverse normal matrix (the squared
        // norms of the inverse factor's columns) times the residual variance.
        let l = factor.l_dirty();
        let residual_variance = cost / (samples.len() - N) as f64;
        let centre_sigma_px = (residual_variance
            * (inverse_diagonal(l, FLOOR_TERMS) + inverse_diagonal(l, FLOOR_TERMS + 1)))
        .sqrt();
        Some((step, cost, centre_sigma_px))
    }

    /// The normal equations of a step over `samples` (the radius and edge's terms as `free`
    /// says), each pixel's Jacobian row added in turn, and the sum of the squared
    /// residuals before the step. Of the floor's block only the lower triangle is kept, summed
    /// once ([`Fit::new`]); the particle's rows are summed whole, as whole rows vectorise (their
    /// part above the diagonal is not read). A pixel beyond the particle's reach has only the
    /// floor's terms, and adds to the right-hand side only. The pixels go in chunks, each in
    /// three passes (the neighbours' light, the particle's own terms, the sums): a pixel's
    /// square root, table lookups and division are a long chain, and a short loop of pixels
    /// that do not depend on each other lets the processor run many such chains at once.
    #[inline(always)]
    fn normal_equations<const N: usize>(
        &self,
        samples: &[(f64, f64, f64)],
        others: &[InFit],
        free: Free,
    ) -> ([[f64; N]; N], [f64; N], f64) {
        let mut jtj = [[0.0; N]; N];
        for (row, block) in jtj.iter_mut().zip(&self.floor_block) {
            row[..FLOOR_TERMS].copy_from_slice(block);
        }
        let mut jtr = [0.0; N];
        let mut cost = 0.0;
        let (table, own) = (logistic_table(), InFit::new(&self.member));
        let mut terms = [PixelTerms::default(); CHUNK];
        for chunk in samples.chunks(CHUNK) {
            let terms = &mut terms[..chunk.len()];
            self.pixel_terms(chunk, (table, &own), others, free, terms);
            for t in terms.iter() {
                cost += t.residual * t.residual;
                let Some(values) = t.values else {
                    for (r, j) in jtr.iter_mut().zip([1.0, t.fx, t.fy]) {
                        *r += t.residual * j;
                    }
                    continue;
                };
                let j: [f64; N] = std::array::from_fn(|a| match a {
                    0 => 1.0,
                    1 => t.fx,
                    2 => t.fy,
                    _ => values[a - FLOOR_TERMS],
                });
                for (r, &ja) in jtr.iter_mut().zip(&j) {
                    *r += t.residual * ja;
                }
                for (row, &ja) in jtj[FLOOR_TERMS..].iter_mut().zip(&j[FLOOR_TERMS..]) {
                    for (m, &jb) in row.iter_mut().zip(&j) {
                        *m += ja * jb;
                    }
                }
            }
        }
        (jtj, jtr, cost)
    }

    /// Each pixel's terms of a chunk (`terms`, index for index with `chunk`): its position about
    /// the floor's centre, its residual under the model (the floor, `others`' light and the
    /// particle's, `own`, looked up in `table`), and where the particle's light reaches it, its
    /// Jacobian values.
    #[inline(always)]
    fn pixel_terms(
        &self,
        chunk: &[(f64, f64, f64)],
        (table, own): (&[f64], &InFit),
        others: &[InFit],
        free: Free,
        terms: &mut [PixelTerms],
    ) {
        let floor = &self.floor;
        let mut light = [0.0; CHUNK];
        for o in others {
            for (l, &(x, y, _)) in light.iter_mut().zip(chunk) {
                *l += o.light(table, (x, y));
            }
        }
        for ((t, &(x, y, v)), &light) in terms.iter_mut().zip(chunk).zip(&light) {
            let (fx, fy) = (x - floor.centre.0, y - floor.centre.1);
            let model = floor.level + floor.slope.0 * fx + floor.slope.1 * fy + light;
            *t = match own.at(table, (x, y)) {
                None => PixelTerms {
                    fx,
                    fy,
                    residual: v - model,
                    values: None,
                },
                Some(at) => PixelTerms {
                    fx,
                    fy,
                    residual: v - (model + own.amplitude * at[4]),
                    values: Some(own.values(at, free)),
                },
            };
        }
    }
}

/// Pixels a step evaluates in one go ([`Fit::normal_equations`]).
const CHUNK: usize = 32;

/// One pixel's part in a step: its position about the floor's centre, its residual before the
/// step, and where the particle's light reaches it, the particle's Jacobian values (x, y,
/// amplitude, radius, edge).
#[derive(Debug, Clone, Copy, Default)]
struct PixelTerms {
    fx: f64,
    fy: f64,
    residual: f64,
    values: Option<[f64; 5]>,
}

/// Element `k` of the diagonal of `(L Lt)^-1`, `l` holding the Cholesky factor `L` in its lower
/// triangle: the squared norm of column `k` of `L^-1`, by forward substitution from row `k`
/// (the rows above are zero). Every step asks it twice: written out, it costs a few dozen
/// multiplications instead of two general triangular solves.
fn inverse_diagonal<const N: usize>(l: &SMatrix<f64, N, N>, k: usize) -> f64 {
    let mut z = [0.0; N];
    z[k] = 1.0 / l[(k, k)];
    for i in k + 1..N {
        let sum: f64 = (k..i).map(|j| l[(i, j)] * z[j]).sum();
        z[i] = -sum / l[(i, i)];
    }
    z[k..].iter().map(|v| v * v).sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_inverse_diagonal_is_that_of_the_inverted_matrix() {
        // A symmetric positive definite matrix: A^T A plus the identity, of a fixed A.
        let a = SMatrix::<f64, 7, 7>::from_fn(|r, c| ((3 * r + 5 * c) % 7) as f64 - 2.5);
        let m = a.transpose() * a + SMatrix::<f64, 7, 7>::identity();
        let inverse = m.try_inverse().expect("invertible");
        let factor = m.cholesky().expect("positive definite");
        for k in 0..7 {
            let from_factor = inverse_diagonal(factor.l_dirty(), k);
            assert!(
                (from_factor - inverse[(k, k)]).abs() < 1e-12 * inverse[(k, k)].abs(),
                "{k}: {from_factor} against {}",
                inverse[(k, k)]
            );
        }
    }
}
