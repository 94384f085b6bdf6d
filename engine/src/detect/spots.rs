//! Overlapping particle images separated by fitting: a region holding several particles is
//! modelled as a sum of round spots (Gaussian to flat-topped, see [`Spot`]) on a constant floor
//! and fitted by Levenberg-Marquardt least squares. Unlike cutting the region's pixels between the particles,
//! the fit lets each spot's tail run under its neighbour, so the centres are not pulled together.

use nalgebra::{SMatrix, SVector};

/// One spot: `amplitude * exp(-(r^2 / (2 sigma^2))^flatness)` around (x, y), pixels and grey
/// levels. Flatness 1 is a Gaussian (a small particle blurred by optics); larger values give the
/// flat top of a disc image wider than the blur.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Spot {
    /// Centre, pixels.
    pub x: f64,
    /// See `x`.
    pub y: f64,
    /// Peak height above the floor, grey levels.
    pub amplitude: f64,
    /// Width, pixels.
    pub sigma: f64,
    /// 1 for a Gaussian, larger for a flatter top.
    pub flatness: f64,
}

/// Parameters per spot in the fit vector, after the floor.
const PER_SPOT: usize = 5;
const MAX_FLATNESS: f64 = 4.0;
const MAX_ITERATIONS: usize = 15;
/// A step that moves no centre by more than this ends the fit: below the 0.01 px that
/// centroids are good to, so smaller steps only cost time.
const CONVERGED_STEP_PX: f64 = 5e-3;

/// Fits `seeds.len()` spots plus a constant floor to `samples` (x, y, value) starting from the
/// seeds. `None` when the fit does not converge, or a step takes a spot where its particle
/// cannot be (gone flat or negative, too narrow or wide, or far from its seed); spots that
/// merged into each other are judged by [`SpotFit::is_trustworthy`].
pub fn fit_spots(samples: &[(f64, f64, f64)], seeds: &[Spot]) -> Option<SpotFit> {
    // Fixed sizes let the compiler unroll the per-pixel work; regions of more than four
    // particles are not fitted.
    let (params, cost, position_sigma_px) = match seeds.len() {
        1 => levenberg_marquardt::<6>(samples, seeds)?,
        2 => levenberg_marquardt::<11>(samples, seeds)?,
        3 => levenberg_marquardt::<16>(samples, seeds)?,
        4 => levenberg_marquardt::<21>(samples, seeds)?,
        _ => return None,
    };
    let spots: Vec<Spot> = (0..seeds.len()).map(|k| spot_in(&params, k)).collect();
    let rms_residual = (cost / samples.len() as f64).sqrt();
    Some(SpotFit {
        spots,
        rms_residual,
        position_sigma_px,
    })
}

/// Fitted spots and how far the samples stray from them.
#[derive(Debug, Clone, PartialEq)]
pub struct SpotFit {
    /// The fitted spots, in seed order.
    pub spots: Vec<Spot>,
    /// Root-mean-square difference between the samples and the fitted model, grey levels.
    pub rms_residual: f64,
    /// Per spot, the standard deviation of its centre (radial, both axes together) that the
    /// residuals imply through the fit's covariance, pixels.
    pub position_sigma_px: Vec<f64>,
}

/// A fit whose residual exceeds this fraction of its weakest spot's amplitude has missed
/// something (a third particle, a spot that is not round): such fits place centres half a pixel
/// or more from the truth.
const MAX_RELATIVE_RESIDUAL: f64 = 0.05;

/// Spots closer than this multiple of the sum of their half-widths (at half maximum) share so
/// much light that their centres trade off against each other: their vectors' out-of-plane
/// errors are several times the others'.
const MIN_SEPARATION_IN_HALF_WIDTHS: f64 = 1.0;

/// See [`SpotFit::is_measured`]: a looser bound admits centres whose errors cost the
/// out-of-plane velocity more than their vectors add.
const MAX_POSITION_SIGMA_PX: f64 = 0.03;

impl SpotFit {
    /// Whether the fitted centres are good for measuring: the model explains the pixels and the
    /// spots are far enough apart that each centre is set by its own light.
    pub fn is_trustworthy(&self) -> bool {
        let apart = (0..self.spots.len()).all(|k| self.is_apart(k, MIN_SEPARATION_IN_HALF_WIDTHS));
        self.explains_the_pixels() && apart
    }

    /// Whether spot `k` lies more than `half_widths` times the sum of their half widths from
    /// every other spot.
    pub fn is_apart(&self, k: usize, half_widths: f64) -> bool {
        let Some(a) = self.spots.get(k) else {
            return false;
        };
        self.spots.iter().enumerate().all(|(j, b)| {
            j == k || (a.x - b.x).hypot(a.y - b.y) > half_widths * (a.half_width() + b.half_width())
        })
    }

    /// Whether spot `k`'s centre is good for measuring by its own uncertainty: the model
    /// explains the pixels and the residuals leave the centre within `MAX_POSITION_SIGMA_PX`.
    /// For spots seeded where tracks expect them: centres the pixels pin down this well are
    /// as close to the truth as trustworthy fits give, however close the spots.
    pub fn is_measured(&self, k: usize) -> bool {
        self.explains_the_pixels()
            && self
                .position_sigma_px
                .get(k)
                .is_some_and(|&s| s < MAX_POSITION_SIGMA_PX)
    }

    /// Whether the model leaves no more unexplained light than noise: no particle missed, none
    /// of an odd shape.
    pub fn explains_the_pixels(&self) -> bool {
        let weakest = self
            .spots
            .iter()
            .map(|s| s.amplitude)
            .fold(f64::MAX, f64::min);
        self.rms_residual < MAX_RELATIVE_RESIDUAL * weakest
    }
}

impl Spot {
    /// Whether a fitted spot may still be the particle it was seeded as (`seed`): brighter
    /// than the floor, neither collapsed nor spread far beyond the seed's width, and near
    /// where it was seeded.
    fn is_plausible(&self, seed: &Spot) -> bool {
        self.amplitude > 0.0
            && self.sigma > 0.3
            && self.sigma < 3.0 * seed.sigma
            && (self.x - seed.x).hypot(self.y - seed.y) < 2.0 * seed.sigma
    }

    /// Distance from the centre at which the spot falls to half its amplitude, pixels.
    pub fn half_width(&self) -> f64 {
        self.sigma * std::f64::consts::SQRT_2 * std::f64::consts::LN_2.powf(0.5 / self.flatness)
    }
}

/// The floor and each spot's parameters, and the sum of squared residuals, once converged.
fn levenberg_marquardt<const N: usize>(
    samples: &[(f64, f64, f64)],
    seeds: &[Spot],
) -> Option<(Vec<f64>, f64, Vec<f64>)> {
    if samples.len() <= N {
        return None;
    }
    let floor = samples
        .iter()
        .map(|s| s.2)
        .fold(f64::MAX, f64::min)
        .max(0.0);
    let mut params = SVector::<f64, N>::from_fn(|i, _| {
        if i == 0 {
            return floor;
        }
        let s = &seeds[(i - 1) / PER_SPOT];
        [s.x, s.y, s.amplitude, s.sigma, s.flatness][(i - 1) % PER_SPOT]
    });
    let mut current = evaluate(samples, &params);
    let mut damping = 1e-3;
    for _ in 0..MAX_ITERATIONS {
        let mut damped = current.normal;
        for i in 0..N {
            damped[(i, i)] += damping * current.normal[(i, i)].max(1e-12);
        }
        let Some(step) = damped.cholesky().map(|c| c.solve(&current.gradient)) else {
            damping *= 10.0;
            continue;
        };
        let mut trial = params + step;
        for k in 0..seeds.len() {
            let f = &mut trial[5 + PER_SPOT * k];
            *f = f.clamp(1.0, MAX_FLATNESS);
        }
        // One pass gives the trial's cost and, should it be taken, the next normal equations.
        let next = evaluate(samples, &trial);
        if next.cost.is_finite() && next.cost <= current.cost {
            let moved = (0..seeds.len())
                .map(|k| step[1 + PER_SPOT * k].abs() + step[2 + PER_SPOT * k].abs())
                .fold(0.0, f64::max);
            params = trial;
            current = next;
            damping = (damping / 3.0).max(1e-9);
            // A spot taken where its particle cannot be (most often by the first step) ends
            // the fit as it would end after every step left: such fits seldom come back, and
            // they were most of the steps fitting three or four spots took.
            let implausible = |k: usize| !spot_in(params.as_slice(), k).is_plausible(&seeds[k]);
            if (0..seeds.len()).any(implausible) {
                return None;
            }
            if moved < CONVERGED_STEP_PX {
                let inverse = current.normal.try_inverse()?;
                let variance = current.cost / (samples.len() - N) as f64;
                let position_sigma_px = (0..seeds.len())
                    .map(|k| {
                        let (x, y) = (1 + PER_SPOT * k, 2 + PER_SPOT * k);
                        (variance * (inverse[(x, x)] + inverse[(y, y)]))
                            .max(0.0)
                            .sqrt()
                    })
                    .collect();
                return Some((
                    params.iter().copied().collect(),
                    current.cost,
                    position_sigma_px,
                ));
            }
        } else {
            damping *= 4.0;
            if damping > 1e8 {
                return None;
            }
        }
    }
    None
}

/// Spot `k` of a fit's parameters (the floor first, then [`PER_SPOT`] values per spot).
fn spot_in(params: &[f64], k: usize) -> Spot {
    let at = 1 + PER_SPOT * k;
    Spot {
        x: params[at],
        y: params[at + 1],
        amplitude: params[at + 2],
        sigma: params[at + 3].abs(),
        flatness: params[at + 4],
    }
}

/// The sum of squared residuals at some parameters, with the Gauss-Newton normal equations
/// there (`J^T J` and `J^T r`).
struct Evaluation<const N: usize> {
    cost: f64,
    normal: SMatrix<f64, N, N>,
    gradient: SVector<f64, N>,
}

/// Beyond this `q = r^2 / (2 sigma^2)` a spot contributes under `exp(-20)` of its amplitude.
const NEGLIGIBLE_Q: f64 = 20.0;

fn evaluate<const N: usize>(
    samples: &[(f64, f64, f64)],
    params: &SVector<f64, N>,
) -> Evaluation<N> {
    let spots = (N - 1) / PER_SPOT;
    let mut normal = SMatrix::<f64, N, N>::zeros();
    let mut gradient = SVector::<f64, N>::zeros();
    let mut cost = 0.0;
    let mut row = [0.0; N];
    row[0] = 1.0;
    for &(x, y, v) in samples {
        let mut value = params[0];
        for k in 0..spots {
            let base = 1 + PER_SPOT * k;
            let (cx, cy, a, s, p) = (
                params[base],
                params[base + 1],
                params[base + 2],
                params[base + 3],
                params[base + 4],
            );
            let (dx, dy) = (x - cx, y - cy);
            let s2 = s * s;
            let q = (dx * dx + dy * dy) / (2.0 * s2);
            let derivatives = if q > NEGLIGIBLE_Q {
                [0.0; PER_SPOT]
            } else if q > 0.0 {
                // q^p through one logarithm, which the flatness derivative needs anyway; in
                // single precision, twice as fast and far finer than the pixels' noise.
                let ln_q = (q as f32).ln();
                let qp = f64::from((p as f32 * ln_q).exp());
                let g = f64::from((-qp as f32).exp());
                let ln_q = f64::from(ln_q);
                let agp = a * g * p * qp / q;
                value += a * g;
                [
                    agp * dx / s2,
                    agp * dy / s2,
                    g,
                    agp * 2.0 * q / s,
                    -a * g * qp * ln_q,
                ]
            } else {
                // At the centre: g = 1 and every derivative but the amplitude's vanishes (p >= 1).
                value += a;
                [0.0, 0.0, 1.0, 0.0, 0.0]
            };
            row[base..base + PER_SPOT].copy_from_slice(&derivatives);
        }
        let residual = v - value;
        cost += residual * residual;
        let jacobian_row = SVector::<f64, N>::from(row);
        gradient += jacobian_row * residual;
        normal.syger(1.0, &jacobian_row, &jacobian_row, 1.0);
    }
    // syger writes the lower triangle only.
    normal.fill_upper_triangle_with_lower_triangle();
    Evaluation {
        cost,
        normal,
        gradient,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spot(x: f64, y: f64, amplitude: f64, sigma: f64, flatness: f64) -> Spot {
        Spot {
            x,
            y,
            amplitude,
            sigma,
            flatness,
        }
    }

    /// The model itself, sampled on a square of pixels.
    fn render(spots: &[Spot], floor: f64, size: usize) -> Vec<(f64, f64, f64)> {
        (0..size * size)
            .map(|i| {
                let (x, y) = ((i % size) as f64, (i / size) as f64);
                let v: f64 = spots
                    .iter()
                    .map(|s| {
                        let q = ((x - s.x).powi(2) + (y - s.y).powi(2)) / (2.0 * s.sigma * s.sigma);
                        s.amplitude * (-q.powf(s.flatness)).exp()
                    })
                    .sum();
                (x, y, floor + v)
            })
            .collect()
    }

    /// Seeds as a 2-means cut gives them: pulled towards each other by most of a pixel.
    fn cut_seeds(truth: &[Spot; 2]) -> [Spot; 2] {
        [
            spot(truth[0].x + 0.7, truth[0].y + 0.2, 100.0, 2.2, 1.2),
            spot(truth[1].x - 0.8, truth[1].y - 0.2, 100.0, 2.2, 1.2),
        ]
    }

    #[test]
    fn overlapping_spots_are_recovered_where_a_cut_would_pull_them_together() {
        let gaussians = [
            spot(9.3, 10.2, 120.0, 1.8, 1.0),
            spot(13.6, 11.1, 80.0, 1.6, 1.0),
        ];
        // Flat-topped, as a disc wider than the blur images.
        let discs = [
            spot(9.1, 10.3, 150.0, 2.6, 2.5),
            spot(17.0, 11.0, 150.0, 2.6, 2.5),
        ];
        for truth in [gaussians, discs] {
            let fitted = fit_spots(&render(&truth, 3.0, 26), &cut_seeds(&truth)).expect("fit");
            for (f, t) in fitted.spots.iter().zip(&truth) {
                assert!((f.x - t.x).hypot(f.y - t.y) < 1e-2, "{f:?} vs {t:?}");
            }
            assert!(fitted.is_trustworthy(), "{fitted:?}");
        }
    }

    #[test]
    fn a_centre_is_measured_when_the_pixels_pin_it_down() {
        // Noise of one grey level: apart, the centres are pinned to a few hundredths of a pixel
        // and say so; overlapping at under a half-width each, they trade light and the fit's
        // covariance says that too.
        let noisy = |truth: &[Spot]| {
            let mut rng = crate::synth::Rng::new(3);
            let mut samples = render(truth, 3.0, 26);
            for s in &mut samples {
                s.2 += rng.normal();
            }
            samples
        };
        let apart = [
            spot(9.3, 10.2, 120.0, 1.5, 1.0),
            spot(15.6, 11.1, 100.0, 1.5, 1.0),
        ];
        let fitted = fit_spots(&noisy(&apart), &cut_seeds(&apart)).expect("fit");
        assert!(
            (0..2).all(|k| fitted.is_measured(k)) && fitted.position_sigma_px[0] > 0.001,
            "{fitted:?}"
        );
        let merged = [
            spot(11.0, 10.2, 120.0, 1.5, 1.0),
            spot(12.2, 10.6, 100.0, 1.5, 1.0),
        ];
        let fitted = fit_spots(&noisy(&merged), &cut_seeds(&merged)).expect("fit");
        assert!((0..2).all(|k| !fitted.is_measured(k)), "{fitted:?}");
    }

    #[test]
    fn spots_closer_than_their_half_widths_are_fitted_but_not_trusted() {
        // 3.4 px apart, half-widths 2.1 and 1.9 px.
        let truth = [
            spot(9.3, 10.2, 120.0, 1.8, 1.0),
            spot(12.6, 11.1, 80.0, 1.6, 1.0),
        ];
        let fitted = fit_spots(&render(&truth, 3.0, 24), &cut_seeds(&truth)).expect("fit");
        for (f, t) in fitted.spots.iter().zip(&truth) {
            assert!((f.x - t.x).hypot(f.y - t.y) < 1e-2, "{f:?} vs {t:?}");
        }
        assert!(!fitted.is_trustworthy(), "{fitted:?}");
    }

    #[test]
    fn one_spot_is_not_fitted_as_two() {
        let samples = render(&[spot(10.0, 10.0, 100.0, 2.0, 1.0)], 0.0, 20);
        let seeds = [
            spot(9.0, 10.0, 60.0, 2.0, 1.0),
            spot(11.0, 10.0, 60.0, 2.0, 1.0),
        ];
        assert!(fit_spots(&samples, &seeds).is_none_or(|f| !f.is_trustworthy()));
    }
}
