//! How the particles and the headset move.

use std::f64::consts::PI;

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};

use super::Rng;

/// One random Fourier mode of a divergence-free field: `(a cos(k.x + w t) + b sin(k.x + w t))`
/// with `a` and `b` perpendicular to `k`.
#[derive(Debug, Clone)]
pub struct Mode {
    k: Vector3<f64>,
    a: Vector3<f64>,
    b: Vector3<f64>,
    omega: f64,
}

/// The flow the particles follow.
#[derive(Debug, Clone)]
pub enum Flow {
    /// One velocity everywhere, m/s.
    Uniform(Vector3<f64>),
    /// Solid-body rotation about an axis along world z through `axis`, plus a uniform drift
    /// along it: speed grows linearly from the axis, with a centripetal acceleration.
    Vortex {
        /// A point on the axis (along z), metres.
        axis: Point3<f64>,
        /// Angular velocity, rad/s.
        omega_rad_s: f64,
        /// Speed along the axis, m/s.
        axial_m_s: f64,
    },
    /// Kinematic-simulation turbulence: a sum of divergence-free modes with a k^-5/3 spectrum.
    Turbulence {
        /// Mean velocity added to the modes, m/s.
        mean: Vector3<f64>,
        /// The Fourier modes.
        modes: Vec<Mode>,
    },
}

impl Flow {
    /// The velocity at `x` and time `t`, m/s.
    pub fn velocity(&self, x: &Point3<f64>, t: f64) -> Vector3<f64> {
        match self {
            Flow::Uniform(v) => *v,
            Flow::Vortex {
                axis,
                omega_rad_s,
                axial_m_s,
            } => {
                let r = x - axis;
                Vector3::new(-omega_rad_s * r.y, omega_rad_s * r.x, *axial_m_s)
            }
            Flow::Turbulence { mean, modes } => {
                let mut u = *mean;
                for m in modes {
                    let phase = m.k.dot(&x.coords) + m.omega * t;
                    u += m.a * phase.cos() + m.b * phase.sin();
                }
                u
            }
        }
    }

    pub(super) fn turbulence(
        rng: &mut Rng,
        rms_speed: f64,
        smallest_m: f64,
        largest_m: f64,
    ) -> Self {
        let count = 48;
        let (k_min, k_max) = (2.0 * PI / largest_m, 2.0 * PI / smallest_m);
        let mut modes: Vec<Mode> = (0..count)
            .map(|_| {
                let k_mag = k_min * (k_max / k_min).powf(rng.uniform());
                let k = rng.unit_vector() * k_mag;
                let perpendicular = |rng: &mut Rng| {
                    let v = rng.unit_vector();
                    (v - k * (v.dot(&k) / k.norm_squared())).normalize()
                };
                // Energy per mode ~ E(k) dk with E ~ k^-5/3 and dk ~ k on a log spacing.
                let amplitude = k_mag.powf(-5.0 / 6.0 + 0.5);
                Mode {
                    k,
                    a: perpendicular(rng) * amplitude * rng.normal(),
                    b: perpendicular(rng) * amplitude * rng.normal(),
                    omega: 0.0,
                }
            })
            .collect();
        // Mean square speed of the sum is half the sum of |a|^2 + |b|^2.
        let mean_square: f64 = modes
            .iter()
            .map(|m| (m.a.norm_squared() + m.b.norm_squared()) / 2.0)
            .sum();
        let gain = rms_speed / mean_square.sqrt();
        for m in &mut modes {
            m.a *= gain;
            m.b *= gain;
            m.omega = 0.5 * rms_speed * m.k.norm() * rng.range(-1.0, 1.0);
        }
        Flow::Turbulence {
            mean: Vector3::zeros(),
            modes,
        }
    }
}

/// How the headset moves.
#[derive(Debug, Clone)]
pub enum HeadMotion {
    /// No pose in the recording: world = rig.
    None,
    /// A constant pose for every frame.
    Fixed(Isometry3<f64>),
    /// Sinusoidal sway and turn about a base pose.
    Oscillating {
        /// Translation amplitude per axis, metres.
        translation_amplitude_m: Vector3<f64>,
        /// Translation frequency per axis, Hz.
        translation_frequency_hz: Vector3<f64>,
        /// Roll, pitch, yaw amplitudes, radians.
        rotation_amplitude_rad: Vector3<f64>,
        /// Rotation frequency per axis, Hz.
        rotation_frequency_hz: Vector3<f64>,
    },
}

impl HeadMotion {
    /// The headset's pose at `t_s` (`None`: world = rig).
    pub fn world_from_rig(&self, t_s: f64) -> Option<Isometry3<f64>> {
        match self {
            HeadMotion::None => None,
            HeadMotion::Fixed(pose) => Some(*pose),
            HeadMotion::Oscillating {
                translation_amplitude_m: ta,
                translation_frequency_hz: tf,
                rotation_amplitude_rad: ra,
                rotation_frequency_hz: rf,
            } => {
                let wave = |amp: f64, hz: f64| amp * (2.0 * PI * hz * t_s).sin();
                Some(Isometry3::from_parts(
                    Translation3::new(wave(ta.x, tf.x), wave(ta.y, tf.y), wave(ta.z, tf.z)),
                    UnitQuaternion::from_euler_angles(
                        wave(ra.x, rf.x),
                        wave(ra.y, rf.y),
                        wave(ra.z, rf.z),
                    ),
                ))
            }
        }
    }
}
