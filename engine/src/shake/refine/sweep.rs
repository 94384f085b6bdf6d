//! One camera's overlapping particles measured in sweeps: each particle in turn fitted alone
//! against its pixels with its neighbours' modelled images taken out, until no particle
//! moves. A particle's fit is then small (its centre, amplitude, radius, and the floor under
//! it) however many particles touch in a chain, and every particle is fitted once per sweep,
//! not once in every group it belongs to.

use super::step::Fit;
use super::{
    logistic_table, window, Free, InFit, Member, CONVERGED_STEP_PX, MARGIN_PX, MAX_ITERATIONS,
    SETTLED_STEP_IN_REACHES,
};
use crate::geometry::RectPoint;
use crate::spatial::{PointGrid, GRID_CELL_PX};
use crate::ImageView;

/// A particle whose step moves its centre (along x plus along y) by less than this fraction
/// of its centre's standard error (from its fit's own residuals) has settled, and a sweep in
/// which none moves more ends the sweeps: a smaller step changes no measurement. Sweeps of
/// touching particles converge slowly (each moves its neighbours' optimum a little), and a
/// fixed step of a fraction of a pixel spends most of their steps where the noise is larger.
/// A lone fit, which learns the radius and edge too, runs on to [`CONVERGED_STEP_PX`], as its
/// centre settles before its shape does.
const SETTLED_IN_SIGMAS: f64 = 0.25;

/// The particles of one camera's model, by id, as the sweeps leave them.
#[derive(Default)]
pub(super) struct Sweep {
    /// Per id (ids are small: a camera's detections, then its predicted particles), the
    /// particle's index, [`usize::MAX`] where none was added.
    index: Vec<usize>,
    seeds: Vec<Member>,
    /// Each particle and the floor under it, as the sweeps have taken them so far.
    fits: Vec<Fit>,
    /// Each particle's pixels (its seed's box).
    samples: Vec<Vec<(f64, f64, f64)>>,
    /// Per particle, the others whose light reaches its box.
    touching: Vec<Vec<usize>>,
    last_move_px: Vec<f64>,
    gone: Vec<bool>,
    failed: Vec<bool>,
    /// The neighbours' models of the particle a step fits (a buffer kept across steps).
    others: Vec<InFit>,
    /// Per particle, whether it is held where it was added (its light counts, it is not
    /// fitted).
    held: Vec<bool>,
}

impl Sweep {
    /// Adds particle `id` seeded as `seed` (once; a second add of the same id is ignored).
    pub(super) fn add(&mut self, id: usize, seed: Member) {
        if id >= self.index.len() {
            self.index.resize(id + 1, usize::MAX);
        }
        if self.index[id] == usize::MAX {
            self.index[id] = self.seeds.len();
            self.seeds.push(seed);
            self.held.push(false);
        }
    }

    /// Adds particle `id` as [`Self::add`] does (once), held where it stands: measured
    /// already, it lends its light to the others' fits and is not fitted again.
    pub(super) fn hold(&mut self, id: usize, at: Member) {
        if self.element(id).is_none() {
            self.add(id, at);
            if let Some(held) = self.held.last_mut() {
                *held = true;
            }
        }
    }

    /// Every particle fitted in turn until no particle moves by more than
    /// [`SETTLED_IN_SIGMAS`] of its centre's standard error (nor by more than
    /// [`CONVERGED_STEP_PX`]) in a sweep, or for as many sweeps as a fit takes steps.
    pub(super) fn run(&mut self, image: ImageView<'_>) {
        self.prepare(|m| window(image, &[(m.at, half_px(m))]));
        self.sweep();
    }

    /// As [`Self::run`], each particle fitted against those of `pixels` (x, y, grey level)
    /// in its box only.
    pub(super) fn run_on(&mut self, pixels: &[(f64, f64, f64)]) {
        self.prepare(|m| {
            let half = half_px(m);
            pixels
                .iter()
                .filter(|p| (p.0 - m.at.x).abs() <= half && (p.1 - m.at.y).abs() <= half)
                .copied()
                .collect()
        });
        self.sweep();
    }

    /// The sweeps of [`Self::run`] on prepared particles.
    fn sweep(&mut self) {
        let n = self.seeds.len();
        let mut active = vec![true; n];
        for _ in 0..MAX_ITERATIONS {
            let mut moved = vec![false; n];
            for i in 0..n {
                if active[i] && !self.held[i] && !self.gone[i] && !self.failed[i] {
                    moved[i] = self.step(i);
                }
            }
            if !moved.iter().any(|&m| m) {
                break;
            }
            // A particle is fitted again where it or a neighbour moved.
            for i in 0..n {
                active[i] = moved[i] || self.touching[i].iter().any(|&j| moved[j]);
            }
        }
    }

    /// Each particle's pixels (`sample` of its seed) and the particles whose light reaches
    /// them.
    fn prepare(&mut self, sample: impl Fn(&Member) -> Vec<(f64, f64, f64)>) {
        let n = self.seeds.len();
        self.last_move_px = self
            .held
            .iter()
            .map(|&h| if h { 0.0 } else { f64::INFINITY })
            .collect();
        self.gone = vec![false; n];
        self.failed = vec![false; n];
        // A held particle is not fitted: it needs no pixels.
        self.samples = self
            .seeds
            .iter()
            .zip(&self.held)
            .map(|(m, &held)| if held { Vec::new() } else { sample(m) })
            .collect();
        self.fits = self
            .seeds
            .iter()
            .zip(&self.samples)
            .map(|(&member, s)| Fit::new(member, s))
            .collect();
        // The grid takes points of any plane: these are raw pixels. A held particle without
        // light (one an earlier sweep pushed off, held wherever that step threw it) touches
        // nothing.
        let grid = PointGrid::new(
            self.seeds
                .iter()
                .enumerate()
                .filter(|(i, m)| !self.held[*i] || m.shape.amplitude != 0.0)
                .map(|(i, m)| {
                    (
                        RectPoint {
                            x: m.at.x,
                            y: m.at.y,
                        },
                        i,
                    )
                }),
            GRID_CELL_PX,
        );
        let light_reach = |m: &Member| m.shape.reach_px() + MARGIN_PX;
        let farthest = self.seeds.iter().map(light_reach).fold(0.0, f64::max);
        self.touching = self
            .seeds
            .iter()
            .enumerate()
            .map(|(i, m)| {
                // A held particle is never stepped: whose light reaches it does not matter.
                if self.held[i] {
                    return Vec::new();
                }
                let half = half_px(m);
                grid.near(m.at.x, m.at.y, (half + farthest) * std::f64::consts::SQRT_2)
                    .filter(|&&(p, j)| {
                        let reach = half + light_reach(&self.seeds[j]);
                        j != i && (p.x - m.at.x).abs() <= reach && (p.y - m.at.y).abs() <= reach
                    })
                    .map(|&(_, j)| j)
                    .collect()
            })
            .collect();
    }

    /// One Gauss-Newton step of particle `i`'s fit (its floor, centre, amplitude and radius)
    /// against its pixels with its neighbours' light taken out; whether it moved by more than
    /// it has settled to (see [`SETTLED_IN_SIGMAS`]).
    fn step(&mut self, i: usize) -> bool {
        let mut others = std::mem::take(&mut self.others);
        others.clear();
        others.extend(self.models(&self.touching[i]));
        let seed = self.seeds[i];
        let mut fit = self.fits[i];
        let stepped = fit.step(
            &self.samples[i],
            &others,
            (Free::Radius, seed.shape.radius_px),
        );
        self.others = others;
        let Some(stepped) = stepped else {
            self.failed[i] = true;
            return false;
        };
        if fit.member.left_reach_of(&seed) {
            self.gone[i] = true;
            fit.member.shape.amplitude = 0.0;
        }
        self.fits[i] = fit;
        self.last_move_px[i] = stepped.moved_px;
        let settled_px = (SETTLED_IN_SIGMAS * stepped.centre_sigma_px).max(CONVERGED_STEP_PX);
        stepped.moved_px >= settled_px
    }

    /// The models of particles `ids` as they stand, but those gone.
    fn models<'s>(&'s self, ids: &'s [usize]) -> impl Iterator<Item = InFit> + 's {
        ids.iter()
            .filter(|&&j| !self.gone[j])
            .map(|&j| InFit::new(&self.fits[j].member))
    }

    /// Particle `id`'s index, if it was added.
    pub(super) fn element(&self, id: usize) -> Option<usize> {
        self.index.get(id).copied().filter(|&i| i != usize::MAX)
    }

    /// Particle `i` as the sweeps left it (no light where it is gone).
    pub(super) fn member(&self, i: usize) -> Member {
        self.fits[i].member
    }

    /// Whether particle `i` has a fit (none where a step of it failed).
    pub(super) fn fitted(&self, i: usize) -> bool {
        !self.failed[i]
    }

    /// Whether particle `i`'s last step was small against its image's reach (see
    /// [`SETTLED_STEP_IN_REACHES`]).
    pub(super) fn settled(&self, i: usize) -> bool {
        self.gone[i]
            || self.last_move_px[i] / self.seeds[i].shape.reach_px() < SETTLED_STEP_IN_REACHES
    }

    /// The RMS residual on particle `i`'s pixels of the model: its floor and every particle
    /// whose light reaches them.
    pub(super) fn rms_on(&self, i: usize) -> f64 {
        let table = logistic_table();
        let floor = self.fits[i].floor;
        let lit: Vec<InFit> = self
            .models(std::slice::from_ref(&i))
            .chain(self.models(&self.touching[i]))
            .collect();
        let samples = &self.samples[i];
        let sum: f64 = samples
            .iter()
            .map(|&(x, y, v)| {
                let light: f64 = lit.iter().map(|o| o.light(table, (x, y))).sum();
                (v - floor.at((x, y)) - light).powi(2)
            })
            .sum();
        (sum / samples.len().max(1) as f64).sqrt()
    }
}

/// Half the width of a particle's box.
fn half_px(m: &Member) -> f64 {
    m.shape.radius_px + MARGIN_PX
}
