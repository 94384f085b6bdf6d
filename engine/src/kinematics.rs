//! Stage 5: velocity by moving least squares (method section 5.5, eqs. 13-15).
//!
//! `q(t) = a + b (t - t_n) + c (t - t_n)^2` is fitted to the positions of a window of frames; the
//! velocity at `t_n` is `b` and the smoothed position `a`. The method centres the window on `t_n`
//! (`+-M` frames). Times come from the frames' timestamps, so jittered frame intervals are honoured.

use crate::spatial::median;
use nalgebra::{DMatrix, Point3, Vector3};

/// A fitted path evaluated at one time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MotionFit {
    /// Fitted position at the evaluation time (a).
    pub position: Point3<f64>,
    /// Fitted velocity at the evaluation time (b), units per second.
    pub velocity: Vector3<f64>,
    /// Root-mean-square distance of the samples from the fitted curve.
    pub rms_residual: f64,
    /// What the samples say about this fit's error.
    pub error: FitError,
}

impl MotionFit {
    /// `None` when a degenerate fit produced non-finite numbers.
    fn finite(self) -> Option<Self> {
        self.position
            .coords
            .iter()
            .chain(self.velocity.iter())
            .all(|v| v.is_finite())
            .then_some(self)
    }
}

/// A fit's error budget per component (x, y, z): the sample noise its residuals show, what a
/// sample noise does to the fitted velocity and position (the fit is linear in the samples, so
/// their variances are the noise variance times a gain), and the squared bias expected from
/// the path's terms the fit's order does not reach.
///
/// The noise estimate rests on few residuals (a window of 11 samples leaves 7 degrees of
/// freedom to a cubic), so a caller that knows a typical noise for the scene can pool it in
/// (`sigmas`) rather than let one window's luck decide.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FitError {
    pub noise_variance: Vector3<f64>,
    /// Degrees of freedom behind `noise_variance` (0: the samples say nothing about it).
    pub noise_dof: f64,
    pub velocity_gain: Vector3<f64>,
    pub position_gain: Vector3<f64>,
    /// Squared biases stated from path terms other than the cubic one.
    pub velocity_bias_sq: Vector3<f64>,
    pub position_bias_sq: Vector3<f64>,
    /// The path's cubic term as the window's cubic fit estimates it (0 without one), and its
    /// variance per unit of sample noise variance.
    pub cubic_term: Vector3<f64>,
    pub cubic_term_gain: f64,
    /// How much of the cubic term the chosen fit's velocity and position take in (0 for a
    /// cubic).
    pub velocity_cubic_absorption: Vector3<f64>,
    pub position_cubic_absorption: Vector3<f64>,
    /// Squared velocity and position bias per unit of misfit: residual energy beyond what the
    /// sample noise explains, read as the path's fifth-order (velocity) and fourth-order
    /// (position) terms, the lowest ones the cubic leaves in its residuals.
    pub velocity_misfit_gain: Vector3<f64>,
    pub position_misfit_gain: Vector3<f64>,
}

/// What a scene's other tracks say about any one window: a typical sample noise variance
/// per component with the degrees of freedom it is worth against a window's own estimate, and
/// per component where the scene's paths plainly curve, the spread of their cubic term across
/// the scene's windows (its variance, noise taken out).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScenePrior {
    pub noise_variance: Vector3<f64>,
    pub noise_dof: f64,
    pub cubic_term_spread: [Option<f64>; 3],
}

impl FitError {
    /// A fit's budget from its sample noise alone (per component, with its degrees of freedom)
    /// and its velocity and position gains: no path term stated.
    fn from_noise(
        noise_variance: Vector3<f64>,
        noise_dof: f64,
        velocity_gain: Vector3<f64>,
        position_gain: Vector3<f64>,
    ) -> Self {
        Self {
            noise_variance,
            noise_dof,
            velocity_gain,
            position_gain,
            velocity_bias_sq: Vector3::zeros(),
            position_bias_sq: Vector3::zeros(),
            cubic_term: Vector3::zeros(),
            cubic_term_gain: 0.0,
            velocity_cubic_absorption: Vector3::zeros(),
            position_cubic_absorption: Vector3::zeros(),
            velocity_misfit_gain: Vector3::zeros(),
            position_misfit_gain: Vector3::zeros(),
        }
    }

    /// The window's own sample noise variance pooled with the scene's, if known.
    pub fn pooled_noise(&self, prior: Option<&ScenePrior>) -> Vector3<f64> {
        match prior {
            Some(p) if p.noise_dof > 0.0 => {
                (self.noise_variance * self.noise_dof + p.noise_variance * p.noise_dof)
                    / (self.noise_dof + p.noise_dof)
            }
            _ => self.noise_variance,
        }
    }

    /// The cubic term's estimate variance per component at sample noise `noise`.
    pub fn cubic_term_variance(&self, noise: &Vector3<f64>) -> Vector3<f64> {
        noise * self.cubic_term_gain
    }

    /// 1-sigma velocity and position errors per component. With a scene prior, the window's
    /// noise estimate is pooled with the scene's, residual energy beyond the scene's noise
    /// counts as the path's higher-order terms, and the cubic term is taken as the scene's
    /// spread says it is likely to be given the window's estimate: a fit chosen because its
    /// window's cubic term looked small is not thereby taken at its word.
    pub fn sigmas(&self, prior: Option<&ScenePrior>) -> (Vector3<f64>, Vector3<f64>) {
        let noise = self.pooled_noise(prior);
        let cubic_variance = self.cubic_term_variance(&noise);
        // Residual energy beyond what the scene's noise explains: the path's higher-order
        // terms, taken whole (fourth order and up, whatever their phase) as an envelope of
        // the fifth-order term's size (without it turbulence's u and v lay 83.7 and 85.1 %
        // within 2 sigma, 94.4 and 95.6 % with). Counted only where the window's noise
        // estimate is plainly above the scene's (a chi-square of 7 degrees of freedom passes
        // twice its mean by chance 5 % of the time): counting every chance excess made the
        // uniform flow's median sigmas five times larger (u 1.46 against 0.28 mm/s).
        const SIGNIFICANT_EXCESS: f64 = 2.0;
        let misfit = match prior {
            Some(p) if p.noise_dof > 0.0 => Vector3::from_fn(|c, _| {
                let (window, scene) = (self.noise_variance[c], p.noise_variance[c]);
                if window > SIGNIFICANT_EXCESS * scene {
                    (window - scene) * self.noise_dof
                } else {
                    0.0
                }
            }),
            _ => Vector3::zeros(),
        };
        let cubic_sq = Vector3::from_fn(|c, _| {
            let (d, v) = (self.cubic_term[c], cubic_variance[c]);
            match prior.and_then(|p| p.cubic_term_spread[c]) {
                // The posterior mean of d^2 under a zero-mean Gaussian prior of variance tau2.
                Some(tau2) if tau2 > 0.0 => {
                    let shrunk = d * tau2 / (tau2 + v);
                    shrunk * shrunk + tau2 * v / (tau2 + v)
                }
                // Otherwise the window's own unbiased estimate of d^2.
                _ => (d * d - v).max(0.0),
            }
        });
        let velocity = Vector3::from_fn(|c, _| {
            (self.velocity_gain[c] * noise[c]
                + self.velocity_bias_sq[c]
                + self.velocity_cubic_absorption[c].powi(2) * cubic_sq[c]
                + self.velocity_misfit_gain[c] * misfit[c])
                .sqrt()
        });
        let position = Vector3::from_fn(|c, _| {
            (self.position_gain[c] * noise[c]
                + self.position_bias_sq[c]
                + self.position_cubic_absorption[c].powi(2) * cubic_sq[c]
                + self.position_misfit_gain[c] * misfit[c])
                .sqrt()
        });
        (velocity, position)
    }
}

/// Least-squares quadratic through `samples` (time in seconds, position), evaluated at `t_eval_s`.
/// `None` with fewer than three samples or when the times cannot support a quadratic.
pub fn fit_quadratic(samples: &[(f64, Point3<f64>)], t_eval_s: f64) -> Option<MotionFit> {
    PolynomialFit::new(samples, t_eval_s, 2)?.motion().finite()
}

/// A least-squares polynomial `sum c_k tau^k` with `tau = (t - t_eval) / scale_s`, with what the
/// adaptive choice needs to predict its errors.
struct PolynomialFit {
    /// Row k: the coefficient of `tau^k` for x, y and z.
    coefficients: DMatrix<f64>,
    /// `(X^T X)^-1` in scaled time: a coefficient's variance is this diagonal times sigma^2.
    inverse_normal: DMatrix<f64>,
    /// X: row r holds `tau_r^k` for each term k.
    design: DMatrix<f64>,
    /// Row r: sample r's offset from the fitted curve, x, y and z.
    residuals: DMatrix<f64>,
    /// Per component, sum of squared residuals.
    squared_residuals: Vector3<f64>,
    samples: usize,
    scale_s: f64,
}

impl PolynomialFit {
    fn new(samples: &[(f64, Point3<f64>)], t_eval_s: f64, order: usize) -> Option<Self> {
        let terms = order + 1;
        if samples.len() < terms {
            return None;
        }
        let scale_s = samples
            .iter()
            .map(|(t, _)| (t - t_eval_s).abs())
            .fold(0.0, f64::max);
        if scale_s.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
            return None;
        }
        let design = DMatrix::from_fn(samples.len(), terms, |r, k| {
            ((samples[r].0 - t_eval_s) / scale_s).powi(k as i32)
        });
        let positions = DMatrix::from_fn(samples.len(), 3, |r, c| samples[r].1[c]);
        let inverse_normal = (design.transpose() * &design).try_inverse()?;
        let coefficients = &inverse_normal * design.transpose() * &positions;
        let residuals = positions - &design * &coefficients;
        let squared_residuals = Vector3::from_fn(|c, _| residuals.column(c).norm_squared());
        coefficients.iter().all(|v| v.is_finite()).then_some(Self {
            coefficients,
            inverse_normal,
            design,
            residuals,
            squared_residuals,
            samples: samples.len(),
            scale_s,
        })
    }

    fn position(&self, c: usize) -> f64 {
        self.coefficients[(0, c)]
    }

    fn velocity(&self, c: usize) -> f64 {
        self.coefficients[(1, c)] / self.scale_s
    }

    /// Variance of the velocity for a sample noise `sigma2`.
    fn velocity_variance(&self, sigma2: f64) -> f64 {
        sigma2 * self.inverse_normal[(1, 1)] / (self.scale_s * self.scale_s)
    }

    /// What this fit's velocity and position make of noise and of the path terms it does not
    /// model: fixed by its sample times alone, so worked out once per fit.
    fn sensitivity(&self) -> Sensitivity {
        let (velocity_gain, position_gain) = self.gains();
        let weights = &self.inverse_normal * self.design.transpose();
        let mut velocity_per_term = [0.0; 6];
        let mut position_per_term = [0.0; 6];
        let mut unfollowed_norm_sq = [0.0; 6];
        for power in 2..=5 {
            let powers = self.design.column(1).map(|tau| tau.powi(power));
            let absorbed = &weights * &powers;
            let p = power as usize;
            velocity_per_term[p] = absorbed[(1, 0)] * self.scale_s.powi(power - 1);
            position_per_term[p] = absorbed[(0, 0)] * self.scale_s.powi(power);
            unfollowed_norm_sq[p] =
                (powers - &self.design * absorbed).norm_squared() * self.scale_s.powi(2 * power);
        }
        Sensitivity {
            velocity_gain,
            position_gain,
            velocity_per_term,
            position_per_term,
            unfollowed_norm_sq,
        }
    }

    /// The quadratic coefficient (half the acceleration) of component `c` and its variance for
    /// a sample noise `sigma2`; `None` below order 2.
    fn quadratic_term(&self, c: usize, sigma2: f64) -> Option<(f64, f64)> {
        (self.coefficients.nrows() > 2).then(|| {
            let scale2 = self.scale_s * self.scale_s;
            (
                self.coefficients[(2, c)] / scale2,
                sigma2 * self.inverse_normal[(2, 2)] / (scale2 * scale2),
            )
        })
    }

    fn rms_residual(&self) -> f64 {
        (self.squared_residuals.sum() / self.samples as f64).sqrt()
    }

    /// Residual degrees of freedom: samples beyond the polynomial's terms.
    fn dof(&self) -> usize {
        self.samples.saturating_sub(self.coefficients.nrows())
    }

    /// Per component, the sample noise variance the residuals show (zero without residual
    /// degrees of freedom).
    fn noise_variance(&self) -> Vector3<f64> {
        match self.dof() {
            0 => Vector3::zeros(),
            dof => self.squared_residuals / dof as f64,
        }
    }

    /// The variances of velocity and position per unit of sample noise variance.
    fn gains(&self) -> (f64, f64) {
        (self.velocity_variance(1.0), self.inverse_normal[(0, 0)])
    }

    /// This fit's error budget with its own noise estimate and no bias term.
    fn error(&self) -> FitError {
        let (velocity_gain, position_gain) = self.gains();
        FitError::from_noise(
            self.noise_variance(),
            self.dof() as f64,
            Vector3::repeat(velocity_gain),
            Vector3::repeat(position_gain),
        )
    }

    /// The fitted path at the evaluation time.
    fn motion(&self) -> MotionFit {
        MotionFit {
            position: Point3::from(Vector3::from_fn(|c, _| self.position(c))),
            velocity: Vector3::from_fn(|c, _| self.velocity(c)),
            rms_residual: self.rms_residual(),
            error: self.error(),
        }
    }
}

/// A fit's velocity and position variances per unit of sample noise variance, and how much of a
/// path term `d (t - t_eval)^p` each absorbs per unit of `d` (index `p`, 2 to 5; 0 where the
/// fit's order reaches the term): the bias the fit has where the path has that term. And the
/// residual energy a unit `d` leaves (what the fit cannot follow of the term), by which the
/// residuals tell how large such a term is.
struct Sensitivity {
    velocity_gain: f64,
    position_gain: f64,
    velocity_per_term: [f64; 6],
    position_per_term: [f64; 6],
    unfollowed_norm_sq: [f64; 6],
}

/// A candidate window of a track, fitted once with the method's quadratic (centred on the
/// evaluation time): the smoothness check reads its residuals, the adaptive choice its fit.
pub struct QuadraticWindow {
    /// Frames each side of the centre the window spans.
    pub half_window_frames: usize,
    samples: Vec<(f64, Point3<f64>)>,
    quadratic: PolynomialFit,
}

impl QuadraticWindow {
    /// `None` where `fit_quadratic` would be.
    pub fn new(
        half_window_frames: usize,
        samples: Vec<(f64, Point3<f64>)>,
        t_eval_s: f64,
    ) -> Option<Self> {
        let quadratic = PolynomialFit::new(&samples, t_eval_s, 2)?;
        Some(Self {
            half_window_frames,
            samples,
            quadratic,
        })
    }

    /// Each sample's offset from the quadratic, in sample order.
    pub fn residuals(&self) -> impl Iterator<Item = Vector3<f64>> + '_ {
        self.quadratic
            .residuals
            .row_iter()
            .map(|r| Vector3::new(r[0], r[1], r[2]))
    }

    /// The quadratic's path at the evaluation time (`fit_quadratic` of the window).
    pub fn motion(&self) -> Option<MotionFit> {
        self.quadratic.motion().finite()
    }
}

/// The fit chosen for one velocity component.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FitChoice {
    /// Frames each side of the centre the chosen window spans.
    pub half_window_frames: u8,
    /// Polynomial order: 2 (the method's quadratic), 3, or 1 (a line reaching into the past).
    pub order: u8,
}

/// A velocity whose fit was chosen per component from the data.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AdaptiveFit {
    pub fit: MotionFit,
    pub choice: [FitChoice; 3],
}

/// One candidate fit of one component, with what its error statement needs.
struct Candidate {
    /// Squared error expected for the choice.
    expected_sq: f64,
    position: f64,
    velocity: f64,
    velocity_gain: f64,
    position_gain: f64,
    velocity_bias_sq: f64,
    position_bias_sq: f64,
    velocity_cubic_absorption: f64,
    position_cubic_absorption: f64,
    velocity_misfit_gain: f64,
    position_misfit_gain: f64,
}

/// Velocity at `t_eval_s` from the candidate windows `windows` (half-width in frames and its
/// samples, narrowest first, each containing the previous), choosing per component the fit with
/// the smallest expected squared error: a quadratic over each window, or a cubic over the widest.
///
/// A quadratic over a wider window averages more noise away but absorbs more of the path's cubic
/// term (a changing acceleration) into its velocity. The cubic over the widest window estimates
/// that term and the noise (its residuals); from them each candidate's error is predicted as
/// `bias^2 + variance`, the cubic term's own noise discounted so a straight path is not read as
/// curved (and ignored unless it is far above that noise). Falls back to the widest quadratic when the samples cannot support a cubic. The
/// reported residual is the widest quadratic's, as the smoothness check expects.
///
/// `past`, where given, is a window reaching further back than M (and M ahead): a straight line
/// through it joins the candidates, its bias predicted from the acceleration its own quadratic
/// shows (and the cubic term). Where a track's acceleration is lost in its noise (slow or
/// uniform flow) the line's many samples beat any centred fit: at +-5 frames plus 10 more
/// behind, its velocity noise is 0.38 of the centred quadratic's. Its position is a line's too.
pub fn fit_adaptive(
    windows: &[QuadraticWindow],
    past: Option<&QuadraticWindow>,
    t_eval_s: f64,
) -> Option<AdaptiveFit> {
    let widest = windows.last()?;
    let reference_quadratic = &widest.quadratic;
    let fallback = || AdaptiveFit {
        fit: reference_quadratic.motion(),
        choice: [FitChoice {
            half_window_frames: widest.half_window_frames as u8,
            order: 2,
        }; 3],
    };
    // A cubic's noise estimate needs residual degrees of freedom to mean anything.
    let cubic = match PolynomialFit::new(&widest.samples, t_eval_s, 3) {
        Some(c) if c.samples >= 4 + 3 => c,
        _ => {
            let widest_quadratic = fallback();
            return widest_quadratic.fit.finite().map(|_| widest_quadratic);
        }
    };
    let cubic_sensitivity = cubic.sensitivity();
    let quadratics: Vec<(usize, &PolynomialFit, Sensitivity)> = windows
        .iter()
        .map(|w| {
            (
                w.half_window_frames,
                &w.quadratic,
                w.quadratic.sensitivity(),
            )
        })
        .collect();
    let past_line = past.and_then(|p| {
        let line = PolynomialFit::new(&p.samples, t_eval_s, 1)?;
        let sensitivity = line.sensitivity();
        Some((p, line, sensitivity))
    });
    let dof = (cubic.samples - 4) as f64;
    let noise = cubic.noise_variance();
    let mut position = Vector3::zeros();
    let mut velocity = Vector3::zeros();
    let (mut velocity_gain, mut position_gain) = (Vector3::zeros(), Vector3::zeros());
    let mut velocity_bias_sq = Vector3::zeros();
    let mut position_bias_sq = Vector3::zeros();
    let turning = turning_rate_sq(reference_quadratic, &cubic);
    let (fifth_norm_sq, fourth_norm_sq) = (
        cubic_sensitivity.unfollowed_norm_sq[5],
        cubic_sensitivity.unfollowed_norm_sq[4],
    );
    let misfit_gain = |per_term: f64, norm_sq: f64| {
        if norm_sq > 0.0 {
            per_term * per_term / norm_sq
        } else {
            0.0
        }
    };
    let (mut velocity_misfit_gain, mut position_misfit_gain) = (Vector3::zeros(), Vector3::zeros());
    let (mut velocity_cubic_absorption, mut position_cubic_absorption) =
        (Vector3::zeros(), Vector3::zeros());
    let mut cubic_term = Vector3::zeros();
    let scale3 = cubic.scale_s.powi(3);
    let cubic_term_gain = cubic.inverse_normal[(3, 3)] / (scale3 * scale3);
    let mut choice = [FitChoice {
        half_window_frames: widest.half_window_frames as u8,
        order: 3,
    }; 3];
    for c in 0..3 {
        let sigma2 = noise[c];
        let d = cubic.coefficients[(3, c)] / scale3;
        let d_variance = sigma2 * cubic_term_gain;
        // The cubic term counts only where it stands out of its own noise by a wide margin
        // (z^2 > 32): with a noise level estimated from a handful of residuals, a laxer test
        // reads noise as curvature on straight paths and trades the quadratic's precision for
        // nothing (measured: uniform flow w error 0.82 % -> 1.6 % at z^2 > 2).
        const CUBIC_SIGNIFICANCE: f64 = 32.0;
        let d2 = if d * d > CUBIC_SIGNIFICANCE * d_variance {
            d * d - d_variance
        } else {
            0.0
        };
        // The error a fit states is another matter than the choice: there the cubic term,
        // unless plainly significant, is better taken as zero; as an uncertainty it counts as
        // `FitError::sigmas` weighs it (ignoring it understated turbulence's errors
        // several-fold).
        cubic_term[c] = d;
        // A path turning at rate w has a fifth derivative of w^4 times its velocity (exactly so
        // on a circle), which no candidate here models: stated as each fit's bias from it.
        let fifth_term = turning * turning * reference_quadratic.velocity(c) / 120.0;
        // The position's: the acceleration (half of it: a line's), the cubic term, and the
        // fourth-order term of a turning path (w^2 times its acceleration, on a circle).
        let half_acceleration_sq = reference_quadratic
            .quadratic_term(c, sigma2)
            .map_or(0.0, |(q, q_variance)| (q * q - q_variance).max(0.0));
        let fourth_term_sq = turning * turning * 4.0 * half_acceleration_sq / (24.0 * 24.0);
        let candidate =
            |fit: &PolynomialFit, sensitivity: &Sensitivity, bias_sq: f64, bias_sq_stated: f64| {
                let (velocity_bias, position_bias) = (
                    &sensitivity.velocity_per_term,
                    &sensitivity.position_per_term,
                );
                let bias_sq_stated = bias_sq_stated + (velocity_bias[5] * fifth_term).powi(2);
                let position_bias_sq = position_bias[2].powi(2) * half_acceleration_sq
                    + position_bias[4].powi(2) * fourth_term_sq;
                Candidate {
                    expected_sq: bias_sq + fit.velocity_variance(sigma2),
                    position: fit.position(c),
                    velocity: fit.velocity(c),
                    velocity_gain: sensitivity.velocity_gain,
                    position_gain: sensitivity.position_gain,
                    velocity_bias_sq: bias_sq_stated,
                    position_bias_sq,
                    velocity_cubic_absorption: velocity_bias[3],
                    position_cubic_absorption: position_bias[3],
                    velocity_misfit_gain: misfit_gain(velocity_bias[5], fifth_norm_sq),
                    position_misfit_gain: misfit_gain(position_bias[4], fourth_norm_sq),
                }
            };
        let mut best = candidate(&cubic, &cubic_sensitivity, 0.0, 0.0);
        for (m, fit, sensitivity) in &quadratics {
            let bias = sensitivity.velocity_per_term[3];
            let expected = d2 * bias * bias + fit.velocity_variance(sigma2);
            // Ties go to the quadratic (the method's fit), then to the wider window.
            if expected <= best.expected_sq {
                best = candidate(fit, sensitivity, d2 * bias * bias, 0.0);
                choice[c] = FitChoice {
                    half_window_frames: *m as u8,
                    order: 2,
                };
            }
        }
        if let Some((past, line, sensitivity)) = &past_line {
            if let Some((q, q_variance)) = past.quadratic.quadratic_term(c, sigma2) {
                // The acceleration's square, its own noise taken out (unbiased, floored at 0).
                let q2 = (q * q - q_variance).max(0.0);
                let (b2, b3) = (
                    sensitivity.velocity_per_term[2],
                    sensitivity.velocity_per_term[3],
                );
                let bias_sq = q2 * b2 * b2 + d2 * b3 * b3;
                if bias_sq + line.velocity_variance(sigma2) < best.expected_sq {
                    best = candidate(line, sensitivity, bias_sq, q2 * b2 * b2);
                    choice[c] = FitChoice {
                        half_window_frames: past.half_window_frames as u8,
                        order: 1,
                    };
                }
            }
        }
        position[c] = best.position;
        velocity[c] = best.velocity;
        velocity_gain[c] = best.velocity_gain;
        position_gain[c] = best.position_gain;
        velocity_bias_sq[c] = best.velocity_bias_sq;
        position_bias_sq[c] = best.position_bias_sq;
        velocity_cubic_absorption[c] = best.velocity_cubic_absorption;
        position_cubic_absorption[c] = best.position_cubic_absorption;
        velocity_misfit_gain[c] = best.velocity_misfit_gain;
        position_misfit_gain[c] = best.position_misfit_gain;
    }
    MotionFit {
        position: Point3::from(position),
        velocity,
        rms_residual: reference_quadratic.rms_residual(),
        error: FitError {
            noise_variance: noise,
            noise_dof: dof,
            velocity_gain,
            position_gain,
            velocity_bias_sq,
            position_bias_sq,
            cubic_term,
            cubic_term_gain,
            velocity_cubic_absorption,
            position_cubic_absorption,
            velocity_misfit_gain,
            position_misfit_gain,
        },
    }
    .finite()
    .map(|fit| AdaptiveFit { fit, choice })
}

/// The square of the rate at which the path turns (or changes speed), per second: its
/// acceleration over its speed, from the widest quadratic's terms with their noise taken out
/// (`noise` gives the sample noise); 0 where the path is straight or at rest.
fn turning_rate_sq(quadratic: &PolynomialFit, noise: &PolynomialFit) -> f64 {
    let sigma2 = noise.noise_variance();
    let mut acceleration_sq = 0.0;
    let mut speed_sq = 0.0;
    for c in 0..3 {
        if let Some((q, q_variance)) = quadratic.quadratic_term(c, sigma2[c]) {
            acceleration_sq += 4.0 * (q * q - q_variance).max(0.0);
        }
        speed_sq += quadratic.velocity(c).powi(2);
    }
    if speed_sq > 0.0 {
        acceleration_sq / speed_sq
    } else {
        0.0
    }
}

/// Least-squares straight line through `samples`, evaluated at `t_eval_s`: a lower-noise
/// derivative than the quadratic's where the window is one-sided, at the cost of a bias of
/// about `acceleration * (t_eval_s - mean sample time)`. `None` with fewer than two samples or
/// coincident times.
pub fn fit_line(samples: &[(f64, Point3<f64>)], t_eval_s: f64) -> Option<MotionFit> {
    if samples.len() < 2 {
        return None;
    }
    let n = samples.len() as f64;
    let mean_t = samples.iter().map(|(t, _)| t - t_eval_s).sum::<f64>() / n;
    let mean_p = samples.iter().map(|(_, p)| p.coords).sum::<Vector3<f64>>() / n;
    let mut stt = 0.0;
    let mut stp = Vector3::zeros();
    for (t, p) in samples {
        let dt = t - t_eval_s - mean_t;
        stt += dt * dt;
        stp += dt * (p.coords - mean_p);
    }
    if stt.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
        return None;
    }
    let velocity = stp / stt;
    let a = mean_p - velocity * mean_t;
    let squared_by_component = samples.iter().fold(Vector3::zeros(), |sum, (t, p)| {
        sum + (p.coords - (a + velocity * (t - t_eval_s))).map(|r| r * r)
    });
    let squared = squared_by_component.sum();
    let dof = samples.len() - 2;
    let fit = MotionFit {
        position: Point3::from(a),
        velocity,
        rms_residual: (squared / n).sqrt(),
        error: FitError::from_noise(
            if dof == 0 {
                Vector3::zeros()
            } else {
                squared_by_component / dof as f64
            },
            dof as f64,
            Vector3::repeat(1.0 / stt),
            Vector3::repeat(1.0 / n + mean_t * mean_t / stt),
        ),
    };
    fit.finite()
}

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
    use proptest::prelude::*;

    /// The stated velocity and position sigmas of a quadratic and a line agree with the scatter
    /// of their estimates over many noisy draws of the same path (Monte Carlo, 4000 draws: the
    /// standard deviation is known to about 1.1 %, so 5 % is a tight bound).
    #[test]
    fn stated_sigmas_match_the_scatter_of_repeated_fits() {
        let sigma = 0.002;
        let times: Vec<f64> = (-5..=5).map(|k| f64::from(k) / 30.0).collect();
        let path = |t: f64| Point3::new(0.1 + 0.5 * t + 2.0 * t * t, -0.2 * t, 1.0 + 0.3 * t);
        let mut rng = crate::synth::Rng::new(11);
        type Fit = fn(&[(f64, Point3<f64>)], f64) -> Option<MotionFit>;
        for (name, fit, truth_velocity) in [
            (
                "quadratic",
                fit_quadratic as Fit,
                Vector3::new(0.5, -0.2, 0.3),
            ),
            ("line", fit_line as Fit, Vector3::new(0.5, -0.2, 0.3)),
        ] {
            let (mut velocities, mut positions, mut stated) = (Vec::new(), Vec::new(), Vec::new());
            for _ in 0..4000 {
                let samples: Vec<(f64, Point3<f64>)> = times
                    .iter()
                    .map(|&t| {
                        let noise = Vector3::new(rng.normal(), rng.normal(), rng.normal()) * sigma;
                        (t, path(t) + noise)
                    })
                    .collect();
                let f = fit(&samples, 0.0).expect("fits");
                velocities.push(f.velocity.x);
                positions.push(f.position.x);
                // The noise the fit is told, not its own estimate: the gains are under test.
                let known = FitError {
                    noise_variance: Vector3::repeat(sigma * sigma),
                    noise_dof: 1e9,
                    ..f.error
                };
                stated.push(known.sigmas(None));
            }
            let std = |v: &[f64]| {
                let mean = v.iter().sum::<f64>() / v.len() as f64;
                (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (v.len() - 1) as f64).sqrt()
            };
            let (sv, sp) = stated[0];
            let ratio_v = std(&velocities) / sv.x;
            let ratio_p = std(&positions) / sp.x;
            assert!(
                (ratio_v - 1.0).abs() < 0.05,
                "{name}: velocity scatter / stated {ratio_v}"
            );
            assert!(
                (ratio_p - 1.0).abs() < 0.05,
                "{name}: position scatter / stated {ratio_p}"
            );
            if name == "quadratic" {
                // The quadratic is unbiased on a quadratic path.
                let mean = velocities.iter().sum::<f64>() / velocities.len() as f64;
                assert!((mean - truth_velocity.x).abs() < 3.0 * sv.x / 60.0);
            }
        }
    }

    #[test]
    fn a_pooled_noise_counts_in_proportion_to_its_degrees_of_freedom() {
        let error = FitError {
            velocity_bias_sq: Vector3::new(0.0, 9.0, 0.0),
            ..FitError::from_noise(
                Vector3::new(4.0, 4.0, 4.0),
                10.0,
                Vector3::repeat(1.0),
                Vector3::repeat(0.25),
            )
        };
        let prior = ScenePrior {
            noise_variance: Vector3::repeat(1.0),
            noise_dof: 30.0,
            cubic_term_spread: [None; 3],
        };
        let (v, p) = error.sigmas(Some(&prior));
        // (10 * 4 + 30 * 1) / 40 = 1.75.
        assert!((v.x - 1.75f64.sqrt()).abs() < 1e-12);
        assert!((v.y - (1.75f64 + 9.0).sqrt()).abs() < 1e-12, "bias adds");
        assert!((p.x - (0.25 * 1.75f64).sqrt()).abs() < 1e-12);
        let (alone, _) = error.sigmas(None);
        assert!((alone.x - 2.0).abs() < 1e-12);
    }

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

    #[test]
    fn central_difference_when_m_is_one() {
        let samples = [
            (0.0, Point3::new(0.0, 0.0, 1.0)),
            (0.1, Point3::new(0.3, 0.0, 1.0)),
            (0.2, Point3::new(0.5, 0.0, 1.0)),
        ];
        let fit = fit_quadratic(&samples, 0.1).expect("well posed");
        assert!((fit.velocity.x - 2.5).abs() < 1e-12);
        assert!(fit.rms_residual < 1e-12);
    }

    #[test]
    fn too_few_or_degenerate_samples() {
        let p = Point3::origin();
        assert!(fit_quadratic(&[(0.0, p), (1.0, p)], 0.5).is_none());
        assert!(fit_quadratic(&[(0.0, p), (0.0, p), (0.0, p)], 0.0).is_none());
    }

    #[test]
    fn a_line_through_uniform_motion_is_exact_at_any_time() {
        let samples: Vec<_> = (0..5)
            .map(|i| {
                let t = 2.0 + 0.1 * i as f64;
                (t, Point3::new(1.0 + 3.0 * t, -t, 0.5))
            })
            .collect();
        let fit = fit_line(&samples, 2.4).expect("well posed");
        assert!((fit.velocity - Vector3::new(3.0, -1.0, 0.0)).norm() < 1e-12);
        assert!((fit.position - Point3::new(8.2, -2.4, 0.5)).norm() < 1e-12);
        assert!(fit_line(&samples[..1], 2.0).is_none());
    }

    fn window(
        m: usize,
        dt: f64,
        path: impl Fn(f64) -> f64,
        noise: impl Fn(usize) -> f64,
    ) -> Vec<(f64, Point3<f64>)> {
        (0..2 * m + 1)
            .map(|i| {
                let t = (i as f64 - m as f64) * dt;
                let x = path(t) + noise(i);
                (t, Point3::new(x, x, x))
            })
            .collect()
    }

    fn nested(
        m: usize,
        dt: f64,
        path: impl Fn(f64) -> f64 + Copy,
        noise: impl Fn(usize) -> f64 + Copy,
    ) -> Vec<QuadraticWindow> {
        let widest = window(m, dt, path, noise);
        (2..=m)
            .map(|w| QuadraticWindow::new(w, widest[m - w..=m + w].to_vec(), 0.0).expect("fit"))
            .collect()
    }

    fn error_budget() -> FitError {
        FitError {
            noise_variance: Vector3::new(4.0, 0.5, 4.0),
            noise_dof: 7.0,
            velocity_gain: Vector3::repeat(1.0),
            position_gain: Vector3::repeat(1.0),
            velocity_bias_sq: Vector3::zeros(),
            position_bias_sq: Vector3::zeros(),
            cubic_term: Vector3::new(0.0, 0.0, 3.0),
            cubic_term_gain: 0.5,
            velocity_cubic_absorption: Vector3::new(0.0, 0.0, 2.0),
            position_cubic_absorption: Vector3::zeros(),
            velocity_misfit_gain: Vector3::new(0.1, 0.1, 0.0),
            position_misfit_gain: Vector3::new(0.2, 0.0, 0.0),
        }
    }

    #[test]
    fn residual_energy_beyond_the_scene_noise_counts_as_the_paths_shape() {
        let prior = ScenePrior {
            noise_variance: Vector3::repeat(1.0),
            noise_dof: 10.0,
            cubic_term_spread: [None; 3],
        };
        let (v, p) = error_budget().sigmas(Some(&prior));
        // x: pooled (7 * 4 + 10 * 1) / 17; residual energy 28 against the scene's 7.
        let pooled = 38.0 / 17.0;
        assert!((v.x - (pooled + 0.1 * 21.0f64).sqrt()).abs() < 1e-12);
        assert!((p.x - (pooled + 0.2 * 21.0f64).sqrt()).abs() < 1e-12);
        // y: residuals quieter than the scene's noise show no misfit.
        assert!((v.y - ((7.0 * 0.5 + 10.0) / 17.0f64).sqrt()).abs() < 1e-12);
        // Nor do residuals within chance of it (1.8 times the scene's variance).
        let lucky = FitError {
            noise_variance: Vector3::repeat(1.8),
            ..error_budget()
        };
        let (v, _) = lucky.sigmas(Some(&prior));
        assert!((v.x - ((7.0 * 1.8 + 10.0) / 17.0f64).sqrt()).abs() < 1e-12);
        // Without a scene, nothing tells misfit from noise.
        let (alone, _) = error_budget().sigmas(None);
        assert!((alone.x - 2.0).abs() < 1e-12);
    }

    #[test]
    fn the_cubic_term_is_weighed_against_the_scenes_spread() {
        let error = error_budget();
        let noise_z = (7.0 * 4.0 + 10.0) / 17.0;
        let variance = 0.5 * noise_z;
        let with = |tau2: Option<f64>| {
            let prior = ScenePrior {
                noise_variance: Vector3::repeat(1.0),
                noise_dof: 10.0,
                cubic_term_spread: [None, None, tau2],
            };
            error.sigmas(Some(&prior)).0.z.powi(2) - noise_z
        };
        // No scene spread known (or none to speak of): the window's own unbiased estimate,
        // d^2 - var.
        assert!((with(None) - 4.0 * (9.0 - variance)).abs() < 1e-9);
        assert!((with(Some(0.0)) - 4.0 * (9.0 - variance)).abs() < 1e-9);
        // A scene of strongly curved paths: the estimate stands, with its own uncertainty.
        let wide = with(Some(1e9));
        assert!((wide - 4.0 * (9.0 + variance)).abs() < 1e-3, "{wide}");
        // In between, shrunk towards the scene's spread: a small estimate is not taken at its
        // word where the scene's paths curve.
        let middle = with(Some(2.0));
        assert!(middle > 0.0 && middle < wide, "{middle}");
        let small = FitError {
            cubic_term: Vector3::new(0.0, 0.0, 0.1),
            ..error
        };
        let prior = ScenePrior {
            noise_variance: Vector3::repeat(1.0),
            noise_dof: 10.0,
            cubic_term_spread: [None, None, Some(50.0)],
        };
        let stated = small.sigmas(Some(&prior)).0.z.powi(2) - noise_z;
        assert!(stated > 4.0 * variance * 0.9, "{stated}");
    }

    /// Paths turning at 20-40 rad/s sampled at 100 Hz (+-5 frames span 1-2 rad): the cubic's
    /// velocity keeps a fifth-order bias its residuals show but its noise model does not. The
    /// stated sigmas cover the errors only with the misfit counted.
    #[test]
    fn stated_sigmas_cover_a_path_the_cubic_cannot_follow() {
        let (dt, sigma) = (0.01, 2e-5);
        let mut rng = crate::synth::Rng::new(5);
        let prior = ScenePrior {
            noise_variance: Vector3::repeat(sigma * sigma),
            noise_dof: 10.0,
            cubic_term_spread: [None; 3],
        };
        let (mut covered, mut covered_without, mut trials) = (0, 0, 0);
        for _ in 0..2000 {
            let phase = rng.range(0.0, std::f64::consts::TAU);
            let omega = rng.range(20.0, 40.0);
            let path = move |t: f64| 0.02 * (omega * t + phase).sin();
            let noise: Vec<f64> = (0..11).map(|_| rng.normal() * sigma).collect();
            let windows = nested(5, dt, path, |i| noise[i]);
            let Some(fit) = fit_adaptive(&windows, None, 0.0) else {
                continue;
            };
            let truth = 0.02 * omega * phase.cos();
            let error = (fit.fit.velocity.x - truth).abs();
            let (stated, _) = fit.fit.error.sigmas(Some(&prior));
            let without = FitError {
                velocity_misfit_gain: Vector3::zeros(),
                ..fit.fit.error
            }
            .sigmas(Some(&prior))
            .0;
            trials += 1;
            covered += usize::from(error < 2.0 * stated.x);
            covered_without += usize::from(error < 2.0 * without.x);
        }
        let share = covered as f64 / trials as f64;
        let share_without = covered_without as f64 / trials as f64;
        println!("within 2 sigma: {share:.4} (without the misfit {share_without:.4})");
        assert!(trials > 1900);
        // An envelope: a pure sinusoid's fourth-order term counts as if it were fifth-order.
        assert!((0.9..=0.998).contains(&share), "within 2 sigma: {share}");
        assert!(share_without < 0.85, "without the misfit: {share_without}");
    }

    /// A path whose acceleration changes fast (x = t^3 scaled): the quadratic on +-5 is biased,
    /// the chosen fit is not.
    #[test]
    fn a_changing_acceleration_gets_an_unbiased_fit() {
        let dt = 0.01;
        let path = |t: f64| 0.3 * t + 400.0 * t * t * t;
        let noise = |i: usize| 1e-5 * ((i * 7919) % 13) as f64 / 13.0;
        let windows = nested(5, dt, path, noise);
        let quadratic = windows[3].motion().expect("fit");
        let chosen = fit_adaptive(&windows, None, 0.0).expect("fit");
        assert!((quadratic.velocity.x - 0.3).abs() > 0.05, "{quadratic:?}");
        assert!((chosen.fit.velocity.x - 0.3).abs() < 0.01, "{chosen:?}");
        assert!(chosen.choice[0].order == 3 || chosen.choice[0].half_window_frames < 5);
    }

    /// Samples from `past` frames before the centre to `m` after it, with the same noise
    /// sequence as `nested`'s window on the frames they share.
    fn past_window(
        m: usize,
        past: usize,
        dt: f64,
        path: impl Fn(f64) -> f64,
        noise: impl Fn(usize) -> f64,
    ) -> QuadraticWindow {
        let samples = (0..=past + m)
            .map(|i| {
                let t = (i as f64 - past as f64) * dt;
                let x = path(t) + noise(i);
                (t, Point3::new(x, x, x))
            })
            .collect();
        QuadraticWindow::new(m, samples, 0.0).expect("fit")
    }

    /// RMS velocity error (x) of the adaptive fit over 300 noisy paths, without and with the
    /// line reaching 15 frames back, and how often the line was chosen.
    fn with_and_without_the_past(path: impl Fn(f64) -> f64 + Copy) -> (f64, f64, usize) {
        let (dt, m, past) = (0.01, 5, 15);
        let truth = (path(1e-6) - path(-1e-6)) / 2e-6;
        let (mut without, mut with, mut lines) = (0.0, 0.0, 0);
        for seed in 0..300u64 {
            let mut rng = crate::synth::Rng::new(seed);
            let noise: Vec<f64> = (0..=past + m).map(|_| 1e-3 * rng.normal()).collect();
            let centred = nested(m, dt, path, |i| noise[i + past - m]);
            let long = past_window(m, past, dt, path, |i| noise[i]);
            let a = fit_adaptive(&centred, None, 0.0).expect("fit");
            let b = fit_adaptive(&centred, Some(&long), 0.0).expect("fit");
            without += (a.fit.velocity.x - truth).powi(2);
            with += (b.fit.velocity.x - truth).powi(2);
            lines += usize::from(b.choice[0].order == 1);
        }
        ((without / 300.0).sqrt(), (with / 300.0).sqrt(), lines)
    }

    /// Uniform motion: the line through 21 frames has 0.38 of the centred quadratic's noise
    /// (0.036 against 0.095 in units of sigma / dt). It is left out where the noise happens to
    /// look like an acceleration (one path in eight), so the RMS error falls by a third (0.0093
    /// -> 0.0062), not more.
    #[test]
    fn a_line_into_the_past_cuts_the_noise_on_a_straight_path() {
        let (without, with, lines) = with_and_without_the_past(|t| 0.5 * t);
        println!("straight: rms {without:.4} -> {with:.4}, line chosen {lines} of 300");
        assert!(with < 0.75 * without, "{without} -> {with}");
        assert!(lines > 200, "{lines}");
    }

    /// An acceleration of 20 m/s^2 biases the line by 1 m/s (a * 5 frames * dt): it is left out
    /// and the error is what the centred fits give.
    #[test]
    fn a_line_into_the_past_is_left_out_where_the_path_accelerates() {
        let (without, with, lines) = with_and_without_the_past(|t| 0.5 * t + 10.0 * t * t);
        println!("accelerating: rms {without:.4} -> {with:.4}, line chosen {lines} of 300");
        assert!(with <= 1.05 * without, "{without} -> {with}");
        assert!(lines < 5, "{lines}");
    }

    /// A straight path with noise: the method's quadratic on the full window is kept.
    #[test]
    fn a_straight_noisy_path_keeps_the_full_quadratic() {
        let dt = 0.01;
        let mut kept = 0;
        for seed in 0..200u64 {
            let mut rng = crate::synth::Rng::new(seed);
            let noise: Vec<f64> = (0..11).map(|_| 1e-3 * rng.normal()).collect();
            let windows = nested(5, dt, |t| 0.5 * t, |i| noise[i]);
            let chosen = fit_adaptive(&windows, None, 0.0).expect("fit");
            kept += chosen
                .choice
                .iter()
                .filter(|c| c.order == 2 && c.half_window_frames == 5)
                .count();
        }
        assert!(
            kept >= 590,
            "{kept} of 600 components kept the full quadratic"
        );
    }

    proptest! {
        #[test]
        fn recovers_any_quadratic_exactly(
            a in -5.0f64..5.0, b in -5.0f64..5.0, c in -5.0f64..5.0, m in 1usize..6, dt in 0.005f64..0.1
        ) {
            let samples: Vec<_> = (0..2 * m + 1)
                .map(|i| {
                    let t = 10.0 + i as f64 * dt;
                    let tau = t - (10.0 + m as f64 * dt);
                    (t, Point3::new(a + b * tau + c * tau * tau, b, -a))
                })
                .collect();
            let fit = fit_quadratic(&samples, samples[m].0).expect("well posed");
            prop_assert!((fit.velocity.x - b).abs() < 1e-6 * (1.0 + b.abs()));
            prop_assert!(fit.velocity.y.abs() < 1e-6);
            prop_assert!((fit.position.x - a).abs() < 1e-8 * (1.0 + a.abs()));
        }
    }
}
