//! The named scenarios and what defines each.

use std::f64::consts::PI;
use std::fmt;
use std::str::FromStr;

use nalgebra::{Isometry3, Point3, Vector3};

use super::rigs::{axes_crossing, convergent_rig, hololens_raw_rig, parallel_rig};
use super::{Flow, HeadMotion, Rng};
use crate::geometry::StereoRig;

/// The named scenarios (`mrptv synth --help` and `demo --help` describe each).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Scenario {
    /// The method's validation case.
    Uniform,
    /// A HoloLens-2-like flume.
    Flume,
    /// A wind tunnel.
    WindTunnel,
    /// Synthetic turbulence.
    Turbulence,
    /// The uniform case, densely seeded.
    Dense,
    /// The flume seen by a moving head.
    MovingHead,
    /// The raw HoloLens 2 geometry.
    HololensRaw,
    /// A convergent lab rig.
    Convergent,
    /// A fast wind tunnel.
    Fast,
    /// Creeping flow.
    Creep,
    /// A vortex.
    Vortex,
    /// A long-lens convergent rig.
    WideConvergent,
    /// The raw HoloLens 2 geometry in a furnished room.
    Cluttered,
    /// Dense seeding.
    Seeded,
    /// Dense seeding in turbulence.
    SeededTurbulence,
}

impl Scenario {
    /// Every scenario, in the order help lists them.
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

    /// The name commands take.
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

    /// A line on what it tests.
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

/// Everything that defines a scenario.
#[derive(Debug, Clone)]
pub struct ScenarioSpec {
    /// Which scenario.
    pub scenario: Scenario,
    /// Its cameras.
    pub rig: StereoRig,
    /// Time between frames, seconds.
    pub frame_interval_s: f64,
    /// Frames when none are asked for.
    pub default_frames: usize,
    /// Particles when none are asked for.
    pub default_particles: usize,
    /// Axis-aligned box in the world frame the particles live in.
    pub domain_min: Point3<f64>,
    /// See `domain_min`.
    pub domain_max: Point3<f64>,
    /// The flow.
    pub flow: Flow,
    /// Mean particle diameter, metres.
    pub diameter_m: f64,
    /// Its standard deviation, metres.
    pub diameter_sd_m: f64,
    /// The method's illumination coefficient l: brightness = l / (4 pi R^2), grey levels m^2.
    pub illumination: f64,
    /// Relative standard deviation of per-particle brightness.
    pub brightness_spread: f64,
    /// Background grey level at the image's left edge, and its rise to the right edge.
    pub background: f64,
    /// See `background`.
    pub background_gradient: f64,
    /// Relative change of particle brightness from the image's left edge to its right edge.
    pub illumination_gradient: f64,
    /// Sensor noise, grey levels (standard deviation).
    pub noise_sd: f64,
    /// How the headset moves.
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

impl ScenarioSpec {
    /// The scenario's definition: rig, frame rate, domain, flow, particles and imaging.
    pub fn new(scenario: Scenario) -> Self {
        match scenario {
            Scenario::Uniform => unit_cube(scenario),
            Scenario::Dense => ScenarioSpec {
                default_particles: 1000,
                default_frames: 60,
                ..unit_cube(scenario)
            },
            Scenario::Turbulence => {
                let mut rng = Rng::new(0x7u64 << 32 | 99);
                ScenarioSpec {
                    default_frames: 60,
                    flow: Flow::turbulence(&mut rng, 1.0, 0.25, 1.0),
                    ..unit_cube(scenario)
                }
            }
            Scenario::Flume => flume(scenario),
            Scenario::WindTunnel => wind_tunnel(scenario),
            Scenario::MovingHead => moving_head(scenario),
            Scenario::HololensRaw => hololens_raw(scenario),
            Scenario::Fast => ScenarioSpec {
                // The domain fills the view, so particles cross it instead of appearing and
                // vanishing inside it.
                default_particles: 100,
                domain_min: Point3::new(-0.8, -0.6, 0.7),
                domain_max: Point3::new(0.8, 0.6, 1.1),
                flow: Flow::Uniform(Vector3::new(1.53, -1.38, 0.0) * 2.0),
                ..wind_tunnel(scenario)
            },
            Scenario::Creep => ScenarioSpec {
                default_particles: 200,
                diameter_m: 0.006,
                diameter_sd_m: 0.0008,
                // 0.5 px per frame at 0.5 m.
                flow: Flow::Uniform(Vector3::new(0.0172, -0.0069, 0.0)),
                ..flume(scenario)
            },
            Scenario::Vortex => vortex(scenario),
            Scenario::WideConvergent => wide_convergent(scenario),
            Scenario::Seeded => seeded(scenario),
            Scenario::SeededTurbulence => {
                let mut rng = Rng::new(0x5EED << 32 | 7);
                ScenarioSpec {
                    default_frames: 90,
                    flow: Flow::turbulence(&mut rng, 0.12, 0.1, 0.4),
                    ..seeded(scenario)
                }
            }
            Scenario::Cluttered => cluttered(scenario),
            Scenario::Convergent => convergent(scenario),
        }
    }
}

/// The method's synthetic camera: 960x720 with a 60 degree diagonal field of view, looking at a
/// unit cube.
fn unit_cube(scenario: Scenario) -> ScenarioSpec {
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
}

/// HoloLens-2-like front cameras looking into a flume.
fn flume(scenario: Scenario) -> ScenarioSpec {
    ScenarioSpec {
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
    }
}

/// Foam particles in a wind tunnel, seen by the flume's cameras.
fn wind_tunnel(scenario: Scenario) -> ScenarioSpec {
    ScenarioSpec {
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
        ..flume(scenario)
    }
}

/// Small particles (6 mm: 2.5-6 px) as densely as PTV users seed, in a 10 cm slab that fills
/// both views, so the images are evenly crowded.
fn seeded(scenario: Scenario) -> ScenarioSpec {
    ScenarioSpec {
        default_frames: 90,
        default_particles: 1540,
        domain_min: Point3::new(-0.33, -0.32, 0.5),
        domain_max: Point3::new(0.43, 0.32, 0.6),
        diameter_m: 0.006,
        diameter_sd_m: 0.0013,
        scatter_depth_reentry: true,
        ..flume(scenario)
    }
}

/// The flume seen through the raw HoloLens 2 geometry.
fn hololens_raw(scenario: Scenario) -> ScenarioSpec {
    ScenarioSpec {
        rig: hololens_raw_rig(),
        // Raw frames are sideways: the baseline (rig y) is world x, so the world is upright.
        head: HeadMotion::Fixed(Isometry3::rotation(Vector3::z() * (-PI / 2.0))),
        default_particles: 20,
        domain_min: Point3::new(-0.1, -0.15, 0.38),
        domain_max: Point3::new(0.2, 0.15, 0.68),
        ..flume(scenario)
    }
}

/// The flume seen by a wearer who sways and turns.
fn moving_head(scenario: Scenario) -> ScenarioSpec {
    ScenarioSpec {
        default_particles: 20,
        domain_min: Point3::new(-0.15, -0.15, 0.36),
        domain_max: Point3::new(0.25, 0.15, 0.66),
        head: HeadMotion::Oscillating {
            translation_amplitude_m: Vector3::new(0.02, 0.01, 0.015),
            translation_frequency_hz: Vector3::new(0.4, 0.3, 0.25),
            rotation_amplitude_rad: Vector3::new(0.02, 0.035, 0.05),
            rotation_frequency_hz: Vector3::new(0.2, 0.5, 0.35),
        },
        ..flume(scenario)
    }
}

/// Solid-body rotation about an axis along the flume camera's view.
fn vortex(scenario: Scenario) -> ScenarioSpec {
    ScenarioSpec {
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
        ..flume(scenario)
    }
}

/// A long-lens lab rig, 45 degrees between the axes, small particles around the crossing.
fn wide_convergent(scenario: Scenario) -> ScenarioSpec {
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
        ..flume(scenario)
    }
}

/// The raw HoloLens 2 geometry in a furnished room: blur, vignetting, hot pixels, LEDs, posters.
fn cluttered(scenario: Scenario) -> ScenarioSpec {
    ScenarioSpec {
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
        ..hololens_raw(scenario)
    }
}

/// A lab rig of two toed-in cameras, the particles around the axes' crossing (0.15 m across,
/// 0.56 m out, in the baseline's frame).
fn convergent(scenario: Scenario) -> ScenarioSpec {
    let toe_in = 15f64.to_radians();
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
        ..flume(scenario)
    }
}
