//! Moving least squares (method section 5.5, eqs. 13-15): `q(t) = a + b (t - t_n) + c (t - t_n)^2`
//! fitted to the positions of a window of frames; the velocity at `t_n` is `b` and the smoothed
//! position `a`. The method centres the window on `t_n` (`+-M` frames). Times come from the
//! frames' timestamps, so jittered frame intervals are honoured.
//!
//! Beyond the method, [`fit_adaptive`] chooses each component's fit from the track's own
//! residuals: a quadratic over a narrower window, a cubic, or a line reaching into the past.

use nalgebra::{Matrix3, Point3, SMatrix, SVector, Vector3};

use super::uncertainty::{ComponentBudget, QuantityBudget, UncertaintyBudget};

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
    pub error: UncertaintyBudget,
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

/// Least-squares quadratic through `samples` (time in seconds, position), evaluated at `t_eval_s`.
/// `None` with fewer than three samples or when the times cannot support a quadratic.
pub fn fit_quadratic(samples: &[(f64, Point3<f64>)], t_eval_s: f64) -> Option<MotionFit> {
    PolynomialFit::new(samples, t_eval_s, 2)?.motion().finite()
}

/// Where a least-squares quadratic through `samples` puts the particle at `t_eval_s`: the
/// position alone, as a prediction wants it ([`fit_quadratic`] also works out what its velocity
/// is worth). `None` with fewer than three samples or when the times cannot support a quadratic.
pub fn quadratic_position(samples: &[(f64, Point3<f64>)], t_eval_s: f64) -> Option<Point3<f64>> {
    if samples.len() < 3 {
        return None;
    }
    let scale_s = time_scale(samples, t_eval_s)?;
    let (mut normal, mut moments) = (Matrix3::zeros(), Matrix3::zeros());
    for (t, p) in samples {
        let tau = (t - t_eval_s) / scale_s;
        let row = Vector3::new(1.0, tau, tau * tau);
        normal += row * row.transpose();
        moments += row * p.coords.transpose();
    }
    // Row k of the solution: the coefficient of tau^k for x, y and z; tau is 0 at t_eval_s.
    let coefficients = normal.try_inverse()? * moments;
    let position = Point3::from(coefficients.row(0).transpose());
    position.iter().all(|v| v.is_finite()).then_some(position)
}

/// The polynomial fits' unit of time: the farthest sample from `t_eval_s`, seconds (every
/// `tau` within +-1); `None` where every sample is at `t_eval_s` (or a time is not finite).
fn time_scale(samples: &[(f64, Point3<f64>)], t_eval_s: f64) -> Option<f64> {
    let scale_s = samples
        .iter()
        .map(|(t, _)| (t - t_eval_s).abs())
        .fold(0.0, f64::max);
    (scale_s.partial_cmp(&0.0) == Some(std::cmp::Ordering::Greater)).then_some(scale_s)
}

/// The most terms a [`PolynomialFit`] has: the cubic's.
const MAX_TERMS: usize = 4;

/// A least-squares polynomial `sum c_k tau^k` with `tau = (t - t_eval) / scale_s`, with what the
/// adaptive choice needs to predict its errors. Every track fits several per frame, so its sums
/// are fixed-size (the terms it does not have are zero, their block of the inverse normal
/// matrix the identity) and nothing but its samples' times and residuals is allocated.
struct PolynomialFit {
    /// The polynomial's terms (its order plus one).
    terms: usize,
    /// Row k: the coefficient of `tau^k` for x, y and z.
    coefficients: SMatrix<f64, MAX_TERMS, 3>,
    /// `(X^T X)^-1` in scaled time: a coefficient's variance is this diagonal times sigma^2.
    inverse_normal: SMatrix<f64, MAX_TERMS, MAX_TERMS>,
    /// Each sample's scaled time `tau` (the design matrix X holds its powers).
    taus: Vec<f64>,
    /// Each sample's offset from the fitted curve, x, y and z.
    residuals: Vec<Vector3<f64>>,
    /// Per component, sum of squared residuals.
    squared_residuals: Vector3<f64>,
    samples: usize,
    scale_s: f64,
}

/// The powers of `tau` a fit of `terms` terms has (`tau^k`), zero beyond them.
fn powers_of(tau: f64, terms: usize) -> SVector<f64, MAX_TERMS> {
    let mut row = SVector::zeros();
    let mut power = 1.0;
    for k in 0..terms {
        row[k] = power;
        power *= tau;
    }
    row
}

impl PolynomialFit {
    fn new(samples: &[(f64, Point3<f64>)], t_eval_s: f64, order: usize) -> Option<Self> {
        let terms = order + 1;
        if samples.len() < terms || terms > MAX_TERMS {
            return None;
        }
        let scale_s = time_scale(samples, t_eval_s)?;
        let taus: Vec<f64> = samples
            .iter()
            .map(|(t, _)| (t - t_eval_s) / scale_s)
            .collect();
        // The terms the fit does not have keep the identity, so that the inverse of the whole
        // is the inverse of the fit's own block.
        let mut normal = SMatrix::<f64, MAX_TERMS, MAX_TERMS>::from_fn(|a, b| {
            f64::from(u8::from(a == b && a >= terms))
        });
        let mut moments = SMatrix::<f64, MAX_TERMS, 3>::zeros();
        for (&tau, (_, p)) in taus.iter().zip(samples) {
            let row = powers_of(tau, terms);
            normal += row * row.transpose();
            moments += row * p.coords.transpose();
        }
        let inverse_normal = normal.try_inverse()?;
        let coefficients = inverse_normal * moments;
        let residuals: Vec<Vector3<f64>> = taus
            .iter()
            .zip(samples)
            .map(|(&tau, (_, p))| p.coords - coefficients.tr_mul(&powers_of(tau, terms)))
            .collect();
        let squared_residuals = residuals
            .iter()
            .fold(Vector3::zeros(), |sum, r| sum + r.component_mul(r));
        coefficients.iter().all(|v| v.is_finite()).then_some(Self {
            terms,
            coefficients,
            inverse_normal,
            taus,
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
        // The fit of each path term tau^p (p = 2 to 5) alone: X^T of it, its coefficients,
        // then what of it the fit leaves.
        let mut moments = [SVector::<f64, MAX_TERMS>::zeros(); 6];
        for &tau in &self.taus {
            let (row, path) = self.rows_at(tau);
            for p in 2..=5 {
                moments[p] += row * path[p];
            }
        }
        let absorbed = moments.map(|m| self.inverse_normal * m);
        let mut unfollowed = [0.0; 6];
        for &tau in &self.taus {
            let (row, path) = self.rows_at(tau);
            for p in 2..=5 {
                unfollowed[p] += (path[p] - row.dot(&absorbed[p])).powi(2);
            }
        }
        let mut velocity_per_term = [0.0; 6];
        let mut position_per_term = [0.0; 6];
        let mut unfollowed_norm_sq = [0.0; 6];
        for power in 2..=5 {
            let p = power as usize;
            velocity_per_term[p] = absorbed[p][1] * self.scale_s.powi(power - 1);
            position_per_term[p] = absorbed[p][0] * self.scale_s.powi(power);
            unfollowed_norm_sq[p] = unfollowed[p] * self.scale_s.powi(2 * power);
        }
        Sensitivity {
            velocity: TermResponse {
                gain: velocity_gain,
                per_term: velocity_per_term,
            },
            position: TermResponse {
                gain: position_gain,
                per_term: position_per_term,
            },
            unfollowed_norm_sq,
        }
    }

    /// A sample at scaled time `tau`: its row of the design matrix, and `tau^p` for p up to 5.
    fn rows_at(&self, tau: f64) -> (SVector<f64, MAX_TERMS>, [f64; 6]) {
        let mut path = [1.0; 6];
        for p in 1..6 {
            path[p] = path[p - 1] * tau;
        }
        (powers_of(tau, self.terms), path)
    }

    /// The quadratic coefficient (half the acceleration) of component `c` and its variance for
    /// a sample noise `sigma2`; `None` below order 2.
    fn quadratic_term(&self, c: usize, sigma2: f64) -> Option<(f64, f64)> {
        (self.terms > 2).then(|| {
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
        self.samples.saturating_sub(self.terms)
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
    fn error(&self) -> UncertaintyBudget {
        let (velocity_gain, position_gain) = self.gains();
        UncertaintyBudget::from_noise(
            self.noise_variance(),
            self.dof() as f64,
            velocity_gain,
            position_gain,
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

/// How one fitted quantity responds to noise and to path terms: its variance per unit of
/// sample noise variance, and how much of a path term `d (t - t_eval)^p` it absorbs per unit of
/// `d` (index `p`, 2 to 5; 0 where the fit's order reaches the term): the bias the fit has where
/// the path has that term.
struct TermResponse {
    gain: f64,
    per_term: [f64; 6],
}

/// A fit's velocity and position responses ([`TermResponse`]), and the residual energy a unit
/// `d` of each path term leaves (what the fit cannot follow of the term), by which the residuals
/// tell how large such a term is.
struct Sensitivity {
    velocity: TermResponse,
    position: TermResponse,
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

    /// [`Self::new`] where some samples are measured only across a line of sight (a particle
    /// one camera hid: `sights[r]` is the centre of the camera that saw sample `r`; along its
    /// line the sample is only predicted). The quadratic is the least-squares one to what the
    /// samples measure ([`fill_along_sights`]); each such sample is then placed on its line
    /// where that quadratic passes nearest, so the window's residuals and later fits see its
    /// across-sight offset only. `None` where `new` would be, or where the samples seen by both
    /// cameras cannot pin the quadratic along the lines of sight.
    pub fn with_sights(
        half_window_frames: usize,
        mut samples: Vec<(f64, Point3<f64>)>,
        sights: &[Option<Point3<f64>>],
        t_eval_s: f64,
    ) -> Option<Self> {
        if sights.iter().any(Option::is_some) {
            fill_along_sights(&mut samples, sights, t_eval_s)?;
        }
        Self::new(half_window_frames, samples, t_eval_s)
    }

    /// Each sample's offset from the quadratic, in sample order.
    pub fn residuals(&self) -> impl Iterator<Item = Vector3<f64>> + '_ {
        self.quadratic.residuals.iter().copied()
    }

    /// The quadratic's path at the evaluation time (`fit_quadratic` of the window).
    pub fn motion(&self) -> Option<MotionFit> {
        self.quadratic.motion().finite()
    }
}

/// Places each sample measured only across a line of sight (`sights[r]`, the camera that saw
/// it) where the least-squares quadratic passes nearest on its line. That quadratic weighs each
/// such sample by the projection across its line (`I - u u^T`), the others fully: one 9 x 9
/// solve for the three components' three coefficients together, as a line of sight couples
/// them. An unweighted fit of the placed samples is the same quadratic (at it, each placed
/// sample's residual is its across-sight one). `None` where the solve is singular.
fn fill_along_sights(
    samples: &mut [(f64, Point3<f64>)],
    sights: &[Option<Point3<f64>>],
    t_eval_s: f64,
) -> Option<()> {
    let scale_s = time_scale(samples, t_eval_s)?;
    let terms = |t: f64| {
        let tau = (t - t_eval_s) / scale_s;
        [1.0, tau, tau * tau]
    };
    let (mut normal, mut rhs) = (SMatrix::<f64, 9, 9>::zeros(), SVector::<f64, 9>::zeros());
    for ((t, p), sight) in samples.iter().zip(sights) {
        let across = match sight {
            Some(camera) => {
                let u = (p - camera).try_normalize(1e-12)?;
                Matrix3::identity() - u * u.transpose()
            }
            None => Matrix3::identity(),
        };
        let phi = terms(*t);
        for k in 0..3 {
            for l in 0..3 {
                let block = across * (phi[k] * phi[l]);
                let mut view = normal.fixed_view_mut::<3, 3>(3 * k, 3 * l);
                view += block;
            }
            let mut rows = rhs.fixed_rows_mut::<3>(3 * k);
            rows += across * p.coords * phi[k];
        }
    }
    let coefficients = normal.cholesky()?.solve(&rhs);
    for ((t, p), sight) in samples.iter_mut().zip(sights) {
        if let Some(camera) = sight {
            let phi = terms(*t);
            let path = (0..3).fold(Vector3::zeros(), |q, k| {
                q + coefficients.fixed_rows::<3>(3 * k) * phi[k]
            });
            *p = nearest_on_sight(camera, p, &Point3::from(path));
        }
    }
    Some(())
}

/// The point on the line of sight from `camera` through `seen` nearest to `path`.
fn nearest_on_sight(camera: &Point3<f64>, seen: &Point3<f64>, path: &Point3<f64>) -> Point3<f64> {
    let Some(sight) = (seen - camera).try_normalize(1e-12) else {
        return *seen;
    };
    camera + sight * (path - camera).dot(&sight)
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
    /// The fit.
    pub fit: MotionFit,
    /// Each component's chosen fit.
    pub choice: [FitChoice; 3],
}

/// One candidate fit of one component, with what its error statement needs.
struct Candidate {
    /// Squared error expected for the choice.
    expected_sq: f64,
    position: f64,
    velocity: f64,
    velocity_budget: ComponentBudget,
    position_budget: ComponentBudget,
}

/// Velocity at `t_eval_s` from the candidate windows `windows` (half-width in frames and its
/// samples, narrowest first, each containing the previous), choosing per component the fit with
/// the smallest expected squared error: a quadratic over each window, or a cubic over the widest.
///
/// A quadratic over a wider window averages more noise away but absorbs more of the path's cubic
/// term (a changing acceleration) into its velocity. The cubic over the widest window estimates
/// that term and the noise (its residuals); from them each candidate's error is predicted as
/// `bias^2 + variance`, the cubic term's own noise discounted so a straight path is not read as
/// curved (and ignored unless it is far above that noise). Where the samples cannot support a
/// cubic with residual degrees of freedom, the short window's own choice ([`fit_short`]). The
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
    let Some(choices) = Choices::new(windows, past, t_eval_s) else {
        return fit_short(widest, t_eval_s);
    };
    let noise = choices.cubic.noise_variance();
    let mut position = Vector3::zeros();
    let mut velocity = Vector3::zeros();
    let mut error = UncertaintyBudget {
        noise_variance: noise,
        noise_dof: (choices.cubic.samples - 4) as f64,
        cubic_term: Vector3::zeros(),
        cubic_term_gain: choices.cubic_term_gain,
        velocity: QuantityBudget::from_noise_gain(0.0),
        position: QuantityBudget::from_noise_gain(0.0),
    };
    let mut choice = [FitChoice {
        half_window_frames: widest.half_window_frames as u8,
        order: 3,
    }; 3];
    for c in 0..3 {
        let (best, chosen, cubic_term) = choices.best(c, noise[c]);
        position[c] = best.position;
        velocity[c] = best.velocity;
        error.cubic_term[c] = cubic_term;
        error.velocity.set_component(c, best.velocity_budget);
        error.position.set_component(c, best.position_budget);
        if let Some(chosen) = chosen {
            choice[c] = chosen;
        }
    }
    MotionFit {
        position: Point3::from(position),
        velocity,
        rms_residual: widest.quadratic.rms_residual(),
        error,
    }
    .finite()
    .map(|fit| AdaptiveFit { fit, choice })
}

/// The fit of a window too short for a cubic with residual degrees of freedom (fewer than
/// seven samples: a fast particle seen for a few frames), chosen per component among the
/// quadratic over the whole window, the cubic through the same samples and the quadratic
/// through the three samples nearest the centre (the position is the quadratic's). Their
/// biases are stated from the path's turning rate as the quadratic shows it: a path turning at
/// rate w has a cubic term of w^2/6 of its velocity and a fifth-order one of w^4/120 (exactly
/// so on a circle), so the quadratic over +-2 frames, which takes in 3.4 times the cubic term,
/// is 5 % slow on a path turning by 0.3 rad a frame, and its three innermost samples 1.5 %.
fn fit_short(widest: &QuadraticWindow, t_eval_s: f64) -> Option<AdaptiveFit> {
    let quadratic = &widest.quadratic;
    let whole = FitChoice {
        half_window_frames: widest.half_window_frames as u8,
        order: 2,
    };
    let others = other_short_fits(widest, t_eval_s);
    let fits: Vec<(&PolynomialFit, FitChoice)> = std::iter::once((quadratic, whole))
        .chain(others.iter().map(|(f, c)| (f, *c)))
        .collect();
    let sensitivities: Vec<Sensitivity> = fits.iter().map(|(f, _)| f.sensitivity()).collect();
    let (noise, turning) = short_noise_and_turning(quadratic, &sensitivities[0]);
    let mut motion = quadratic.motion();
    motion.error.noise_variance = noise;
    let mut choice = [whole; 3];
    for c in 0..3 {
        let speed = quadratic.velocity(c);
        let (cubic_term, fifth_term) = (turning * speed / 6.0, turning * turning * speed / 120.0);
        let expected = |k: usize| {
            let per_term = &sensitivities[k].velocity.per_term;
            (per_term[3] * cubic_term + per_term[5] * fifth_term).powi(2)
                + fits[k].0.velocity_variance(noise[c])
        };
        let best = (0..fits.len())
            .min_by(|&a, &b| expected(a).total_cmp(&expected(b)))
            .unwrap_or(0);
        motion.velocity[c] = fits[best].0.velocity(c);
        choice[c] = fits[best].1;
        motion.error.cubic_term[c] = cubic_term;
        // The position stays the whole window's quadratic's: at the centre of a symmetric
        // window no odd term biases it, and it averages the most noise.
        let fourth_term = quadratic
            .quadratic_term(c, noise[c])
            .map_or(0.0, |(q, _)| turning * q / 12.0);
        let budgets = [
            (&sensitivities[best], fifth_term),
            (&sensitivities[0], fourth_term),
        ];
        set_short_budget(&mut motion.error, c, budgets);
    }
    motion.finite().map(|fit| AdaptiveFit { fit, choice })
}

/// The fits a short window's quadratic competes with: the cubic through its samples (where
/// they leave it a residual degree of freedom) and the quadratic through its three innermost.
fn other_short_fits(widest: &QuadraticWindow, t_eval_s: f64) -> Vec<(PolynomialFit, FitChoice)> {
    let cubic = PolynomialFit::new(&widest.samples, t_eval_s, 3)
        .filter(|c| c.dof() > 0)
        .map(|cubic| {
            let choice = FitChoice {
                half_window_frames: widest.half_window_frames as u8,
                order: 3,
            };
            (cubic, choice)
        });
    let inner = innermost_quadratic(&widest.samples, t_eval_s).map(|inner| {
        let choice = FitChoice {
            half_window_frames: 1,
            order: 2,
        };
        (inner, choice)
    });
    cubic.into_iter().chain(inner).collect()
}

/// Component `c` of a short fit's budget: for the velocity and for the position, the fit's noise
/// gain, the cubic term it takes in (the budget holds the term) and the bias the turning path's
/// next term leaves it (fifth-order for the velocity, fourth-order for the position), each
/// given as the fit's sensitivity and that term.
fn set_short_budget(error: &mut UncertaintyBudget, c: usize, budgets: [(&Sensitivity, f64); 2]) {
    let [(velocity, fifth_term), (position, fourth_term)] = budgets;
    let component = |response: &TermResponse, power: usize, term: f64| ComponentBudget {
        noise_gain: response.gain,
        bias_sq: (response.per_term[power] * term).powi(2),
        cubic_absorption: response.per_term[3],
        misfit_gain: 0.0,
    };
    error
        .velocity
        .set_component(c, component(&velocity.velocity, 5, fifth_term));
    error
        .position
        .set_component(c, component(&position.position, 4, fourth_term));
}

/// A short window's sample noise and its path's turning rate squared. On a turning path the
/// quadratic's residuals hold the cubic term it cannot follow as well as the noise: read as
/// noise, the misfit would hide the turn. So the turning rate is read with the residuals as
/// noise, the misfit that turn leaves taken out of them (by the quadratic's `sensitivity`), and
/// the rate read again.
fn short_noise_and_turning(
    quadratic: &PolynomialFit,
    sensitivity: &Sensitivity,
) -> (Vector3<f64>, f64) {
    let unfollowed = sensitivity.unfollowed_norm_sq[3];
    let dof = quadratic.dof().max(1) as f64;
    let mut noise = quadratic.noise_variance();
    let mut turning = turning_rate_sq(quadratic, &noise);
    for _ in 0..2 {
        noise = Vector3::from_fn(|c, _| {
            let cubic_term = turning * quadratic.velocity(c) / 6.0;
            (quadratic.squared_residuals[c] - unfollowed * cubic_term * cubic_term).max(0.0) / dof
        });
        turning = turning_rate_sq(quadratic, &noise);
    }
    (noise, turning)
}

/// The quadratic through the sample at `t_eval_s`'s frame and the one each side of it (the
/// three nearest in time, where they straddle it).
fn innermost_quadratic(samples: &[(f64, Point3<f64>)], t_eval_s: f64) -> Option<PolynomialFit> {
    let mut nearest: Vec<(f64, Point3<f64>)> = samples.to_vec();
    nearest.sort_by(|a, b| (a.0 - t_eval_s).abs().total_cmp(&(b.0 - t_eval_s).abs()));
    nearest.truncate(3);
    let straddles =
        nearest.iter().any(|s| s.0 < t_eval_s) && nearest.iter().any(|s| s.0 > t_eval_s);
    (nearest.len() == 3 && straddles)
        .then(|| PolynomialFit::new(&nearest, t_eval_s, 2))
        .flatten()
}

/// The candidate fits of a track's windows, fitted once for all three components.
struct Choices<'a> {
    /// The widest window's quadratic: the reference for the path's acceleration and turning.
    reference: &'a PolynomialFit,
    cubic: PolynomialFit,
    cubic_sensitivity: Sensitivity,
    quadratics: Vec<(usize, &'a PolynomialFit, Sensitivity)>,
    past_line: Option<(&'a QuadraticWindow, PolynomialFit, Sensitivity)>,
    /// The path's turning rate squared (`turning_rate_sq`).
    turning: f64,
    scale3: f64,
    cubic_term_gain: f64,
}

/// What a component's path terms are, for stating each candidate's bias.
struct PathTerms {
    c: usize,
    sigma2: f64,
    /// The fifth-order term of a turning path.
    fifth_term: f64,
    /// The acceleration's half squared, and the fourth-order term squared.
    half_acceleration_sq: f64,
    fourth_term_sq: f64,
}

impl<'a> Choices<'a> {
    /// `None` where the widest window cannot support a cubic with residual degrees of freedom
    /// (its noise estimate needs them to mean anything).
    fn new(
        windows: &'a [QuadraticWindow],
        past: Option<&'a QuadraticWindow>,
        t_eval_s: f64,
    ) -> Option<Self> {
        let widest = windows.last()?;
        let cubic =
            PolynomialFit::new(&widest.samples, t_eval_s, 3).filter(|c| c.samples >= 4 + 3)?;
        let cubic_sensitivity = cubic.sensitivity();
        let quadratics = windows
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
        let turning = turning_rate_sq(&widest.quadratic, &cubic.noise_variance());
        let scale3 = cubic.scale_s.powi(3);
        let cubic_term_gain = cubic.inverse_normal[(3, 3)] / (scale3 * scale3);
        Some(Self {
            reference: &widest.quadratic,
            cubic,
            cubic_sensitivity,
            quadratics,
            past_line,
            turning,
            scale3,
            cubic_term_gain,
        })
    }

    /// Component `c`'s best candidate at sample noise `sigma2`, the fit chosen where it is not
    /// the cubic, and the cubic term the cubic estimates.
    fn best(&self, c: usize, sigma2: f64) -> (Candidate, Option<FitChoice>, f64) {
        let d = self.cubic.coefficients[(3, c)] / self.scale3;
        let d_variance = sigma2 * self.cubic_term_gain;
        // The cubic term counts for the choice only where it stands out of its own noise by a
        // wide margin (z^2 > 32): with a noise level estimated from a handful of residuals, a
        // laxer test reads noise as curvature on straight paths and trades the quadratic's
        // precision for nothing. The error a fit states is another matter: there the cubic
        // term counts as `UncertaintyBudget::sigmas` weighs it.
        const CUBIC_SIGNIFICANCE: f64 = 32.0;
        let d2 = if d * d > CUBIC_SIGNIFICANCE * d_variance {
            d * d - d_variance
        } else {
            0.0
        };
        let terms = self.path_terms(c, sigma2);
        let mut chosen = None;
        let mut best = self.candidate(&terms, &self.cubic, &self.cubic_sensitivity, 0.0, 0.0);
        for (m, fit, sensitivity) in &self.quadratics {
            let bias = sensitivity.velocity.per_term[3];
            let expected = d2 * bias * bias + fit.velocity_variance(sigma2);
            // Ties go to the quadratic (the method's fit), then to the wider window.
            if expected <= best.expected_sq {
                best = self.candidate(&terms, fit, sensitivity, d2 * bias * bias, 0.0);
                chosen = Some(FitChoice {
                    half_window_frames: *m as u8,
                    order: 2,
                });
            }
        }
        if let Some((line, choice)) = self.past_line_candidate(&terms, d2, best.expected_sq) {
            best = line;
            chosen = Some(choice);
        }
        (best, chosen, d)
    }

    /// The line into the past as component `c`'s candidate, where it beats `to_beat`.
    fn past_line_candidate(
        &self,
        terms: &PathTerms,
        d2: f64,
        to_beat: f64,
    ) -> Option<(Candidate, FitChoice)> {
        let (past, line, sensitivity) = self.past_line.as_ref()?;
        let (q, q_variance) = past.quadratic.quadratic_term(terms.c, terms.sigma2)?;
        // The acceleration's square, its own noise taken out (unbiased, floored at 0).
        let q2 = (q * q - q_variance).max(0.0);
        let (b2, b3) = (
            sensitivity.velocity.per_term[2],
            sensitivity.velocity.per_term[3],
        );
        let bias_sq = q2 * b2 * b2 + d2 * b3 * b3;
        (bias_sq + line.velocity_variance(terms.sigma2) < to_beat).then(|| {
            let candidate = self.candidate(terms, line, sensitivity, bias_sq, q2 * b2 * b2);
            let choice = FitChoice {
                half_window_frames: past.half_window_frames as u8,
                order: 1,
            };
            (candidate, choice)
        })
    }

    /// The path terms of component `c` no candidate models: a path turning at rate w has a
    /// fifth derivative of w^4 times its velocity (exactly so on a circle), stated as each fit's
    /// velocity bias; the position's are the acceleration (half of it: a line's), the cubic
    /// term, and the fourth-order term of a turning path (w^2 times its acceleration, on a
    /// circle).
    fn path_terms(&self, c: usize, sigma2: f64) -> PathTerms {
        let fifth_term = self.turning * self.turning * self.reference.velocity(c) / 120.0;
        let half_acceleration_sq = self
            .reference
            .quadratic_term(c, sigma2)
            .map_or(0.0, |(q, q_variance)| (q * q - q_variance).max(0.0));
        let fourth_term_sq =
            self.turning * self.turning * 4.0 * half_acceleration_sq / (24.0 * 24.0);
        PathTerms {
            c,
            sigma2,
            fifth_term,
            half_acceleration_sq,
            fourth_term_sq,
        }
    }

    /// A fit as a candidate for one component: its expected squared error (`bias_sq` plus its
    /// noise), and the budget it states (`bias_sq_stated` plus the turning path's terms).
    fn candidate(
        &self,
        terms: &PathTerms,
        fit: &PolynomialFit,
        sensitivity: &Sensitivity,
        bias_sq: f64,
        bias_sq_stated: f64,
    ) -> Candidate {
        let (velocity_bias, position_bias) = (
            &sensitivity.velocity.per_term,
            &sensitivity.position.per_term,
        );
        let bias_sq_stated = bias_sq_stated + (velocity_bias[5] * terms.fifth_term).powi(2);
        let position_bias_sq = position_bias[2].powi(2) * terms.half_acceleration_sq
            + position_bias[4].powi(2) * terms.fourth_term_sq;
        let unfollowed = &self.cubic_sensitivity.unfollowed_norm_sq;
        let misfit_gain = |per_term: f64, norm_sq: f64| {
            if norm_sq > 0.0 {
                per_term * per_term / norm_sq
            } else {
                0.0
            }
        };
        Candidate {
            expected_sq: bias_sq + fit.velocity_variance(terms.sigma2),
            position: fit.position(terms.c),
            velocity: fit.velocity(terms.c),
            velocity_budget: ComponentBudget {
                noise_gain: sensitivity.velocity.gain,
                bias_sq: bias_sq_stated,
                cubic_absorption: velocity_bias[3],
                misfit_gain: misfit_gain(velocity_bias[5], unfollowed[5]),
            },
            position_budget: ComponentBudget {
                noise_gain: sensitivity.position.gain,
                bias_sq: position_bias_sq,
                cubic_absorption: position_bias[3],
                misfit_gain: misfit_gain(position_bias[4], unfollowed[4]),
            },
        }
    }
}

/// The square of the rate at which the path turns (or changes speed), per second: its
/// acceleration over its speed, from the widest quadratic's terms with their noise taken out
/// (`sigma2`, the sample noise variance per component); 0 where the path is straight or at rest.
fn turning_rate_sq(quadratic: &PolynomialFit, sigma2: &Vector3<f64>) -> f64 {
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
        error: UncertaintyBudget::from_noise(
            if dof == 0 {
                Vector3::zeros()
            } else {
                squared_by_component / dof as f64
            },
            dof as f64,
            1.0 / stt,
            1.0 / n + mean_t * mean_t / stt,
        ),
    };
    fit.finite()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::velocity::uncertainty::ScenePrior;
    use proptest::prelude::*;

    #[test]
    fn a_predicted_quadratic_position_is_the_full_fits() {
        let path = |t: f64| Point3::new(0.1 + 0.5 * t + 2.0 * t * t, -0.2 * t, 1.0 + 0.3 * t * t);
        let mut rng = crate::synth::Rng::new(5);
        let samples: Vec<(f64, Point3<f64>)> = (0..6)
            .map(|k| {
                let t = f64::from(k) / 30.0;
                let noise = Vector3::new(rng.normal(), rng.normal(), rng.normal()) * 1e-3;
                (t, path(t) + noise)
            })
            .collect();
        // Ahead of the samples, as a prediction asks.
        let t = 7.0 / 30.0;
        let full = fit_quadratic(&samples, t).expect("fits").position;
        let light = quadratic_position(&samples, t).expect("fits");
        assert!((full - light).norm() < 1e-12, "{full} vs {light}");
        assert!(quadratic_position(&samples[..2], t).is_none());
        let same_time = [(0.1, path(0.1)); 3];
        assert!(quadratic_position(&same_time, 0.1).is_none());
    }

    #[test]
    fn samples_seen_by_one_camera_count_across_its_line_of_sight_only() {
        let path = |t: f64| Point3::new(0.02 + 0.5 * t + 2.0 * t * t, -0.2 * t, 0.5 + 0.3 * t);
        let camera = Point3::new(0.1, 0.0, 0.0);
        // Three of eleven samples hidden in one camera: on the other one's line of sight, but
        // 3 cm off along it (where their tracks predicted them).
        let hidden = [-4, -1, 3];
        let (samples, sights): (Vec<_>, Vec<_>) = (-5..=5)
            .map(|k| {
                let t = f64::from(k) / 30.0;
                let p = path(t);
                if hidden.contains(&k) {
                    let off = (p - camera).normalize() * 0.03;
                    ((t, p + off), Some(camera))
                } else {
                    ((t, p), None)
                }
            })
            .unzip();
        let truth = Vector3::new(0.5, -0.2, 0.3);
        let window = QuadraticWindow::with_sights(5, samples.clone(), &sights, 0.0).expect("fits");
        let error = (window.motion().expect("finite").velocity - truth).norm();
        assert!(error < 1e-9 * truth.norm(), "{error}");
        // Taken as measured where they were placed, they pull the velocity off.
        let naive = QuadraticWindow::new(5, samples, 0.0).expect("fits");
        let naive_error = (naive.motion().expect("finite").velocity - truth).norm();
        assert!(naive_error > 0.02 * truth.norm(), "{naive_error}");
    }

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
                let known = UncertaintyBudget {
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
            let mut without = fit.fit.error;
            without.velocity.misfit_gain = Vector3::zeros();
            let without = without.sigmas(Some(&prior)).0;
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

    /// A particle on a circle at 30 Hz, moving 3 cm and turning by `turn` radians a frame, seen
    /// for the five frames around the centre, with `noise_m` of noise: its +-2 window, and its
    /// velocity at the centre.
    fn short_circle(turn: f64, noise_m: f64) -> (QuadraticWindow, Vector3<f64>) {
        let (dt, step_m, phase): (f64, f64, f64) = (1.0 / 30.0, 0.03, 0.4);
        let (omega, radius) = (turn / dt, step_m / turn);
        let centre = Point3::new(-radius * phase.cos(), -radius * phase.sin(), 0.5);
        let noise = |k: i32| noise_m * f64::from((k * 7919).rem_euclid(13) - 6) / 6.0;
        let samples = (-2..=2)
            .map(|k| {
                let t = f64::from(k) * dt;
                let angle = omega * t + phase;
                let p = centre + Vector3::new(angle.cos(), angle.sin(), 0.0) * radius;
                (t, p + Vector3::repeat(noise(k)))
            })
            .collect();
        let velocity = Vector3::new(-phase.sin(), phase.cos(), 0.0) * radius * omega;
        (
            QuadraticWindow::new(2, samples, 0.0).expect("fit"),
            velocity,
        )
    }

    /// A vortex turning its particles by 0.3 rad a frame: the quadratic over the five frames
    /// around the centre is 5 % slow; the fit chosen for so short a window follows the turn.
    #[test]
    fn a_fast_turning_particle_seen_for_five_frames_gets_an_unbiased_velocity() {
        let (window, truth) = short_circle(0.3, 1e-5);
        let quadratic = window.motion().expect("fit");
        let chosen = fit_adaptive(std::slice::from_ref(&window), None, 0.0).expect("fit");
        let relative = |v: Vector3<f64>| (v - truth).norm() / truth.norm();
        assert!(relative(quadratic.velocity) > 0.04, "{quadratic:?}");
        assert!(relative(chosen.fit.velocity) < 0.01, "{chosen:?}");
        // The stated error covers the chosen fit's.
        let (stated, _) = chosen.fit.error.sigmas(None);
        assert!(
            (chosen.fit.velocity - truth).norm() < 3.0 * stated.norm(),
            "{stated:?}"
        );
    }

    /// A straight path seen for five frames keeps the quadratic over all of them: the fits
    /// that follow a turn only add noise there.
    #[test]
    fn a_straight_path_seen_for_five_frames_keeps_its_quadratic() {
        let (window, truth) = short_circle(1e-6, 1e-3);
        let chosen = fit_adaptive(std::slice::from_ref(&window), None, 0.0).expect("fit");
        let whole = FitChoice {
            half_window_frames: 2,
            order: 2,
        };
        assert_eq!(chosen.choice, [whole; 3]);
        assert!((chosen.fit.velocity - truth).norm() < 0.05 * truth.norm());
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

    /// Uniform motion: the line through 21 frames has 0.38 of the centred quadratic's noise. It
    /// is left out where the noise happens to look like an acceleration, so the RMS error falls
    /// by about a third, not more.
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
