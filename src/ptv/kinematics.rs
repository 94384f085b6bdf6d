//! Stage 5: velocity by moving least squares (method section 5.5, eqs. 13-15).
//!
//! `q(t) = a + b (t - t_n) + c (t - t_n)^2` is fitted to the positions of a window of frames; the
//! velocity at `t_n` is `b` and the smoothed position `a`. The method centres the window on `t_n`
//! (`+-M` frames). Times come from the frames' timestamps, so jittered frame intervals are honoured.

use nalgebra::{Matrix3, Point3, Vector3};

/// A fitted path evaluated at one time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MotionFit {
    /// Fitted position at the evaluation time (a).
    pub position: Point3<f64>,
    /// Fitted velocity at the evaluation time (b), units per second.
    pub velocity: Vector3<f64>,
    /// Root-mean-square distance of the samples from the fitted curve.
    pub rms_residual: f64,
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
    if samples.len() < 3 {
        return None;
    }
    // Times are scaled to [-1, 1] so the normal equations stay well conditioned at any frame rate.
    let scale_s = samples
        .iter()
        .map(|(t, _)| (t - t_eval_s).abs())
        .fold(0.0, f64::max);
    if scale_s.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
        return None;
    }
    let mut normal = Matrix3::<f64>::zeros();
    let mut rhs = Matrix3::<f64>::zeros();
    for (t, p) in samples {
        let tau = (t - t_eval_s) / scale_s;
        let basis = Vector3::new(1.0, tau, tau * tau);
        normal += basis * basis.transpose();
        rhs += basis * p.coords.transpose();
    }
    // Rows of `coefficients` are a, b, c; columns are x, y, z.
    let coefficients = normal.try_inverse()? * rhs;
    let a = Vector3::new(
        coefficients[(0, 0)],
        coefficients[(0, 1)],
        coefficients[(0, 2)],
    );
    let b = Vector3::new(
        coefficients[(1, 0)],
        coefficients[(1, 1)],
        coefficients[(1, 2)],
    ) / scale_s;
    let c = Vector3::new(
        coefficients[(2, 0)],
        coefficients[(2, 1)],
        coefficients[(2, 2)],
    ) / (scale_s * scale_s);
    let squared: f64 = samples
        .iter()
        .map(|(t, p)| {
            let tau = t - t_eval_s;
            (p.coords - (a + b * tau + c * tau * tau)).norm_squared()
        })
        .sum();
    let fit = MotionFit {
        position: Point3::from(a),
        velocity: b,
        rms_residual: (squared / samples.len() as f64).sqrt(),
    };
    fit.finite()
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
    let squared: f64 = samples
        .iter()
        .map(|(t, p)| (p.coords - (a + velocity * (t - t_eval_s))).norm_squared())
        .sum();
    let fit = MotionFit {
        position: Point3::from(a),
        velocity,
        rms_residual: (squared / n).sqrt(),
    };
    fit.finite()
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

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
