//! What each vector's stated 1-sigma errors rest on: a fit's [`UncertaintyBudget`] (the sample
//! noise its residuals show and how the fitted velocity and position respond to noise and to
//! the path terms the fit does not reach), weighed against what the scene's other tracks show
//! ([`ScenePrior`], learnt by the scene pool).

use std::collections::VecDeque;

use nalgebra::Vector3;

use crate::spatial::median;

/// How one fitted quantity (velocity or position) responds, per component (x, y, z): its variance
/// per unit of sample noise variance (the fit is linear in the samples), the squared bias stated
/// from path terms other than the cubic one, how much of the path's cubic term it takes in (0
/// for a cubic), and its squared bias per unit of misfit (residual energy beyond what the sample
/// noise explains, read as the path's next terms the cubic leaves in its residuals: fifth-order
/// for the velocity, fourth-order for the position).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct QuantityBudget {
    /// Variance per unit of sample noise variance.
    pub noise_gain: Vector3<f64>,
    /// Squared bias from the path terms stated, other than the cubic one.
    pub bias_sq: Vector3<f64>,
    /// What the quantity takes in of a unit cubic term.
    pub cubic_absorption: Vector3<f64>,
    /// Squared bias per unit of misfit.
    pub misfit_gain: Vector3<f64>,
}

impl QuantityBudget {
    /// A quantity that responds to noise alone, with the same gain in every component.
    pub fn from_noise_gain(gain: f64) -> Self {
        Self {
            noise_gain: Vector3::repeat(gain),
            bias_sq: Vector3::zeros(),
            cubic_absorption: Vector3::zeros(),
            misfit_gain: Vector3::zeros(),
        }
    }

    /// Component `c` of this budget.
    pub fn component(&self, c: usize) -> ComponentBudget {
        ComponentBudget {
            noise_gain: self.noise_gain[c],
            bias_sq: self.bias_sq[c],
            cubic_absorption: self.cubic_absorption[c],
            misfit_gain: self.misfit_gain[c],
        }
    }

    /// Sets component `c` of this budget.
    pub fn set_component(&mut self, c: usize, budget: ComponentBudget) {
        self.noise_gain[c] = budget.noise_gain;
        self.bias_sq[c] = budget.bias_sq;
        self.cubic_absorption[c] = budget.cubic_absorption;
        self.misfit_gain[c] = budget.misfit_gain;
    }

    /// 1-sigma error per component at sample noise variance `noise`, squared cubic term
    /// `cubic_sq` and misfit `misfit`.
    fn sigmas(
        &self,
        noise: &Vector3<f64>,
        cubic_sq: &Vector3<f64>,
        misfit: &Vector3<f64>,
    ) -> Vector3<f64> {
        Vector3::from_fn(|c, _| {
            (self.noise_gain[c] * noise[c]
                + self.bias_sq[c]
                + self.cubic_absorption[c].powi(2) * cubic_sq[c]
                + self.misfit_gain[c] * misfit[c])
                .sqrt()
        })
    }
}

/// One component of a [`QuantityBudget`].
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ComponentBudget {
    /// Variance per unit of sample noise variance.
    pub noise_gain: f64,
    /// Squared bias from the path terms stated, other than the cubic one.
    pub bias_sq: f64,
    /// What the quantity takes in of a unit cubic term.
    pub cubic_absorption: f64,
    /// Squared bias per unit of misfit.
    pub misfit_gain: f64,
}

/// A fit's uncertainty budget: the sample noise its residuals show, the path's cubic term as
/// the window's cubic fit estimates it, and how the velocity and the position respond to each.
///
/// The noise estimate rests on few residuals (a window of 11 samples leaves 7 degrees of
/// freedom to a cubic), so a caller that knows a typical noise for the scene pools it in
/// ([`Self::sigmas`]) rather than let one window's luck decide.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct UncertaintyBudget {
    /// Sample noise variance per component, from the residuals.
    pub noise_variance: Vector3<f64>,
    /// Degrees of freedom behind `noise_variance` (0: the samples say nothing about it).
    pub noise_dof: f64,
    /// The path's cubic term as the window's cubic fit estimates it (0 without one).
    pub cubic_term: Vector3<f64>,
    /// The cubic term's variance per unit of sample noise variance.
    pub cubic_term_gain: f64,
    /// How the velocity responds.
    pub velocity: QuantityBudget,
    /// How the position responds.
    pub position: QuantityBudget,
}

/// What a scene's other tracks say about any one window: a typical sample noise variance per
/// component with the degrees of freedom it is worth against a window's own estimate, and per
/// component where the scene's paths plainly curve, the spread of their cubic term across the
/// scene's windows (its variance, noise taken out).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScenePrior {
    /// The scene's typical sample noise variance where this window is.
    pub noise_variance: Vector3<f64>,
    /// Degrees of freedom that is worth.
    pub noise_dof: f64,
    /// The spread (variance) of the paths' cubic terms, where they plainly curve.
    pub cubic_term_spread: [Option<f64>; 3],
}

impl UncertaintyBudget {
    /// A fit's budget from its sample noise alone (per component, with its degrees of freedom)
    /// and its velocity and position gains: no path term stated.
    pub fn from_noise(
        noise_variance: Vector3<f64>,
        noise_dof: f64,
        velocity_gain: f64,
        position_gain: f64,
    ) -> Self {
        Self {
            noise_variance,
            noise_dof,
            cubic_term: Vector3::zeros(),
            cubic_term_gain: 0.0,
            velocity: QuantityBudget::from_noise_gain(velocity_gain),
            position: QuantityBudget::from_noise_gain(position_gain),
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
        let misfit = self.misfit(prior);
        let cubic_sq = self.cubic_term_sq(prior, &self.cubic_term_variance(&noise));
        (
            self.velocity.sigmas(&noise, &cubic_sq, &misfit),
            self.position.sigmas(&noise, &cubic_sq, &misfit),
        )
    }

    /// Residual energy beyond what the scene's noise explains: the path's higher-order terms,
    /// taken whole (fourth order and up, whatever their phase) as an envelope of the
    /// fifth-order term's size. Counted only where the window's noise estimate is plainly above
    /// the scene's (a chi-square of 7 degrees of freedom passes twice its mean by chance 5 % of
    /// the time): counting every chance excess would state straight paths' errors several times
    /// too large.
    fn misfit(&self, prior: Option<&ScenePrior>) -> Vector3<f64> {
        const SIGNIFICANT_EXCESS: f64 = 2.0;
        match prior {
            Some(p) if p.noise_dof > 0.0 => Vector3::from_fn(|c, _| {
                let (window, scene) = (self.noise_variance[c], p.noise_variance[c]);
                if window > SIGNIFICANT_EXCESS * scene {
                    (window - scene) * self.noise_dof
                } else {
                    0.0
                }
            }),
            _ => Vector3::zeros(),
        }
    }

    /// The squared cubic term per component, its estimate's variance `cubic_variance` taken
    /// into account: under the scene's spread where it is known (the posterior mean of `d^2`
    /// under a zero-mean Gaussian prior of variance `tau2`), else the window's own unbiased
    /// estimate of `d^2`.
    fn cubic_term_sq(
        &self,
        prior: Option<&ScenePrior>,
        cubic_variance: &Vector3<f64>,
    ) -> Vector3<f64> {
        Vector3::from_fn(|c, _| {
            let (d, v) = (self.cubic_term[c], cubic_variance[c]);
            match prior.and_then(|p| p.cubic_term_spread[c]) {
                Some(tau2) if tau2 > 0.0 => {
                    let shrunk = d * tau2 / (tau2 + v);
                    shrunk * shrunk + tau2 * v / (tau2 + v)
                }
                _ => (d * d - v).max(0.0),
            }
        })
    }
}

/// What the scene's tracks have shown so far, for judging any one window: the typical centroid
/// noise, learnt from the tracks' own fit residuals as a disparity noise variance (pixels
/// squared), and how large the paths' cubic terms typically are.
///
/// Each vector's uncertainty rests on its window's residuals, which are few (7 degrees of
/// freedom for 11 samples): alone, their luck would make some sigmas far too small. Pooled with
/// what the scene's other tracks show (scaled to this particle's depth and line of sight by the
/// triangulation's geometry), the estimate steadies while a particle noisier than the rest
/// still shows it. Likewise a window's cubic term, estimated from few samples, is weighed
/// against the spread the scene's windows show ([`UncertaintyBudget::sigmas`]).
#[derive(Debug, Clone, Default)]
pub(crate) struct ScenePool {
    /// Recent windows' noise per unit disparity variance.
    noise_ratios: VecDeque<f64>,
    /// Recent windows' cubic terms squared and their estimates' variances, per component.
    cubic_terms: VecDeque<(Vector3<f64>, Vector3<f64>)>,
    /// What the windows above say, worked out once a frame (`refresh`): every vector of a
    /// frame is judged by the same pool.
    pub(crate) noise_variance: Option<f64>,
    pub(crate) cubic_term_spread: [Option<f64>; 3],
}

impl ScenePool {
    const CAPACITY: usize = 511;
    /// Windows needed before the pool is trusted.
    const MIN_WINDOWS: usize = 16;
    /// Degrees of freedom the pooled estimate is worth against a window's own.
    pub(crate) const WEIGHT_DOF: f64 = 10.0;

    fn push<T>(queue: &mut VecDeque<T>, item: T) {
        if queue.len() == Self::CAPACITY {
            queue.pop_front();
        }
        queue.push_back(item);
    }

    /// Learns a window's noise per unit disparity variance.
    pub(crate) fn add_noise(&mut self, ratio: f64) {
        if ratio.is_finite() && ratio > 0.0 {
            Self::push(&mut self.noise_ratios, ratio);
        }
    }

    /// Learns a window's cubic term and that estimate's variance.
    pub(crate) fn add_cubic_term(&mut self, term: Vector3<f64>, variance: Vector3<f64>) {
        if term.iter().chain(variance.iter()).all(|v| v.is_finite()) {
            Self::push(&mut self.cubic_terms, (term.map(|d| d * d), variance));
        }
    }

    /// Works out what the pool says from the windows added so far.
    ///
    /// The disparity noise variance: the median window, corrected for the median of a
    /// chi-square sitting below its mean (Wilson-Hilferty, at a typical window's 21 degrees
    /// of freedom: three components of 11 samples less a cubic's 4 terms).
    ///
    /// The spread of the paths' cubic terms per component (see `spread_of_terms`), where the
    /// paths plainly curve.
    pub(crate) fn refresh(&mut self) {
        self.noise_variance = (self.noise_ratios.len() >= Self::MIN_WINDOWS).then(|| {
            let mut sorted: Vec<f64> = self.noise_ratios.iter().copied().collect();
            const TYPICAL_DOF: f64 = 21.0;
            median(&mut sorted) / (1.0 - 2.0 / (9.0 * TYPICAL_DOF)).powi(3)
        });
        self.cubic_term_spread = [0, 1, 2].map(|c| self.cubic_spread(c));
    }

    /// The spread of component `c`'s cubic terms, where it exceeds what a typical window
    /// resolves: only then does it say the paths curve. Straight flows show a spread well below
    /// a window's own variance, curving ones far above it; counting the spread that straight
    /// paths' noise shows would state their errors larger than they are, as lines reaching into
    /// the past take in much of a cubic term.
    fn cubic_spread(&self, c: usize) -> Option<f64> {
        if self.cubic_terms.len() < Self::MIN_WINDOWS {
            return None;
        }
        let terms: Vec<(f64, f64)> = self
            .cubic_terms
            .iter()
            .map(|(d2, v)| (d2[c], v[c]))
            .collect();
        let tau2 = spread_of_terms(&terms);
        let mut variances: Vec<f64> = terms.iter().map(|(_, v)| *v).collect();
        (tau2 > median(&mut variances)).then_some(tau2)
    }
}

/// The variance `tau2` of a term spread across windows, from each window's estimate squared and
/// that estimate's own variance `v` (`terms`): estimate over `sqrt(tau2 + v)` is a standard
/// normal, whose square has a median of 0.455, so `tau2` is where the median of
/// `estimate^2 / (tau2 + v)` comes to that. A median, so a few sharply turning paths do not
/// set it; per window, so windows of different noise (near and far particles) are each judged
/// against their own. 0 where the estimates are no larger than their noise.
fn spread_of_terms(terms: &[(f64, f64)]) -> f64 {
    let above_median = |tau2: f64| median_ratio_exceeds(terms, tau2, MEDIAN_OF_CHI_SQUARE_1);
    if terms.is_empty() || !above_median(0.0) {
        return 0.0;
    }
    let mut high = terms.iter().map(|(d2, _)| *d2).fold(0.0, f64::max);
    while above_median(high) && high.is_finite() {
        high *= 2.0;
    }
    // The median ratio falls as tau2 grows: bisect geometrically from twelve decades below
    // to a relative precision of about 1e-6 (below that, tau2 is nothing next to the noise).
    let mut low = high * 1e-12;
    if !above_median(low) {
        return 0.0;
    }
    for _ in 0..24 {
        let middle = (low * high).sqrt();
        if above_median(middle) {
            low = middle;
        } else {
            high = middle;
        }
    }
    (low * high).sqrt()
}

/// The median of a chi-square variable of one degree of freedom.
const MEDIAN_OF_CHI_SQUARE_1: f64 = 0.455;

/// Whether the median of `estimate^2 / (tau2 + v)` over `terms` is above `level`. Of an odd
/// count, the median is above it where more than half the ratios are: a count, no sorting.
fn median_ratio_exceeds(terms: &[(f64, f64)], tau2: f64, level: f64) -> bool {
    let ratio = |&(d2, v): &(f64, f64)| d2 / (tau2 + v).max(f64::MIN_POSITIVE);
    if terms.len() % 2 == 1 {
        let above = terms.iter().filter(|t| ratio(t) > level).count();
        return 2 * above > terms.len();
    }
    let mut ratios: Vec<f64> = terms.iter().map(ratio).collect();
    median(&mut ratios) > level
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Terms drawn with spread `tau2`, each estimated with a noise whose variance varies a
    /// hundredfold between windows (near and far particles).
    fn drawn_terms(tau2: f64, seed: u64) -> Vec<(f64, f64)> {
        let mut rng = crate::synth::Rng::new(seed);
        (0..511)
            .map(|_| {
                let v = 10f64.powf(rng.range(-1.0, 1.0));
                let d = rng.normal() * tau2.sqrt() + rng.normal() * v.sqrt();
                (d * d, v)
            })
            .collect()
    }

    #[test]
    fn the_spread_of_terms_is_told_from_their_noise() {
        for (tau2, seed) in [(0.3, 1), (3.0, 2), (30.0, 3)] {
            let estimate = spread_of_terms(&drawn_terms(tau2, seed));
            assert!(
                (estimate / tau2 - 1.0).abs() < 0.25,
                "tau2 {tau2}: estimated {estimate}"
            );
        }
        // No spread: estimates no larger than their noise say nothing is there.
        let none: Vec<f64> = (4..9)
            .map(|seed| spread_of_terms(&drawn_terms(0.0, seed)))
            .collect();
        assert!(none.iter().all(|&t| t < 0.1), "{none:?}");
        assert_eq!(spread_of_terms(&[]), 0.0);
    }

    #[test]
    fn the_median_ratio_test_agrees_with_the_sorted_median() {
        // Odd counts are counted, even ones sorted: both as the median of the sorted ratios,
        // at levels around it and at a level equal to one of the ratios.
        for n in [1, 2, 15, 16, 510, 511] {
            let terms = &drawn_terms(2.0, n as u64)[..n];
            for tau2 in [0.0, 0.5, 4.0, f64::INFINITY] {
                let mut ratios: Vec<f64> = terms
                    .iter()
                    .map(|&(d2, v)| d2 / (tau2 + v).max(f64::MIN_POSITIVE))
                    .collect();
                let m = median(&mut ratios.clone());
                ratios.sort_by(f64::total_cmp);
                for level in [0.0, 0.455, m * 0.999, m, m * 1.001, ratios[n / 2], 1e9] {
                    assert_eq!(
                        median_ratio_exceeds(terms, tau2, level),
                        m > level,
                        "{n} terms, tau2 {tau2}, level {level}"
                    );
                }
            }
        }
    }

    #[test]
    fn a_pooled_noise_counts_in_proportion_to_its_degrees_of_freedom() {
        let mut budget =
            UncertaintyBudget::from_noise(Vector3::new(4.0, 4.0, 4.0), 10.0, 1.0, 0.25);
        budget.velocity.bias_sq = Vector3::new(0.0, 9.0, 0.0);
        let prior = ScenePrior {
            noise_variance: Vector3::repeat(1.0),
            noise_dof: 30.0,
            cubic_term_spread: [None; 3],
        };
        let (v, p) = budget.sigmas(Some(&prior));
        // (10 * 4 + 30 * 1) / 40 = 1.75.
        assert!((v.x - 1.75f64.sqrt()).abs() < 1e-12);
        assert!((v.y - (1.75f64 + 9.0).sqrt()).abs() < 1e-12, "bias adds");
        assert!((p.x - (0.25 * 1.75f64).sqrt()).abs() < 1e-12);
        let (alone, _) = budget.sigmas(None);
        assert!((alone.x - 2.0).abs() < 1e-12);
    }

    fn budget() -> UncertaintyBudget {
        let mut budget = UncertaintyBudget::from_noise(Vector3::new(4.0, 0.5, 4.0), 7.0, 1.0, 1.0);
        budget.cubic_term = Vector3::new(0.0, 0.0, 3.0);
        budget.cubic_term_gain = 0.5;
        budget.velocity.cubic_absorption = Vector3::new(0.0, 0.0, 2.0);
        budget.velocity.misfit_gain = Vector3::new(0.1, 0.1, 0.0);
        budget.position.misfit_gain = Vector3::new(0.2, 0.0, 0.0);
        budget
    }

    #[test]
    fn residual_energy_beyond_the_scene_noise_counts_as_the_paths_shape() {
        let prior = ScenePrior {
            noise_variance: Vector3::repeat(1.0),
            noise_dof: 10.0,
            cubic_term_spread: [None; 3],
        };
        let (v, p) = budget().sigmas(Some(&prior));
        // x: pooled (7 * 4 + 10 * 1) / 17; residual energy 28 against the scene's 7.
        let pooled = 38.0 / 17.0;
        assert!((v.x - (pooled + 0.1 * 21.0f64).sqrt()).abs() < 1e-12);
        assert!((p.x - (pooled + 0.2 * 21.0f64).sqrt()).abs() < 1e-12);
        // y: residuals quieter than the scene's noise show no misfit.
        assert!((v.y - ((7.0 * 0.5 + 10.0) / 17.0f64).sqrt()).abs() < 1e-12);
        // Nor do residuals within chance of it (1.8 times the scene's variance).
        let lucky = UncertaintyBudget {
            noise_variance: Vector3::repeat(1.8),
            ..budget()
        };
        let (v, _) = lucky.sigmas(Some(&prior));
        assert!((v.x - ((7.0 * 1.8 + 10.0) / 17.0f64).sqrt()).abs() < 1e-12);
        // Without a scene, nothing tells misfit from noise.
        let (alone, _) = budget().sigmas(None);
        assert!((alone.x - 2.0).abs() < 1e-12);
    }

    #[test]
    fn the_cubic_term_is_weighed_against_the_scenes_spread() {
        let budget = budget();
        let noise_z = (7.0 * 4.0 + 10.0) / 17.0;
        let variance = 0.5 * noise_z;
        let with = |tau2: Option<f64>| {
            let prior = ScenePrior {
                noise_variance: Vector3::repeat(1.0),
                noise_dof: 10.0,
                cubic_term_spread: [None, None, tau2],
            };
            budget.sigmas(Some(&prior)).0.z.powi(2) - noise_z
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
        let small = UncertaintyBudget {
            cubic_term: Vector3::new(0.0, 0.0, 0.1),
            ..budget
        };
        let prior = ScenePrior {
            noise_variance: Vector3::repeat(1.0),
            noise_dof: 10.0,
            cubic_term_spread: [None, None, Some(50.0)],
        };
        let stated = small.sigmas(Some(&prior)).0.z.powi(2) - noise_z;
        assert!(stated > 4.0 * variance * 0.9, "{stated}");
    }
}
