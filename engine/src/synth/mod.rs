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

mod flow;
mod render;
mod rigs;
mod rng;
mod scenario;

use nalgebra::{Isometry3, Point3, Vector3};

pub use flow::{Flow, HeadMotion, Mode};
use render::{finish_image, fixed_layers, render_particle, touching};
pub use rigs::{convergent_rig, hololens_raw_rig, parallel_rig};
pub use rng::Rng;
pub use scenario::{Clutter, Scenario, ScenarioSpec};

/// One row of `truth.csv`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TruthRow {
    /// The frame.
    pub frame: u64,
    /// Its time, seconds.
    pub t_s: f64,
    /// The particle's id (a new one each time it re-enters).
    pub pid: u64,
    /// Position, world frame, metres.
    pub position: Point3<f64>,
    /// Velocity, world frame, m/s.
    pub velocity: Vector3<f64>,
    /// Whether the left and the right image show it, where the truth says (`None`: not stated;
    /// projected inside an image counts as shown).
    pub visible: Option<[bool; 2]>,
}

/// One rendered frame with its truth.
#[derive(Debug, Clone)]
pub struct SynthFrame {
    /// The frame's index.
    pub index: u64,
    /// Its time, seconds.
    pub t_s: f64,
    /// The headset's pose (`None`: world = rig).
    pub world_from_rig: Option<Isometry3<f64>>,
    /// The left image, row-major.
    pub left: Vec<u8>,
    /// The right image, row-major.
    pub right: Vec<u8>,
    /// The truth of every particle in the domain.
    pub truth: Vec<TruthRow>,
    /// Particles whose centre projects inside both images.
    pub visible_in_both: usize,
    /// Particles whose centre projects inside the left image, and those of them whose image
    /// there touches or overlaps another particle's.
    pub in_view_left: usize,
    /// See `in_view_left`.
    pub touching_left: usize,
}

#[derive(Debug, Clone)]
pub(super) struct Particle {
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
    /// A generator of `spec` with `particles` particles, deterministic for `seed`.
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
                visible: None,
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
