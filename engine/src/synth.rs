//! Synthetic stereo recordings with known truth, following the method's synthetic camera (section
//! 4.1.1): pinhole projection, image diameter `f d / R`, brightness `l / (4 pi R^2)`, partially
//! covered pixels get their covered fraction. Coverage is measured by 16x16 supersampling of the
//! pixels on a particle's rim (the method estimates it from covered edge lengths). Lens distortion
//! is applied to the disc through the local Jacobian of the lens model, so a distorted camera sees
//! the same particle a real one would, to first order. Optional sensor noise, background,
//! illumination gradient and particle size / brightness spread make it harder than the method's.
//!
//! Particles that leave the domain re-enter on the opposite side as new particles (new `pid`).
//! Everything is deterministic for a given scenario, particle count, frame count and seed.

use std::f64::consts::PI;
use std::fmt;
use std::str::FromStr;

use nalgebra::{
    Isometry3, Matrix2, Point3, Rotation3, Translation3, UnitQuaternion, Vector2, Vector3,
};

use crate::geometry::{CameraModel, Distortion, StereoRig};

/// SplitMix64: tiny, fast and fixed forever, so a seed gives the same recording on any build.
#[derive(Debug, Clone)]
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.uniform()
    }

    /// Standard normal (Box-Muller).
    pub fn normal(&mut self) -> f64 {
        let u1 = 1.0 - self.uniform();
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (2.0 * PI * u2).cos()
    }

    pub fn unit_vector(&mut self) -> Vector3<f64> {
        loop {
            let v = Vector3::new(self.normal(), self.normal(), self.normal());
            if v.norm() > 1e-6 {
                return v.normalize();
            }
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Scenario {
    Uniform,
    Flume,
    WindTunnel,
    Turbulence,
    Dense,
    MovingHead,
    HololensRaw,
    Convergent,
    Fast,
    Creep,
    Vortex,
    WideConvergent,
    Cluttered,
    Seeded,
    SeededTurbulence,
}

impl Scenario {
    pub const ALL: [Scenario; 15] = [
        Scenario::Uniform,
        Scenario::Flume,
        Scenario::WindTunnel,
        Scenario::Turbulence,
        Scenario::Dense,
        Scenario::MovingHead,
        Scenario::HololensRaw,
        Scenario::Convergent,
        Scenario::Fast,
        Scenario::Creep,
        Scenario::Vortex,
        Scenario::WideConvergent,
        Scenario::Cluttered,
        Scenario::Seeded,
        Scenario::SeededTurbulence,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Scenario::Uniform => "uniform",
            Scenario::Flume => "flume",
            Scenario::WindTunnel => "wind-tunnel",
            Scenario::Turbulence => "turbulence",
            Scenario::Dense => "dense",
            Scenario::MovingHead => "moving-head",
            Scenario::HololensRaw => "hololens-raw",
            Scenario::Convergent => "convergent",
            Scenario::Fast => "fast",
            Scenario::Creep => "creep",
            Scenario::Vortex => "vortex",
            Scenario::WideConvergent => "wide-convergent",
            Scenario::Cluttered => "cluttered",
            Scenario::Seeded => "seeded",
            Scenario::SeededTurbulence => "seeded-turbulence",
        }
    }

    pub fn description(self) -> &'static str {
        match self {
            Scenario::Uniform => "the method's validation case: unit cube, 100 particles, (u,v,w) = (1,0,-1), 960x720, h = 0.1, M = 5",
            Scenario::Flume => "HoloLens-2-like flume: 640x480 at 30 Hz, h = 9.9 cm, 10.6 mm particles at 0.32-0.66 m, noise and uneven light",
            Scenario::WindTunnel => "wind tunnel: 4.2 mm foam at 0.6-1.1 m moving ~30 px per frame, M = 2",
            Scenario::Turbulence => "divergence-free synthetic turbulence (random Fourier modes) in the unit cube",
            Scenario::Dense => "the uniform case with 1000 particles: overlaps and ambiguous matches",
            Scenario::MovingHead => "the flume seen by a wearer whose head turns and sways (pose per frame)",
            Scenario::HololensRaw => "raw HoloLens 2 geometry: distortion, 3 deg divergent axes, right camera rolled 180 deg, baseline along image y",
            Scenario::Convergent => "lab rig: two 640x480 cameras, f = 2000 px, 0.3 m apart, toed in 15 deg each; 2 mm particles at 0.5-0.62 m",
            Scenario::Fast => "the wind tunnel at twice the speed, particles at 0.7-1.1 m: 45-75 px per frame, each in view for 6-10 frames",
            Scenario::Creep => "creeping flow in the flume: 0.5 px per frame, 200 particles",
            Scenario::Vortex => "a vortex in front of the flume camera (solid-body rotation, 5 rad/s, axis along the view): under 5 px per frame near the axis, 25-50 px at the rim, 120 particles at 0.32-0.5 m",
            Scenario::Cluttered => "raw HoloLens 2 geometry in a furnished room: Gaussian particle images with motion blur, vignetting, hot pixels, LEDs, posters with print, sensor noise 4",
            Scenario::WideConvergent => "long-lens lab rig: two 640x480 cameras, f = 8000 px, 0.5 m apart, toed in 22.5 deg each (45 deg between axes); 1 mm particles at 0.6 m",
            Scenario::Seeded => "densely seeded tank seen by HoloLens-2-like cameras: 640x480 at 30 Hz, 2.5-6 px particles in a slab at 0.5-0.6 m, 0.005 particles per pixel, uniform flow ~2.3 px per frame",
            Scenario::SeededTurbulence => "the seeded tank in turbulence (random Fourier modes, 10-40 cm, RMS speed 0.12 m/s): accelerating flow, 0-8 px per frame",
        }
    }
}

impl fmt::Display for Scenario {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Scenario {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Scenario::ALL
            .into_iter()
            .find(|sc| sc.name() == s)
            .ok_or_else(|| {
                let names: Vec<_> = Scenario::ALL.iter().map(|s| s.name()).collect();
                format!("unknown scenario '{s}'; one of: {}", names.join(", "))
            })
    }
}

/// One random Fourier mode of a divergence-free field: `(a cos(k.x + w t) + b sin(k.x + w t))`
/// with `a` and `b` perpendicular to `k`.
#[derive(Debug, Clone)]
pub struct Mode {
    k: Vector3<f64>,
    a: Vector3<f64>,
    b: Vector3<f64>,
    omega: f64,
}

#[derive(Debug, Clone)]
pub enum Flow {
    Uniform(Vector3<f64>),
    /// Solid-body rotation about an axis along world z through `axis`, plus a uniform drift
    /// along it: speed grows linearly from the axis, with a centripetal acceleration.
    Vortex {
        axis: Point3<f64>,
        omega_rad_s: f64,
        axial_m_s: f64,
    },
    /// Kinematic-simulation turbulence: a sum of divergence-free modes with a k^-5/3 spectrum.
    Turbulence {
        mean: Vector3<f64>,
        modes: Vec<Mode>,
    },
}

impl Flow {
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

    fn turbulence(rng: &mut Rng, rms_speed: f64, smallest_m: f64, largest_m: f64) -> Self {
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
        translation_amplitude_m: Vector3<f64>,
        translation_frequency_hz: Vector3<f64>,
        /// Roll, pitch, yaw amplitudes, radians.
        rotation_amplitude_rad: Vector3<f64>,
        rotation_frequency_hz: Vector3<f64>,
    },
}

impl HeadMotion {
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

/// Everything that defines a scenario.
#[derive(Debug, Clone)]
pub struct ScenarioSpec {
    pub scenario: Scenario,
    pub rig: StereoRig,
    pub frame_interval_s: f64,
    pub default_frames: usize,
    pub default_particles: usize,
    /// Axis-aligned box in the world frame the particles live in.
    pub domain_min: Point3<f64>,
    pub domain_max: Point3<f64>,
    pub flow: Flow,
    pub diameter_m: f64,
    pub diameter_sd_m: f64,
    /// The method's illumination coefficient l: brightness = l / (4 pi R^2), grey levels m^2.
    pub illumination: f64,
    /// Relative standard deviation of per-particle brightness.
    pub brightness_spread: f64,
    /// Background grey level at the image's left edge, and its rise to the right edge.
    pub background: f64,
    pub background_gradient: f64,
    /// Relative change of particle brightness from the image's left edge to its right edge.
    pub illumination_gradient: f64,
    pub noise_sd: f64,
    pub head: HeadMotion,
    /// What a real camera and room add (all off in the idealised scenes).
    pub clutter: Clutter,
    /// A particle leaving through the near or far face re-enters at a random place on the
    /// opposite one, not straight behind where it left: in a thin slab, a particle that
    /// jumped in depth at the same place in the image would continue the old particle's
    /// track, with a velocity no particle had.
    pub scatter_depth_reentry: bool,
}

/// Image effects of real cameras in real rooms.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Clutter {
    /// Particle images as Gaussian spots (optics blur, sigma in pixels) instead of sharp discs.
    pub psf_sigma_px: f64,
    /// Fraction of the frame interval the shutter is open: particles smear along their motion.
    pub exposure_fraction: f64,
    /// Relative loss of light at the image corners (lens vignetting, quadratic in radius).
    pub vignetting: f64,
    /// Stuck-bright sensor pixels per camera.
    pub hot_pixels: usize,
    /// Small bright fixtures in the room (LEDs, glints) seen by both cameras, 2-4 m away.
    pub fixtures: usize,
    /// Posters on the wall behind: bright rectangles with dark print, this many grey levels
    /// above the background.
    pub poster_contrast: f64,
}

/// A pinhole with its principal point at the image centre.
fn centred_pinhole(width: u32, height: u32, f_px: f64) -> CameraModel {
    CameraModel::pinhole(
        f_px,
        (width as f64 - 1.0) / 2.0,
        (height as f64 - 1.0) / 2.0,
    )
}

/// Two identical pinholes, principal point at the image centre, baseline along x.
pub fn parallel_rig(width: u32, height: u32, f_px: f64, baseline_m: f64) -> StereoRig {
    let camera = centred_pinhole(width, height, f_px);
    StereoRig {
        width,
        height,
        left: camera,
        right: camera,
        right_from_left: Isometry3::translation(-baseline_m, 0.0, 0.0),
    }
}

/// Two identical pinholes `baseline_m` apart, each turned `toe_in_rad` towards the other about
/// the image's y axis, so their optical axes cross at `baseline_m / 2 / tan(toe_in_rad)`.
pub fn convergent_rig(
    width: u32,
    height: u32,
    f_px: f64,
    baseline_m: f64,
    toe_in_rad: f64,
) -> StereoRig {
    let camera = centred_pinhole(width, height, f_px);
    // In a frame with x along the baseline: the left camera at the origin looks towards +x, the
    // right one, at +baseline, towards -x.
    let world_from_left = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), toe_in_rad);
    let right_from_world =
        UnitQuaternion::from_axis_angle(&Vector3::y_axis(), -toe_in_rad).inverse();
    StereoRig {
        width,
        height,
        left: camera,
        right: camera,
        right_from_left: Isometry3::from_parts(
            Translation3::from(-(right_from_world * Vector3::new(baseline_m, 0.0, 0.0))),
            right_from_world * world_from_left,
        ),
    }
}

/// Where the optical axes of a `convergent_rig` cross, in its rig frame (the left camera's).
fn axes_crossing(baseline_m: f64, toe_in_rad: f64) -> Point3<f64> {
    let left_from_baseline =
        UnitQuaternion::from_axis_angle(&Vector3::y_axis(), toe_in_rad).inverse();
    let half_baseline_m = baseline_m / 2.0;
    left_from_baseline * Point3::new(half_baseline_m, 0.0, half_baseline_m / toe_in_rad.tan())
}

/// The raw HoloLens 2 front-camera geometry (published raw intrinsics, a plausible lens model).
pub fn hololens_raw_rig() -> StereoRig {
    let left = CameraModel {
        distortion: Distortion {
            k1: -0.08,
            k2: 0.02,
            p1: 8e-4,
            p2: -5e-4,
            ..Default::default()
        },
        ..CameraModel::pinhole(363.0, 318.0, 232.0)
    };
    let right = CameraModel {
        fx: 364.5,
        fy: 363.8,
        cx: 321.0,
        cy: 231.5,
        skew: 0.0,
        distortion: Distortion {
            k1: -0.075,
            k2: 0.018,
            p1: -6e-4,
            p2: 4e-4,
            ..Default::default()
        },
    };
    // Rolled 180 degrees about the optical axis, diverging 3 degrees about the baseline's normal.
    let right_from_left_rotation = UnitQuaternion::from_rotation_matrix(
        &(Rotation3::from_axis_angle(&Vector3::z_axis(), PI)
            * Rotation3::from_axis_angle(&Vector3::x_axis(), 0.052)
            * Rotation3::from_axis_angle(&Vector3::y_axis(), 0.01)),
    );
    let right_centre_in_left = Vector3::new(0.002, 0.099, 0.003);
    StereoRig {
        width: 640,
        height: 480,
        left,
        right,
        right_from_left: Isometry3::from_parts(
            Translation3::from(-(right_from_left_rotation * right_centre_in_left)),
            right_from_left_rotation,
        ),
    }
}

impl ScenarioSpec {
    pub fn new(scenario: Scenario) -> Self {
        // The method's synthetic camera: 960x720 with a 60 degree diagonal field of view.
        let unit_cube = || {
            let f_px = 600.0 / (PI / 6.0).tan();
            ScenarioSpec {
                scenario,
                rig: parallel_rig(960, 720, f_px, 0.1),
                frame_interval_s: 0.01,
                default_frames: 100,
                default_particles: 100,
                domain_min: Point3::new(-0.45, -0.5, 1.5),
                domain_max: Point3::new(0.55, 0.5, 2.5),
                flow: Flow::Uniform(Vector3::new(1.0, 0.0, -1.0)),
                diameter_m: 0.015,
                diameter_sd_m: 0.0,
                illumination: 230.0 * 4.0 * PI * 1.5 * 1.5,
                brightness_spread: 0.0,
                background: 0.0,
                background_gradient: 0.0,
                illumination_gradient: 0.0,
                noise_sd: 0.0,
                head: HeadMotion::None,
                clutter: Clutter::default(),
                scatter_depth_reentry: false,
            }
        };
        let flume = || ScenarioSpec {
            scenario,
            rig: parallel_rig(640, 480, 363.0, 0.099),
            frame_interval_s: 1.0 / 30.0,
            default_frames: 150,
            default_particles: 30,
            domain_min: Point3::new(-0.15, -0.15, 0.32),
            domain_max: Point3::new(0.25, 0.15, 0.66),
            flow: Flow::Uniform(Vector3::new(0.0983, -0.0372, 0.0)),
            diameter_m: 0.0106,
            diameter_sd_m: 0.0013,
            illumination: 180.0 * 4.0 * PI * 0.25,
            brightness_spread: 0.1,
            background: 15.0,
            background_gradient: 20.0,
            illumination_gradient: 0.3,
            noise_sd: 2.0,
            head: HeadMotion::None,
            clutter: Clutter::default(),
            scatter_depth_reentry: false,
        };
        let wind_tunnel = || ScenarioSpec {
            default_frames: 120,
            default_particles: 60,
            domain_min: Point3::new(-0.3, -0.3, 0.6),
            domain_max: Point3::new(0.4, 0.3, 1.1),
            flow: Flow::Uniform(Vector3::new(1.53, -1.38, 0.0)),
            diameter_m: 0.00418,
            diameter_sd_m: 0.0005,
            illumination: 200.0 * 4.0 * PI * 0.64,
            background: 10.0,
            background_gradient: 10.0,
            illumination_gradient: 0.2,
            ..flume()
        };
        // Small particles (6 mm: 2.5-6 px) as densely as PTV users seed, in a 10 cm slab that
        // fills both views, so the images are evenly crowded.
        let seeded = || ScenarioSpec {
            default_frames: 90,
            default_particles: 1540,
            domain_min: Point3::new(-0.33, -0.32, 0.5),
            domain_max: Point3::new(0.43, 0.32, 0.6),
            diameter_m: 0.006,
            diameter_sd_m: 0.0013,
            scatter_depth_reentry: true,
            ..flume()
        };
        let hololens_raw = || ScenarioSpec {
            rig: hololens_raw_rig(),
            // Raw frames are sideways: the baseline (rig y) is world x, so the world is upright.
            head: HeadMotion::Fixed(Isometry3::rotation(Vector3::z() * (-PI / 2.0))),
            default_particles: 20,
            domain_min: Point3::new(-0.1, -0.15, 0.38),
            domain_max: Point3::new(0.2, 0.15, 0.68),
            ..flume()
        };
        match scenario {
            Scenario::Uniform => unit_cube(),
            Scenario::Dense => ScenarioSpec {
                default_particles: 1000,
                default_frames: 60,
                ..unit_cube()
            },
            Scenario::Turbulence => {
                let mut rng = Rng::new(0x7u64 << 32 | 99);
                ScenarioSpec {
                    default_frames: 60,
                    flow: Flow::turbulence(&mut rng, 1.0, 0.25, 1.0),
                    ..unit_cube()
                }
            }
            Scenario::Flume => flume(),
            Scenario::WindTunnel => wind_tunnel(),
            Scenario::MovingHead => ScenarioSpec {
                default_particles: 20,
                domain_min: Point3::new(-0.15, -0.15, 0.36),
                domain_max: Point3::new(0.25, 0.15, 0.66),
                head: HeadMotion::Oscillating {
                    translation_amplitude_m: Vector3::new(0.02, 0.01, 0.015),
                    translation_frequency_hz: Vector3::new(0.4, 0.3, 0.25),
                    rotation_amplitude_rad: Vector3::new(0.02, 0.035, 0.05),
                    rotation_frequency_hz: Vector3::new(0.2, 0.5, 0.35),
                },
                ..flume()
            },
            Scenario::HololensRaw => hololens_raw(),
            Scenario::Fast => ScenarioSpec {
                // The domain fills the view, so particles cross it instead of appearing and
                // vanishing inside it.
                default_particles: 100,
                domain_min: Point3::new(-0.8, -0.6, 0.7),
                domain_max: Point3::new(0.8, 0.6, 1.1),
                flow: Flow::Uniform(Vector3::new(1.53, -1.38, 0.0) * 2.0),
                ..wind_tunnel()
            },
            Scenario::Creep => ScenarioSpec {
                default_particles: 200,
                diameter_m: 0.006,
                diameter_sd_m: 0.0008,
                // 0.5 px per frame at 0.5 m.
                flow: Flow::Uniform(Vector3::new(0.0172, -0.0069, 0.0)),
                ..flume()
            },
            Scenario::Vortex => ScenarioSpec {
                default_particles: 120,
                default_frames: 150,
                domain_min: Point3::new(-0.15, -0.18, 0.32),
                domain_max: Point3::new(0.25, 0.18, 0.5),
                diameter_m: 0.006,
                diameter_sd_m: 0.0008,
                flow: Flow::Vortex {
                    axis: Point3::new(0.05, 0.0, 0.0),
                    omega_rad_s: 5.0,
                    axial_m_s: 0.02,
                },
                ..flume()
            },
            Scenario::WideConvergent => {
                let toe_in = 22.5f64.to_radians();
                let baseline_m = 0.5;
                let crossing = axes_crossing(baseline_m, toe_in);
                let half = Vector3::new(0.008, 0.006, 0.008);
                ScenarioSpec {
                    rig: convergent_rig(640, 480, 8000.0, baseline_m, toe_in),
                    default_particles: 30,
                    domain_min: crossing - half,
                    domain_max: crossing + half,
                    flow: Flow::Uniform(Vector3::new(0.012, -0.005, 0.002)),
                    diameter_m: 0.0008,
                    diameter_sd_m: 0.0001,
                    illumination: 180.0 * 4.0 * PI * 0.36,
                    ..flume()
                }
            }
            Scenario::Seeded => seeded(),
            Scenario::SeededTurbulence => {
                let mut rng = Rng::new(0x5EED << 32 | 7);
                ScenarioSpec {
                    default_frames: 90,
                    flow: Flow::turbulence(&mut rng, 0.12, 0.1, 0.4),
                    ..seeded()
                }
            }
            Scenario::Cluttered => ScenarioSpec {
                default_particles: 40,
                flow: Flow::Uniform(Vector3::new(0.2, -0.08, 0.03)),
                noise_sd: 4.0,
                clutter: Clutter {
                    psf_sigma_px: 1.0,
                    exposure_fraction: 0.5,
                    vignetting: 0.5,
                    hot_pixels: 40,
                    fixtures: 12,
                    poster_contrast: 60.0,
                },
                ..hololens_raw()
            },
            Scenario::Convergent => {
                let toe_in = 15f64.to_radians();
                // The particles sit around the axes' crossing (0.15 m across, 0.56 m out, in the
                // baseline's frame).
                let crossing = axes_crossing(0.3, toe_in);
                let half = Vector3::new(0.05, 0.04, 0.05);
                ScenarioSpec {
                    rig: convergent_rig(640, 480, 2000.0, 0.3, toe_in),
                    default_particles: 40,
                    domain_min: crossing - half,
                    domain_max: crossing + half,
                    flow: Flow::Uniform(Vector3::new(0.06, -0.025, 0.01)),
                    diameter_m: 0.002,
                    diameter_sd_m: 0.0002,
                    illumination: 180.0 * 4.0 * PI * 0.3,
                    ..flume()
                }
            }
        }
    }
}

/// One row of `truth.csv`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TruthRow {
    pub frame: u64,
    pub t_s: f64,
    pub pid: u64,
    pub position: Point3<f64>,
    pub velocity: Vector3<f64>,
}

/// One rendered frame with its truth.
#[derive(Debug, Clone)]
pub struct SynthFrame {
    pub index: u64,
    pub t_s: f64,
    pub world_from_rig: Option<Isometry3<f64>>,
    pub left: Vec<u8>,
    pub right: Vec<u8>,
    pub truth: Vec<TruthRow>,
    /// Particles whose centre projects inside both images.
    pub visible_in_both: usize,
    /// Particles whose centre projects inside the left image, and those of them whose image
    /// there touches or overlaps another particle's.
    pub in_view_left: usize,
    pub touching_left: usize,
}

#[derive(Debug, Clone)]
struct Particle {
    pid: u64,
    position: Point3<f64>,
    diameter_m: f64,
    brightness_factor: f64,
}

/// Generates a scenario frame by frame.
pub struct Synthesizer {
    spec: ScenarioSpec,
    /// What the room and sensor add to every frame, per camera (grey levels).
    fixed_left: Vec<f32>,
    fixed_right: Vec<f32>,
    particles: Vec<Particle>,
    next_pid: u64,
    rng: Rng,
    noise_rng: Rng,
    frame: u64,
}

impl Synthesizer {
    pub fn new(spec: ScenarioSpec, particles: usize, seed: u64) -> Self {
        let mut room = Rng::new(seed ^ 0x0F1C_E5EE_D000_0001);
        let (fixed_left, fixed_right) = fixed_layers(&spec, &mut room);
        let mut synth = Self {
            spec,
            fixed_left,
            fixed_right,
            particles: Vec::with_capacity(particles),
            next_pid: 0,
            rng: Rng::new(seed),
            noise_rng: Rng::new(seed ^ 0xA5A5_5A5A_DEAD_BEEF),
            frame: 0,
        };
        for _ in 0..particles {
            let position = Point3::from(Vector3::from_fn(|i, _| {
                synth
                    .rng
                    .range(synth.spec.domain_min[i], synth.spec.domain_max[i])
            }));
            let p = synth.new_particle(position);
            synth.particles.push(p);
        }
        synth
    }

    fn new_particle(&mut self, position: Point3<f64>) -> Particle {
        self.next_pid += 1;
        let spec = &self.spec;
        let diameter_m =
            (spec.diameter_m + spec.diameter_sd_m * self.rng.normal()).max(spec.diameter_m * 0.3);
        let brightness_factor = (1.0 + spec.brightness_spread * self.rng.normal()).max(0.2);
        Particle {
            pid: self.next_pid,
            position,
            diameter_m,
            brightness_factor,
        }
    }

    /// Renders the current state, then advances the particles by one frame interval.
    pub fn next_frame(&mut self) -> SynthFrame {
        let spec = &self.spec;
        let t_s = self.frame as f64 * spec.frame_interval_s;
        let world_from_rig = spec.head.world_from_rig(t_s);
        let rig_from_world = world_from_rig.map_or_else(Isometry3::identity, |p| p.inverse());
        let (w, h) = (spec.rig.width as usize, spec.rig.height as usize);
        let mut left = vec![0f32; w * h];
        let mut right = vec![0f32; w * h];
        let mut truth = Vec::with_capacity(self.particles.len());
        let mut visible_in_both = 0;
        let mut left_discs = Vec::new();
        for p in &self.particles {
            let in_rig = rig_from_world * p.position;
            // With the shutter open for part of the frame the image is the average of the
            // particle's positions over the exposure (its motion there taken as uniform).
            let velocity_in_rig = rig_from_world.rotation * spec.flow.velocity(&p.position, t_s);
            let exposure_s = spec.clutter.exposure_fraction * spec.frame_interval_s;
            let steps = if exposure_s > 0.0 { 8 } else { 1 };
            let mut seen_left = false;
            let mut seen_right = false;
            for k in 0..steps {
                let dt = if steps == 1 {
                    0.0
                } else {
                    exposure_s * ((k as f64 + 0.5) / steps as f64 - 0.5)
                };
                let at = in_rig + velocity_in_rig * dt;
                let at_right = spec.rig.right_from_left * at;
                let share = 1.0 / steps as f64;
                let disc = render_particle(spec, &spec.rig.left, &at, p, share, &mut left);
                if k == steps / 2 {
                    left_discs.extend(disc);
                }
                seen_left |= disc.is_some();
                seen_right |=
                    render_particle(spec, &spec.rig.right, &at_right, p, share, &mut right)
                        .is_some();
            }
            visible_in_both += usize::from(seen_left && seen_right);
            truth.push(TruthRow {
                frame: self.frame,
                t_s,
                pid: p.pid,
                position: p.position,
                velocity: spec.flow.velocity(&p.position, t_s),
            });
        }
        let left = finish_image(spec, &left, &self.fixed_left, &mut self.noise_rng);
        let right = finish_image(spec, &right, &self.fixed_right, &mut self.noise_rng);
        let frame = SynthFrame {
            index: self.frame,
            t_s,
            world_from_rig,
            left,
            right,
            truth,
            visible_in_both,
            in_view_left: left_discs.len(),
            touching_left: touching(&mut left_discs),
        };
        self.advance(t_s);
        self.frame += 1;
        frame
    }

    fn advance(&mut self, t_s: f64) {
        const SUBSTEPS: usize = 4;
        let dt = self.spec.frame_interval_s / SUBSTEPS as f64;
        let (lo, hi) = (self.spec.domain_min, self.spec.domain_max);
        for i in 0..self.particles.len() {
            let mut x = self.particles[i].position;
            for s in 0..SUBSTEPS {
                let t = t_s + s as f64 * dt;
                let flow = &self.spec.flow;
                let k1 = flow.velocity(&x, t);
                let k2 = flow.velocity(&(x + k1 * (dt / 2.0)), t + dt / 2.0);
                let k3 = flow.velocity(&(x + k2 * (dt / 2.0)), t + dt / 2.0);
                let k4 = flow.velocity(&(x + k3 * dt), t + dt);
                x += (k1 + 2.0 * k2 + 2.0 * k3 + k4) * (dt / 6.0);
            }
            let outside = (0..3).any(|a| x[a] < lo[a] || x[a] > hi[a]);
            if outside {
                let through_depth = x[2] < lo[2] || x[2] > hi[2];
                for a in 0..3 {
                    let size = hi[a] - lo[a];
                    x[a] = lo[a] + (x[a] - lo[a]).rem_euclid(size);
                }
                if through_depth && self.spec.scatter_depth_reentry {
                    for a in 0..2 {
                        x[a] = self.rng.range(lo[a], hi[a]);
                    }
                }
                self.particles[i] = self.new_particle(x);
            } else {
                self.particles[i].position = x;
            }
        }
    }
}

/// The room and the sensor's fixed pattern for each camera: posters with print on the wall,
/// LEDs seen by both cameras, hot pixels. Empty when the scene has no clutter.
fn fixed_layers(spec: &ScenarioSpec, rng: &mut Rng) -> (Vec<f32>, Vec<f32>) {
    let c = &spec.clutter;
    if *c == Clutter::default() {
        return (Vec::new(), Vec::new());
    }
    let (w, h) = (spec.rig.width as usize, spec.rig.height as usize);
    let mut left = vec![0f32; w * h];
    let mut right = vec![0f32; w * h];
    let spot = |image: &mut [f32], x: f64, y: f64, sigma: f64, peak: f64| {
        let reach = (3.0 * sigma).ceil() as isize;
        for dy in -reach..=reach {
            for dx in -reach..=reach {
                let (px, py) = (x.round() as isize + dx, y.round() as isize + dy);
                if px < 0 || py < 0 || px >= w as isize || py >= h as isize {
                    continue;
                }
                let r2 = (px as f64 - x).powi(2) + (py as f64 - y).powi(2);
                image[py as usize * w + px as usize] +=
                    (peak * (-r2 / (2.0 * sigma * sigma)).exp()) as f32;
            }
        }
    };
    // Posters: each camera sees the wall from its own place; the print is 2-4 px strokes.
    if c.poster_contrast > 0.0 {
        for image in [&mut left, &mut right] {
            for _ in 0..3 {
                let (x0, y0) = (
                    rng.range(0.0, w as f64 * 0.8),
                    rng.range(0.0, h as f64 * 0.8),
                );
                let (pw, ph) = (rng.range(60.0, 160.0), rng.range(60.0, 140.0));
                let (x1, y1) = ((x0 + pw).min(w as f64), (y0 + ph).min(h as f64));
                for y in y0 as usize..y1 as usize {
                    for x in x0 as usize..x1 as usize {
                        // Lines of print: dark strokes on alternate rows of 6 px.
                        let print = (y / 6) % 2 == 1 && (x / 3) % 4 != 0;
                        image[y * w + x] += if print {
                            (0.2 * c.poster_contrast) as f32
                        } else {
                            c.poster_contrast as f32
                        };
                    }
                }
            }
        }
    }
    // LEDs and glints: points 2-4 m away, so both cameras see them, at a consistent disparity.
    for _ in 0..c.fixtures {
        let in_rig = Point3::new(
            rng.range(-1.2, 1.2),
            rng.range(-0.9, 0.9),
            rng.range(2.0, 4.0),
        );
        let peak = rng.range(120.0, 240.0);
        let sigma = rng.range(0.8, 2.0);
        if let Some(p) = spec.rig.left.project(&in_rig) {
            spot(&mut left, p.x, p.y, sigma, peak);
        }
        if let Some(p) = spec.rig.right.project(&(spec.rig.right_from_left * in_rig)) {
            spot(&mut right, p.x, p.y, sigma, peak);
        }
    }
    for image in [&mut left, &mut right] {
        for _ in 0..c.hot_pixels {
            let i = (rng.next_u64() % (w * h) as u64) as usize;
            image[i] += 255.0;
        }
    }
    (left, right)
}

/// A particle's image: centre and radius, pixels.
#[derive(Debug, Clone, Copy)]
struct Disc {
    x: f64,
    y: f64,
    radius: f64,
}

/// How many of the discs touch or overlap another.
fn touching(discs: &mut [Disc]) -> usize {
    discs.sort_by(|a, b| a.x.total_cmp(&b.x));
    let widest = discs.iter().map(|d| d.radius).fold(0.0, f64::max);
    let mut touches = vec![false; discs.len()];
    for i in 0..discs.len() {
        let a = discs[i];
        for j in i + 1..discs.len() {
            let b = discs[j];
            if b.x - a.x > a.radius + widest {
                break;
            }
            if (b.x - a.x).hypot(b.y - a.y) <= a.radius + b.radius {
                touches[i] = true;
                touches[j] = true;
            }
        }
    }
    touches.iter().filter(|&&t| t).count()
}

/// Adds one particle's disc to a camera's float image; returns its image if its centre is in
/// view.
fn render_particle(
    spec: &ScenarioSpec,
    camera: &CameraModel,
    in_camera: &Point3<f64>,
    p: &Particle,
    share: f64,
    image: &mut [f32],
) -> Option<Disc> {
    let centre = camera.project(in_camera)?;
    let range_m = in_camera.coords.norm();
    let (w, h) = (spec.rig.width as usize, spec.rig.height as usize);
    let normalized = Vector2::new(in_camera.x / in_camera.z, in_camera.y / in_camera.z);
    // Pixel offsets map to normalized offsets through the inverse Jacobian of the lens model.
    let eps = 1e-6;
    let project = |n: Vector2<f64>| {
        camera
            .project(&Point3::new(n.x, n.y, 1.0))
            .map_or(Vector2::zeros(), |q| Vector2::new(q.x, q.y))
    };
    let column =
        |d: Vector2<f64>| (project(normalized + d) - project(normalized - d)) / (2.0 * eps);
    let jacobian = Matrix2::from_columns(&[
        column(Vector2::new(eps, 0.0)),
        column(Vector2::new(0.0, eps)),
    ]);
    let inverse = jacobian.try_inverse()?;
    let radius = p.diameter_m / (2.0 * range_m);
    let brightness =
        share * p.brightness_factor * spec.illumination / (4.0 * PI * range_m * range_m);
    let psf = spec.clutter.psf_sigma_px;
    let pixel_reach = jacobian.norm() * radius + 2.0 + 3.0 * psf;
    let half_pixel = inverse.norm() * 0.5;
    let x_range = ((centre.x - pixel_reach).floor().max(0.0) as usize)
        ..=((centre.x + pixel_reach).ceil().min(w as f64 - 1.0).max(0.0) as usize);
    let y_range = ((centre.y - pixel_reach).floor().max(0.0) as usize)
        ..=((centre.y + pixel_reach).ceil().min(h as f64 - 1.0).max(0.0) as usize);
    for py in y_range {
        for px in x_range.clone() {
            let offset = inverse * Vector2::new(px as f64 - centre.x, py as f64 - centre.y);
            let distance = offset.norm();
            let coverage = if psf > 0.0 {
                // A disc seen through optics blur: a Gaussian spot whose spread adds the disc's
                // (radius / 2) to the blur, with the disc's total light.
                let radius_px = radius / half_pixel.max(1e-12) * 0.5;
                let sigma2 = psf * psf + radius_px * radius_px / 4.0;
                let r2 = (px as f64 - centre.x).powi(2) + (py as f64 - centre.y).powi(2);
                PI * radius_px * radius_px * (-r2 / (2.0 * sigma2)).exp() / (2.0 * PI * sigma2)
            } else if distance + half_pixel <= radius {
                1.0
            } else if distance - half_pixel >= radius {
                0.0
            } else {
                const N: usize = 16;
                let mut inside = 0;
                for sy in 0..N {
                    for sx in 0..N {
                        let d = Vector2::new(
                            px as f64 - centre.x + (sx as f64 + 0.5) / N as f64 - 0.5,
                            py as f64 - centre.y + (sy as f64 + 0.5) / N as f64 - 0.5,
                        );
                        inside += usize::from((inverse * d).norm() <= radius);
                    }
                }
                inside as f64 / (N * N) as f64
            };
            if coverage > 0.0 {
                let illumination = 1.0 + spec.illumination_gradient * (px as f64 / w as f64 - 0.5);
                image[py * w + px] += (brightness * coverage * illumination) as f32;
            }
        }
    }
    spec.rig.contains(centre).then(|| Disc {
        x: centre.x,
        y: centre.y,
        // Normalized to pixels by the lens's mean scale; optics blur widens the image by about
        // a sigma on each side.
        radius: radius * std::f64::consts::SQRT_2 / inverse.norm().max(1e-12) + psf,
    })
}

fn finish_image(spec: &ScenarioSpec, signal: &[f32], fixed: &[f32], noise: &mut Rng) -> Vec<u8> {
    let (w, h) = (spec.rig.width as usize, spec.rig.height as usize);
    let (cx, cy) = (w as f64 / 2.0, h as f64 / 2.0);
    let corner2 = cx * cx + cy * cy;
    signal
        .iter()
        .zip(fixed.iter().chain(std::iter::repeat(&0.0)))
        .enumerate()
        .map(|(i, (&s, &f))| {
            let (x, y) = ((i % w) as f64, (i / w) as f64);
            let light =
                1.0 - spec.clutter.vignetting * ((x - cx).powi(2) + (y - cy).powi(2)) / corner2;
            let background = light
                * (spec.background
                    + spec.background_gradient * ((i % w) as f64 / w as f64)
                    + f as f64);
            let s = light as f32 * s;
            let n = if spec.noise_sd > 0.0 {
                spec.noise_sd * noise.normal()
            } else {
                0.0
            };
            (background + s as f64 + n).round().clamp(0.0, 255.0) as u8
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scenario_names_round_trip() {
        for s in Scenario::ALL {
            assert_eq!(s.name().parse::<Scenario>(), Ok(s));
        }
        assert!("nope".parse::<Scenario>().unwrap_err().contains("uniform"));
    }

    #[test]
    fn same_seed_same_frames() {
        let mut a = Synthesizer::new(ScenarioSpec::new(Scenario::Flume), 20, 7);
        let mut b = Synthesizer::new(ScenarioSpec::new(Scenario::Flume), 20, 7);
        for _ in 0..3 {
            let (fa, fb) = (a.next_frame(), b.next_frame());
            assert_eq!(fa.left, fb.left);
            assert_eq!(fa.truth, fb.truth);
        }
    }

    #[test]
    fn turbulence_is_divergence_free() {
        let spec = ScenarioSpec::new(Scenario::Turbulence);
        let e = 1e-5;
        let mut rng = Rng::new(3);
        for _ in 0..20 {
            let x = Point3::new(rng.uniform(), rng.uniform(), rng.uniform() + 1.5);
            let div: f64 = (0..3)
                .map(|a| {
                    let mut d = Vector3::zeros();
                    d[a] = e;
                    (spec.flow.velocity(&(x + d), 0.3)[a] - spec.flow.velocity(&(x - d), 0.3)[a])
                        / (2.0 * e)
                })
                .sum();
            assert!(div.abs() < 1e-5, "divergence {div}");
        }
    }

    #[test]
    fn touching_discs_are_counted_once_each() {
        let disc = |x, y, radius| Disc { x, y, radius };
        // Two touching at the rim, two overlapping, one alone; a wide disc reaches far.
        let mut discs = [
            disc(0.0, 0.0, 1.0),
            disc(2.0, 0.0, 1.0),
            disc(10.0, 0.0, 1.5),
            disc(11.0, 1.0, 1.5),
            disc(30.0, 0.0, 1.0),
            disc(50.0, 0.0, 6.0),
            disc(43.5, 0.0, 1.0),
        ];
        assert_eq!(touching(&mut discs), 6);
        assert_eq!(touching(&mut []), 0);
    }

    #[test]
    fn seeded_scenes_are_as_crowded_as_dense_seeding() {
        for scenario in [Scenario::Seeded, Scenario::SeededTurbulence] {
            let spec = ScenarioSpec::new(scenario);
            let pixels = (spec.rig.width * spec.rig.height) as f64;
            let mut synth = Synthesizer::new(spec.clone(), spec.default_particles, 1);
            let (mut in_view, mut touching) = (0, 0);
            for _ in 0..3 {
                let f = synth.next_frame();
                in_view += f.in_view_left;
                touching += f.touching_left;
            }
            let per_pixel = in_view as f64 / (3.0 * pixels);
            let touching = touching as f64 / in_view as f64;
            assert!(
                (0.0045..0.0055).contains(&per_pixel),
                "{scenario}: {per_pixel}"
            );
            assert!((0.2..0.35).contains(&touching), "{scenario}: {touching}");
        }
    }

    #[test]
    fn domains_are_in_view_of_both_cameras() {
        for scenario in Scenario::ALL {
            let spec = ScenarioSpec::new(scenario);
            let mut synth = Synthesizer::new(spec, 200, 1);
            let (mut seen, mut all) = (0, 0);
            for _ in 0..5 {
                let f = synth.next_frame();
                seen += f.visible_in_both;
                all += f.truth.len();
            }
            // The fast scene's domain fills the view on purpose: its particles cross the
            // images instead of appearing inside them.
            let least = if scenario == Scenario::Fast {
                0.8
            } else {
                0.97
            };
            assert!(
                seen as f64 >= least * all as f64,
                "{scenario}: {seen} of {all} visible"
            );
        }
    }
}
