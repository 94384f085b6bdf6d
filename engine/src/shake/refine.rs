//! Overlapping particles measured with what their tracks know. Each track learns its
//! particle's image shape in each camera from the frames where the particle stands alone: a
//! soft-edged disc, `a / (1 + exp((r - radius) / edge))`, which is a blurred spot for a small
//! radius and a sharp disc for a large one. Where the particle overlaps a neighbour, it is
//! fitted with its edge held at what its track learnt, its centre and amplitude free and its
//! radius free within [`RADIUS_RANGE`] of what its track learnt (the image grows and shrinks as
//! the particle's depth changes, and a track learns its shape only where the particle stands
//! alone), on a sloped background, against its pixels with its neighbours' modelled images
//! taken out (which are fitted the same way, in turn, until none moves). A free fit of two
//! overlapping images trades width against position (the reason a cut's centroids are not
//! measured); with the widths held near what the tracks learnt, the centres are pinned.

mod group;
mod part;
mod step;
mod sweep;

use group::{members_of, Group};

use crate::geometry::{PixelPoint, RectPoint};
use crate::spatial::{median, PointGrid, GRID_CELL_PX};
use crate::ImageView;

/// Gauss-Newton steps of a lone fit, or sweeps, at most; a step (a sweep) that moves no
/// centre by more than [`CONVERGED_STEP_PX`] ends the fit.
const MAX_ITERATIONS: usize = 12;
const CONVERGED_STEP_PX: f64 = 5e-3;
/// A fit explains its pixels when their RMS residual is within this many times what the
/// camera's lone particles leave (noise and one disc's mismatch, learnt): a neighbour no track
/// knows has only a guessed shape. A fit measuring a detected particle's centre may leave each
/// member's mismatch on top (see `Group::judge`). A lone blob explained worse is not one
/// particle, and teaches no shape.
const MAX_RESIDUAL_RATIO: f64 = 4.0;
/// A particle whose last step still moved it by more than this fraction of its image's reach
/// has not settled (it swings between two solutions, or creeps along a valley), and neither
/// it nor a particle whose group it belongs to is measured.
const SETTLED_STEP_IN_REACHES: f64 = 0.05;
/// Pixels of background around a particle's edge that its fits see, pixels.
const MARGIN_PX: f64 = 2.0;

/// A particle's image shape in one camera.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Shape {
    /// Where the disc's edge falls to half its height, pixels.
    pub(crate) radius_px: f64,
    /// The edge's width, pixels.
    pub(crate) edge_px: f64,
    /// The height above the background, grey levels.
    pub(crate) amplitude: f64,
    /// Whether it was guessed from a detection's size rather than learnt from its pixels (a
    /// particle that never stood alone); a guessed shape is learnt as soon as it can be.
    pub(crate) guessed: bool,
}

impl Shape {
    /// Distance within which the image holds nearly all its light, pixels.
    fn reach_px(&self) -> f64 {
        self.radius_px + 3.0 * self.edge_px
    }
}

const STEPS_PER_UNIT: f64 = 32.0;
const REACH: f64 = 20.0;

/// The logistic step's table, on steps of 1 / [`STEPS_PER_UNIT`] over +-[`REACH`].
fn logistic_table() -> &'static [f64] {
    static TABLE: std::sync::LazyLock<Vec<f64>> = std::sync::LazyLock::new(|| {
        let n = (2.0 * REACH * STEPS_PER_UNIT) as usize;
        (0..=n + 1)
            .map(|i| 1.0 / (1.0 + (i as f64 / STEPS_PER_UNIT - REACH).exp()))
            .collect()
    });
    &TABLE
}

/// The logistic step `1 / (1 + exp(z))`, interpolated in `table` ([`logistic_table`], which a
/// fit looks up once): fits evaluate it for every pixel, member and iteration. Linear
/// interpolation on steps of 1/32 is within 2e-5 of the exact value; beyond +-20 the step is
/// flat to 2e-9.
fn logistic_in(table: &[f64], z: f64) -> f64 {
    let u = (z.clamp(-REACH, REACH) + REACH) * STEPS_PER_UNIT;
    // `u` is in 0..=2 REACH STEPS_PER_UNIT: through i32, the conversion is one instruction.
    let k = u as i32;
    let (i, f) = (k as usize, u - f64::from(k));
    table[i] * (1.0 - f) + table[i + 1] * f
}

/// A particle in a fit: its centre and shape (a fit that learns may change the shape's radius
/// and edge; one that measures only its centre and amplitude).
#[derive(Debug, Clone, Copy)]
struct Member {
    at: PixelPoint,
    shape: Shape,
}

impl Member {
    /// Whether a fit has pushed this particle further from its `seed` than the seed's image
    /// reaches: there is no light of it there, it is gone.
    fn left_reach_of(&self, seed: &Member) -> bool {
        farther_than(
            (self.at.x - seed.at.x, self.at.y - seed.at.y),
            seed.shape.reach_px() + MARGIN_PX,
        )
    }
}

/// Whether the offset `(dx, dy)` is longer than `distance` (non-negative), without the square
/// root: the fits ask it per particle and step.
fn farther_than((dx, dy): (f64, f64), distance: f64) -> bool {
    dx * dx + dy * dy > distance * distance
}

/// The outcome of a fit: the members as fitted, the RMS residual (grey levels), and whether
/// its steps settled (see [`SETTLED_STEP_IN_REACHES`]).
struct Fitted {
    members: Vec<Member>,
    rms: f64,
    settled: bool,
}

/// The background under a fit: a level at its box's centre and its slope across it. The
/// background's own gradient (uneven lighting, a room behind the particles) would otherwise
/// stay in the residual, and pull the centre towards the light.
#[derive(Debug, Clone, Copy)]
struct Floor {
    level: f64,
    slope: (f64, f64),
    centre: (f64, f64),
}

/// The floor's unknowns: its level and its slope along x and y.
const FLOOR_TERMS: usize = 3;

impl Floor {
    /// A flat floor at the samples' darkest level, about their mean position.
    fn under(samples: &[(f64, f64, f64)]) -> Self {
        let n = samples.len().max(1) as f64;
        let (sx, sy) = samples
            .iter()
            .fold((0.0, 0.0), |(a, b), s| (a + s.0, b + s.1));
        Self {
            level: samples.iter().map(|s| s.2).fold(f64::MAX, f64::min),
            slope: (0.0, 0.0),
            centre: (sx / n, sy / n),
        }
    }

    fn at(&self, (x, y): (f64, f64)) -> f64 {
        self.level + self.slope.0 * (x - self.centre.0) + self.slope.1 * (y - self.centre.1)
    }
}

/// The shape of a particle standing alone at `at` (equivalent diameter `diameter_px`), and
/// the RMS residual the fit left; `None` where the fit fails or ends implausibly. A shape
/// learnt before (`known`) starts the fit: the particle's image changes little from frame to
/// frame, so the fit has little left to do.
pub(crate) fn learn_shape(
    image: ImageView<'_>,
    at: PixelPoint,
    diameter_px: f64,
    known: Option<Shape>,
) -> Option<(Shape, f64)> {
    let radius_px = (0.5 * diameter_px).max(0.5);
    let samples = window(image, &[(at, radius_px + 1.0 + MARGIN_PX)]);
    let low = samples.iter().map(|s| s.2).fold(f64::MAX, f64::min);
    let peak = image.bilinear(at) - low;
    let (seed_radius, edge_px) = match known.filter(|k| !k.guessed) {
        Some(k) => (k.radius_px, k.edge_px),
        None => (radius_px, 0.5),
    };
    let seed = Member {
        at,
        shape: Shape {
            radius_px: seed_radius,
            edge_px,
            amplitude: peak.max(1.0),
            guessed: false,
        },
    };
    let (m, rms) = fit_alone(&samples, seed)?;
    let plausible = m.shape.edge_px > 0.05
        && m.shape.radius_px > 0.0
        && m.shape.radius_px < 2.0 * radius_px + 1.0
        && (m.at.x - at.x).hypot(m.at.y - at.y) < radius_px;
    plausible.then_some((m.shape, rms))
}

/// A lone particle's shape fitted from `seed` (its floor, centre, amplitude, radius and edge
/// free) until its centre stops moving: the particle as fitted and the RMS residual the fit
/// had at its last step; `None` where a step fails or the centre leaves its reach.
fn fit_alone(samples: &[(f64, f64, f64)], seed: Member) -> Option<(Member, f64)> {
    let mut fit = step::Fit::new(seed, samples);
    let mut cost = f64::INFINITY;
    for _ in 0..MAX_ITERATIONS {
        let stepped = fit.step(samples, &[], (Free::Shape, seed.shape.radius_px))?;
        cost = stepped.cost;
        if fit.member.left_reach_of(&seed) {
            return None;
        }
        if stepped.moved_px < CONVERGED_STEP_PX {
            break;
        }
    }
    Some((fit.member, (cost / samples.len() as f64).sqrt()))
}

/// Whether every member of a group fit stayed within its radius of where it was seeded, but
/// those that `may_vanish` (particles without a detection of their own, which may not be
/// there: the fit is free to move them off).
fn stayed(fitted: &Fitted, seeds: &[Member], may_vanish: impl Fn(usize) -> bool) -> bool {
    fitted
        .members
        .iter()
        .zip(seeds)
        .enumerate()
        .all(|(k, (f, s))| {
            may_vanish(k) || (f.at.x - s.at.x).hypot(f.at.y - s.at.y) <= s.shape.radius_px
        })
}

/// The shape to fit a particle with: its own in this camera, else the one its track learnt in
/// the other camera (both see it from nearly the same distance), a learnt shape before a
/// guessed one.
pub(crate) fn best_known(own: Option<Shape>, other: Option<Shape>) -> Option<Shape> {
    match (own, other) {
        (Some(a), _) if !a.guessed => Some(a),
        (_, Some(b)) if !b.guessed => Some(b),
        (a, b) => a.or(b),
    }
}

/// What a fit may change besides the members' centres and amplitudes.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Free {
    /// Every member's radius and edge: a lone particle's shape is learnt.
    Shape,
    /// Every member's radius, within [`RADIUS_RANGE`] of its seed's: a particle among
    /// neighbours is measured with the edge its track learnt.
    Radius,
}

/// How far a fit among neighbours may take a radius from its seed's (what its track learnt,
/// or a guess), as factors.
const RADIUS_RANGE: (f64, f64) = (0.7, 1.4);

/// A member as a fit iteration evaluates it: its centre, the square of its reach, its
/// amplitude, radius and inverse edge width.
struct InFit {
    at: PixelPoint,
    reach_sq: f64,
    amplitude: f64,
    radius_px: f64,
    per_edge: f64,
}

impl InFit {
    fn new(m: &Member) -> Self {
        let reach = m.shape.reach_px() + MARGIN_PX;
        Self {
            at: m.at,
            reach_sq: reach * reach,
            amplitude: m.shape.amplitude,
            radius_px: m.shape.radius_px,
            per_edge: 1.0 / m.shape.edge_px,
        }
    }

    /// Where pixel `(x, y)` lies from the centre (`dx`, `dy`, distance `r`, and `z`, the
    /// distance past the radius in edge widths) and the disc's height there per unit
    /// amplitude; `None` beyond its reach.
    fn at(&self, table: &[f64], (x, y): (f64, f64)) -> Option<[f64; 5]> {
        let (dx, dy) = (x - self.at.x, y - self.at.y);
        let r_sq = dx * dx + dy * dy;
        if r_sq > self.reach_sq {
            return None;
        }
        let r = r_sq.sqrt();
        let z = (r - self.radius_px) * self.per_edge;
        Some([dx, dy, r, z, logistic_in(table, z)])
    }

    /// This member's light at pixel `(x, y)` (none beyond its reach).
    fn light(&self, table: &[f64], p: (f64, f64)) -> f64 {
        self.at(table, p).map_or(0.0, |[.., g]| self.amplitude * g)
    }

    /// The Jacobian values at a pixel where [`InFit::at`] found it (`dx`, `dy`, `r`, `z`
    /// and the disc's height `g`): x, y, amplitude (the disc's height per unit amplitude),
    /// radius, then edge where free.
    #[inline]
    fn values(&self, [dx, dy, r, z, g]: [f64; 5], free: Free) -> [f64; 5] {
        let a = self.amplitude;
        let dg_dz = -g * (1.0 - g);
        let dg_dr = dg_dz * self.per_edge;
        let mut values = [0.0, 0.0, g, -a * dg_dr, 0.0];
        // r grows as the centre moves away from the pixel; at the centre itself the centre's
        // derivatives are left out.
        if r > 1e-9 {
            let along = -a * dg_dr / r;
            values[0] = along * dx;
            values[1] = along * dy;
        }
        if free == Free::Shape {
            values[4] = -a * dg_dz * z * self.per_edge;
        }
        values
    }
}

/// The pixels (x, y, grey level) within `half` of any of the centres (a box), each once, but
/// those at the sensor's full scale: a clipped pixel (where overlapping particle images add up
/// past it, or a near particle is bright) says only that the light was at least that much.
fn window(image: ImageView<'_>, around: &[(PixelPoint, f64)]) -> Vec<(f64, f64, f64)> {
    let (w, h) = (image.width as i64, image.height as i64);
    let bounds = |c: f64, half: f64, size: i64| {
        (
            ((c - half).floor() as i64).clamp(0, size - 1),
            ((c + half).ceil() as i64).clamp(0, size - 1),
        )
    };
    let (mut x0, mut x1, mut y0, mut y1) = (i64::MAX, i64::MIN, i64::MAX, i64::MIN);
    for (c, half) in around {
        let (a, b) = bounds(c.x, *half, w);
        let (d, e) = bounds(c.y, *half, h);
        (x0, x1, y0, y1) = (x0.min(a), x1.max(b), y0.min(d), y1.max(e));
    }
    let mut samples = Vec::with_capacity(((x1 - x0 + 1) * (y1 - y0 + 1)).max(0) as usize);
    for y in y0..=y1 {
        let row = &image.pixels[(y * w) as usize..((y + 1) * w) as usize];
        for x in x0..=x1 {
            let near = around.iter().any(|(c, half)| {
                (x as f64 - c.x).abs() <= *half && (y as f64 - c.y).abs() <= *half
            });
            let value = row[x as usize];
            if near && value < u8::MAX {
                samples.push((x as f64, y as f64, f64::from(value)));
            }
        }
    }
    samples
}

/// A detection as one camera's shake sees it.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Seen {
    /// Its centroid, raw pixels.
    pub(crate) centroid: PixelPoint,
    /// Its equivalent diameter, pixels.
    pub(crate) diameter_px: f64,
    /// Whether it was told apart from any neighbour without a cut or a fit.
    pub(crate) clear: bool,
    /// Whether its centre was fitted among its neighbours already (parted with the tracks'
    /// shapes, or fitted as a spot): it is not fitted again.
    pub(crate) fitted: bool,
    /// Its centroid, rectified (where neighbours are looked for).
    pub(crate) rect: RectPoint,
}

/// A predicted particle in one camera: the detection its track claimed there (an index into
/// the camera's [`Seen`]s), if any, where its track predicted it (raw and rectified pixels),
/// and whether its track should learn its shape again.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Wanted {
    pub(crate) detection: Option<usize>,
    pub(crate) predicted_px: Option<PixelPoint>,
    pub(crate) predicted_rect: RectPoint,
    /// Its predicted disparity, rectified pixels: its image's size scales with it.
    pub(crate) disparity_px: f64,
    pub(crate) relearn: bool,
}

/// What one camera's shake made of a predicted particle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum Measured {
    /// Its detection stands as detected (clear, or no fit explained its overlap).
    AsDetected,
    /// Fitted among its neighbours with the shapes their tracks learnt: its centre, raw pixels.
    Refitted(PixelPoint),
    /// Not in this image: no detection of its own, and no particle where its track put it.
    Missing,
}

/// What one camera's shake learns across frames: the RMS residual its lone particles' fits
/// leave (noise and the model's mismatch), the scale a group fit is judged by, and their
/// typical edge width, the shape guessed for a neighbour no track knows.
#[derive(Debug, Clone, Default)]
pub(crate) struct CameraShake {
    lone_rms: Option<f64>,
    edge_px: Option<f64>,
    /// A learnt disc radius over half the detection's equivalent diameter: how a clear
    /// detection's size (measured at the threshold) maps to the disc's half-height radius.
    radius_per_half_diameter: Option<f64>,
    /// A learnt disc radius over the particle's disparity, rectified pixels.
    radius_per_disparity: Option<f64>,
    /// The largest radius of the lone particles: a guessed shape is no larger (a guess from a
    /// ghost's disparity or a large bright blob would otherwise cover the image).
    widest_px: Option<f64>,
}

/// One camera's detections by where they are (rectified), and the widest of them: built once
/// per camera and frame for both learning and measuring.
struct Neighbourhood {
    grid: PointGrid,
    widest: f64,
}

impl Neighbourhood {
    fn of(seen: &[Seen]) -> Self {
        Self {
            grid: PointGrid::new(
                seen.iter().enumerate().map(|(i, s)| (s.rect, i)),
                GRID_CELL_PX,
            ),
            widest: seen.iter().map(|s| s.diameter_px).fold(0.0, f64::max),
        }
    }

    /// Whether detection `i` stands alone: clear, and no other detection's image within
    /// twice the fits' margin of its own.
    fn alone(&self, seen: &[Seen], i: usize) -> bool {
        let (c, d) = (seen[i].rect, seen[i].diameter_px);
        seen[i].clear
            && self.grid.near(c.x, c.y, d + self.widest).all(|&(p, j)| {
                j == i
                    || farther_than(
                        (p.x - c.x, p.y - c.y),
                        0.5 * (d + seen[j].diameter_px) + 2.0 * MARGIN_PX,
                    )
            })
    }
}

impl CameraShake {
    /// One camera's predicted particles measured. Each one standing alone (clear, and no
    /// other detection within reach) teaches its track's shape (where the track has none, or
    /// `relearn` says so). Each one whose track knows its shape is fitted among its
    /// neighbours where its image may touch another (its detection does not stand alone, or a
    /// hidden particle is near) or where it has no detection of its own: every neighbour
    /// seeded where its track puts it (a clear detection at its centroid, another at its
    /// prediction; a detection no track knows at its centroid, as a disc of its size), shapes
    /// held, centres and amplitudes free, each fitted against the others' light in turn. A
    /// track that has not learnt its shape in this camera
    /// borrows the one it learnt in the other (`other_camera`): the two see the particle from
    /// nearly the same distance.
    pub(crate) fn measure(
        &mut self,
        image: ImageView<'_>,
        seen: &[Seen],
        wanted: &[Wanted],
        shapes: &mut [Option<Shape>],
        other_camera: &[Option<Shape>],
    ) -> Vec<Measured> {
        let near = Neighbourhood::of(seen);
        self.learn(image, seen, wanted, &near, shapes);
        let unmeasured = |w: &Wanted| {
            w.detection
                .map_or(Measured::Missing, |_| Measured::AsDetected)
        };
        let (Some(lone_rms), Some(edge_px), Some(widest_px)) =
            (self.lone_rms, self.edge_px, self.widest_px)
        else {
            return wanted.iter().map(unmeasured).collect();
        };
        let members = members_of(seen, wanted, shapes, other_camera);
        let group = Group::new(
            (image, seen, wanted),
            &members,
            &near,
            (edge_px, widest_px, MAX_RESIDUAL_RATIO * lone_rms),
        );
        group
            .measure_all()
            .into_iter()
            .zip(wanted)
            .map(|(m, w)| m.unwrap_or_else(|| unmeasured(w)))
            .collect()
    }

    /// The wanted particles' tracks learn their shapes: each one whose detection stands alone
    /// (clear, and no other detection within reach) from its pixels, where its track has no
    /// learnt shape or `relearn` says so; one that has not stood alone gets a guessed shape.
    pub(crate) fn learn_shapes(
        &mut self,
        image: ImageView<'_>,
        seen: &[Seen],
        wanted: &[Wanted],
        shapes: &mut [Option<Shape>],
    ) {
        self.learn(image, seen, wanted, &Neighbourhood::of(seen), shapes);
    }

    /// Lone found particles teach their tracks' shapes, and the camera the residual they
    /// leave and the edge they have; the other particles without a learnt shape get one
    /// guessed with what the camera now knows.
    fn learn(
        &mut self,
        image: ImageView<'_>,
        seen: &[Seen],
        wanted: &[Wanted],
        near: &Neighbourhood,
        shapes: &mut [Option<Shape>],
    ) {
        let mut learnt = Learnt::default();
        for (w, shape) in wanted.iter().zip(shapes.iter_mut()) {
            // A shape is learnt once, and again when `relearn` says so; until then a guess
            // follows the particle's size.
            let attempt = shape.is_none() || w.relearn;
            if let Some(d) = w.detection.filter(|&d| attempt && near.alone(seen, d)) {
                let s = &seen[d];
                // A lone blob the disc explains worse than the camera's lone particles are
                // explained is not one particle (two merged, a streak): nothing to learn.
                let learnt_now =
                    learn_shape(image, s.centroid, s.diameter_px, *shape).filter(|(_, rms)| {
                        self.lone_rms
                            .is_none_or(|lone| *rms <= MAX_RESIDUAL_RATIO * lone)
                    });
                if let Some((shape_now, rms)) = learnt_now {
                    *shape = Some(shape_now);
                    learnt.add(shape_now, rms, s.diameter_px, w.disparity_px);
                }
            }
        }
        // The rest (no shape, or a guessed one) are guessed with what this frame's lone
        // particles taught the camera: on the first frame there is nothing else to guess with,
        // and a track left without a shape would be fitted alone again next frame.
        learnt.teach(self);
        for (w, shape) in wanted.iter().zip(shapes.iter_mut()) {
            if shape.is_none_or(|s| s.guessed) {
                *shape = self.guess(image, seen, w).or(*shape);
            }
        }
    }

    /// The shape of a particle that has not stood alone, with the camera's learnt edge: its
    /// radius from its clear detection's size, or else from its disparity (a particle image's
    /// size falls with depth as its disparity does); `None` until the camera has learnt from
    /// lone particles.
    fn guess(&self, image: ImageView<'_>, seen: &[Seen], w: &Wanted) -> Option<Shape> {
        let edge_px = self.edge_px?;
        let clear = w.detection.map(|d| &seen[d]).filter(|s| s.clear);
        let radius_px = match clear {
            Some(s) => self.radius_per_half_diameter? * 0.5 * s.diameter_px,
            None => self.radius_per_disparity? * w.disparity_px,
        };
        let at = w.detection.map(|d| seen[d].centroid).or(w.predicted_px)?;
        self.guessed_shape(image, at, radius_px, edge_px)
    }

    /// A guessed shape of radius `radius_px` (no wider than the widest lone particle) and edge
    /// `edge_px` at `at`, as bright as the image there; `None` for no radius.
    fn guessed_shape(
        &self,
        image: ImageView<'_>,
        at: PixelPoint,
        radius_px: f64,
        edge_px: f64,
    ) -> Option<Shape> {
        (radius_px > 0.0).then(|| Shape {
            radius_px: radius_px.min(self.widest_px.unwrap_or(radius_px)),
            edge_px,
            amplitude: image.bilinear(at).max(1.0),
            guessed: true,
        })
    }
}

/// What one frame's lone particles taught: per particle, the residual its fit left, its edge,
/// its radius over half its detection's diameter, and over its disparity.
#[derive(Default)]
struct Learnt {
    residuals: Vec<f64>,
    edges: Vec<f64>,
    per_half_diameter: Vec<f64>,
    per_disparity: Vec<f64>,
    radii: Vec<f64>,
}

impl Learnt {
    fn add(&mut self, shape: Shape, rms: f64, diameter_px: f64, disparity_px: f64) {
        self.residuals.push(rms);
        self.edges.push(shape.edge_px);
        self.radii.push(shape.radius_px);
        self.per_half_diameter
            .push(shape.radius_px / (0.5 * diameter_px));
        if disparity_px > 0.0 {
            self.per_disparity.push(shape.radius_px / disparity_px);
        }
    }

    /// The camera's learnt scales moved a tenth of the way to this frame's medians (its widest
    /// radius to this frame's widest).
    fn teach(mut self, camera: &mut CameraShake) {
        let blend = |old: &mut Option<f64>, now: Option<f64>| {
            if let Some(now) = now {
                *old = Some(old.map_or(now, |o| 0.9 * o + 0.1 * now));
            }
        };
        let middle = |values: &mut Vec<f64>| (!values.is_empty()).then(|| median(values));
        blend(&mut camera.lone_rms, middle(&mut self.residuals));
        blend(&mut camera.edge_px, middle(&mut self.edges));
        blend(
            &mut camera.radius_per_half_diameter,
            middle(&mut self.per_half_diameter),
        );
        blend(
            &mut camera.radius_per_disparity,
            middle(&mut self.per_disparity),
        );
        blend(
            &mut camera.widest_px,
            self.radii.iter().copied().reduce(f64::max),
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Overlapping particles measured in sweeps, each seeded at `at` with the shape its track
    /// learnt (only centres and amplitudes free): as fitted, with the largest RMS residual on
    /// any one's pixels, and whether all settled; `None` where a fit fails.
    fn refit(image: ImageView<'_>, seeds: &[Member]) -> Option<Fitted> {
        let mut sweep = sweep::Sweep::default();
        for (id, m) in seeds.iter().enumerate() {
            sweep.add(id, *m);
        }
        sweep.run(image);
        let all: Vec<usize> = (0..seeds.len())
            .map(|id| sweep.element(id))
            .collect::<Option<_>>()?;
        all.iter().all(|&i| sweep.fitted(i)).then(|| Fitted {
            members: all.iter().map(|&i| sweep.member(i)).collect(),
            rms: all.iter().map(|&i| sweep.rms_on(i)).fold(0.0, f64::max),
            settled: all.iter().all(|&i| sweep.settled(i)),
        })
    }

    fn logistic(z: f64) -> f64 {
        logistic_in(logistic_table(), z)
    }

    /// Discs drawn on a floor of 10 with a ramp, rounded to grey levels.
    fn draw(w: usize, h: usize, discs: &[Member]) -> Vec<u8> {
        draw_on(w, h, discs, (0.1, 0.0))
    }

    /// Discs drawn on a floor of 10 (at the origin) sloping by `slope` grey levels per pixel.
    fn draw_on(w: usize, h: usize, discs: &[Member], slope: (f64, f64)) -> Vec<u8> {
        (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f64, (i / w) as f64);
                let v: f64 = discs
                    .iter()
                    .map(|m| {
                        let r = (x - m.at.x).hypot(y - m.at.y);
                        m.shape.amplitude * logistic((r - m.shape.radius_px) / m.shape.edge_px)
                    })
                    .sum();
                (10.0 + slope.0 * x + slope.1 * y + v)
                    .round()
                    .clamp(0.0, 255.0) as u8
            })
            .collect()
    }

    fn disc(x: f64, y: f64) -> Member {
        Member {
            at: PixelPoint { x, y },
            shape: Shape {
                radius_px: 3.0,
                edge_px: 0.6,
                amplitude: 120.0,
                guessed: false,
            },
        }
    }

    #[test]
    fn a_fits_centre_error_is_the_scatter_of_its_centres_under_noise() {
        // One disc, seen through 300 draws of noise (grey levels, sd 4): the standard error a
        // converged fit reports is the scatter of the centres it finds.
        let truth = disc(15.4, 12.7);
        let clean = draw(30, 25, &[truth]);
        let mut state = 11u64;
        let mut noise = || {
            // Sum of 12 uniforms: near-Gaussian, sd 1.
            (0..12)
                .map(|_| {
                    state = state
                        .wrapping_mul(6364136223846793005)
                        .wrapping_add(1442695040888963407);
                    (state >> 11) as f64 / (1u64 << 53) as f64
                })
                .sum::<f64>()
                - 6.0
        };
        let (mut scatter_sq, mut reported) = (0.0, Vec::new());
        let draws = 300;
        for _ in 0..draws {
            let pixels: Vec<u8> = clean
                .iter()
                .map(|&v| (f64::from(v) + 4.0 * noise()).round().clamp(0.0, 254.0) as u8)
                .collect();
            let image = ImageView::new(30, 25, &pixels).expect("sized");
            let samples = window(image, &[(truth.at, truth.shape.radius_px + MARGIN_PX)]);
            let mut fit = step::Fit::new(truth, &samples);
            let mut sigma = 0.0;
            for _ in 0..MAX_ITERATIONS {
                let stepped = fit
                    .step(&samples, &[], (Free::Radius, truth.shape.radius_px))
                    .expect("fits");
                sigma = stepped.centre_sigma_px;
            }
            let (dx, dy) = (fit.member.at.x - truth.at.x, fit.member.at.y - truth.at.y);
            scatter_sq += dx * dx + dy * dy;
            reported.push(sigma);
        }
        let scatter = (scatter_sq / f64::from(draws)).sqrt();
        let reported = median(&mut reported);
        assert!(
            (reported / scatter - 1.0).abs() < 0.2,
            "reported {reported:.4} px, scatter {scatter:.4} px"
        );
    }

    #[test]
    fn the_tabulated_step_is_the_logistic() {
        for i in -2500..=2500 {
            let z = f64::from(i) * 0.0097;
            let exact = 1.0 / (1.0 + z.exp());
            assert!((logistic(z) - exact).abs() < 2e-5, "{z}");
        }
        assert_eq!(logistic(f64::INFINITY), logistic(25.0));
    }

    #[test]
    fn a_lone_particle_teaches_its_shape() {
        let truth = disc(15.4, 12.7);
        let pixels = draw(30, 25, &[truth]);
        let image = ImageView::new(30, 25, &pixels).expect("sized");
        let (shape, rms) =
            learn_shape(image, PixelPoint { x: 15.0, y: 13.0 }, 6.0, None).expect("learnt");
        assert!((shape.radius_px - 3.0).abs() < 0.05, "{shape:?}");
        assert!((shape.edge_px - 0.6).abs() < 0.05, "{shape:?}");
        assert!(rms < 1.0, "{rms}");
        // Learnt again from a shape learnt earlier, when the particle was a little nearer.
        let earlier = Shape {
            radius_px: 3.4,
            edge_px: 0.5,
            ..shape
        };
        let (again, _) = learn_shape(image, PixelPoint { x: 15.0, y: 13.0 }, 6.0, Some(earlier))
            .expect("learnt");
        assert!(
            (again.radius_px - shape.radius_px).abs() < 1e-3,
            "{again:?}"
        );
        assert!((again.edge_px - shape.edge_px).abs() < 1e-3, "{again:?}");
    }

    #[test]
    fn on_its_first_frame_a_camera_guesses_what_it_cannot_learn_from_what_its_lone_particles_taught(
    ) {
        // One particle stands alone, two touch: a camera that has learnt nothing yet learns
        // the first's shape, and gives the touching ones shapes guessed with its edge.
        let truth = [disc(15.4, 12.7), disc(40.0, 15.0), disc(44.5, 15.5)];
        let pixels = draw(60, 30, &truth);
        let image = ImageView::new(60, 30, &pixels).expect("sized");
        let centroids = [at(15.0, 13.0), at(40.0, 15.0), at(44.5, 15.5)];
        let seen = seen_at(&centroids, 6.0, true);
        let mut shapes = [None; 3];
        let mut camera = CameraShake::default();
        camera.learn_shapes(image, &seen, &wanted_at(&centroids), &mut shapes);
        let learnt = shapes[0].expect("learnt");
        assert!(
            !learnt.guessed && (learnt.radius_px - 3.0).abs() < 0.05,
            "{learnt:?}"
        );
        for guessed in &shapes[1..] {
            let guessed = guessed.expect("guessed");
            assert!(guessed.guessed, "{guessed:?}");
            assert_eq!(guessed.edge_px, learnt.edge_px);
        }
    }

    #[test]
    fn two_overlapping_particles_of_known_shape_are_pinned_where_they_are() {
        let truth = [disc(20.3, 15.6), disc(24.4, 16.1)];
        let pixels = draw(44, 30, &truth);
        let image = ImageView::new(44, 30, &pixels).expect("sized");
        // Seeded most of a pixel off each, the fit lands within a few hundredths of a pixel.
        let seeds = [disc(21.0, 15.0), disc(23.6, 16.8)];
        let fitted = refit(image, &seeds).expect("fits");
        assert!(stayed(&fitted, &seeds, |_| false));
        assert_pinned(&fitted, &truth);
    }

    #[test]
    fn particles_whose_images_grew_since_their_tracks_learnt_them_are_pinned_where_they_are() {
        // Nearer the cameras than when their tracks learnt their shapes (radius 3 px), the
        // particles' images are a fifth wider: a fit holding the learnt radius leaves rings
        // of light to its floor and pulls the centres.
        let grown = |x, y| {
            let mut m = disc(x, y);
            m.shape.radius_px = 3.6;
            m
        };
        let truth = [grown(20.3, 15.6), grown(25.1, 16.1)];
        let pixels = draw(46, 32, &truth);
        let image = ImageView::new(46, 32, &pixels).expect("sized");
        let seeds = [disc(21.0, 15.0), disc(24.3, 16.8)];
        let fitted = refit(image, &seeds).expect("fits");
        assert!(fitted.settled);
        assert_pinned(&fitted, &truth);
    }

    #[test]
    fn a_fit_whose_shapes_do_not_match_its_particles_measures_neither() {
        let truth = [disc(20.0, 20.0), disc(21.0, 20.0)];
        let pixels = draw(40, 40, &truth);
        let image = ImageView::new(40, 40, &pixels).expect("sized");
        let fitted = refit(image, &truth).expect("fitted");
        assert!(fitted.settled && fitted.rms < 1.0, "{}", fitted.rms);
        // Shapes half the particles' size: no centres explain the pixels. The fit either
        // swings instead of settling or leaves more than a pair of detected particles may.
        let mut shrunk = truth;
        for m in &mut shrunk {
            m.shape.radius_px = 1.5;
        }
        let fitted = refit(image, &shrunk).expect("fitted");
        let lone_rms = learnt_camera().lone_rms.expect("learnt");
        let pair_bound = MAX_RESIDUAL_RATIO * lone_rms * 2f64.sqrt();
        assert!(!fitted.settled || fitted.rms > pair_bound, "{}", fitted.rms);
    }

    #[test]
    fn overlapping_particles_on_a_steeply_lit_background_are_pinned_where_they_are() {
        // The background climbs 40 grey levels across the group's window: a flat floor would
        // leave a residual of several grey levels and move the centres towards the light.
        let truth = [disc(20.3, 15.6), disc(24.4, 16.1)];
        let pixels = draw_on(44, 30, &truth, (2.5, -1.5));
        let image = ImageView::new(44, 30, &pixels).expect("sized");
        let seeds = [disc(21.0, 15.0), disc(23.6, 16.8)];
        let fitted = refit(image, &seeds).expect("fits");
        assert!(stayed(&fitted, &seeds, |_| false));
        assert_pinned(&fitted, &truth);
    }

    /// A fit that explains the pixels (RMS under a grey level) with every member within
    /// 0.05 px of the particle it stands for.
    fn assert_pinned(fitted: &Fitted, truth: &[Member]) {
        assert!(fitted.rms < 1.0, "{}", fitted.rms);
        for (m, t) in fitted.members.iter().zip(truth) {
            let c = m.at;
            assert!(
                (c.x - t.at.x).hypot(c.y - t.at.y) < 0.05,
                "{c:?} vs {:?}",
                t.at
            );
        }
    }

    #[test]
    fn bright_particles_whose_overlap_clips_are_pinned_by_the_pixels_below_full_scale() {
        let bright = |x, y| {
            let mut m = disc(x, y);
            m.shape.amplitude = 170.0;
            m
        };
        let truth = [bright(20.3, 15.6), bright(24.4, 16.1)];
        let pixels = draw(44, 30, &truth);
        assert!(pixels.iter().filter(|&&p| p == u8::MAX).count() >= 4);
        let image = ImageView::new(44, 30, &pixels).expect("sized");
        let seeds = [bright(21.0, 15.0), bright(23.6, 16.8)];
        let fitted = refit(image, &seeds).expect("fits");
        assert_pinned(&fitted, &truth);
    }

    fn at(x: f64, y: f64) -> PixelPoint {
        PixelPoint { x, y }
    }

    /// Detections at `centroids`, all of one size and clearness.
    fn seen_at(centroids: &[PixelPoint], diameter_px: f64, clear: bool) -> Vec<Seen> {
        centroids
            .iter()
            .map(|&c| Seen {
                centroid: c,
                diameter_px,
                clear,
                fitted: false,
                rect: RectPoint { x: c.x, y: c.y },
            })
            .collect()
    }

    /// Particles predicted at `predicted`, each claiming the detection of its own index.
    fn wanted_at(predicted: &[PixelPoint]) -> Vec<Wanted> {
        predicted
            .iter()
            .enumerate()
            .map(|(i, &p)| Wanted {
                detection: Some(i),
                predicted_px: Some(p),
                predicted_rect: RectPoint { x: p.x, y: p.y },
                disparity_px: 10.0,
                relearn: false,
            })
            .collect()
    }

    /// A camera that has learnt its lone particles' residual and edge.
    fn learnt_camera() -> CameraShake {
        CameraShake {
            lone_rms: Some(0.5),
            edge_px: Some(0.6),
            widest_px: Some(3.0),
            ..Default::default()
        }
    }

    /// Two tracked particles 4 px apart seen as one blob, claimed by the first track; the
    /// second track has no detection of its own and is predicted most of a pixel off.
    fn merged(second_exists: bool) -> Vec<Measured> {
        merged_in_noise(second_exists, 0.0)
    }

    /// As [`merged`], with a checkerboard of +-`noise` grey levels over the image.
    fn merged_in_noise(second_exists: bool, noise: f64) -> Vec<Measured> {
        let truth = [disc(20.3, 15.6), disc(24.4, 16.1)];
        let drawn = if second_exists {
            &truth[..]
        } else {
            &truth[..1]
        };
        let pixels: Vec<u8> = draw(44, 30, drawn)
            .into_iter()
            .enumerate()
            .map(|(i, v)| {
                let sign = if (i % 44 + i / 44) % 2 == 0 {
                    1.0
                } else {
                    -1.0
                };
                (f64::from(v) + sign * noise).round().clamp(0.0, 255.0) as u8
            })
            .collect();
        measure_merged(&pixels)
    }

    /// The two tracks of [`merged`] measured in `pixels` (44 x 30): the first claimed the
    /// blob, the second has no detection of its own and is predicted most of a pixel off.
    fn measure_merged(pixels: &[u8]) -> Vec<Measured> {
        let truth = [disc(20.3, 15.6), disc(24.4, 16.1)];
        let image = ImageView::new(44, 30, pixels).expect("sized");
        let blob = at(22.3, 15.8);
        let seen = [Seen {
            centroid: blob,
            diameter_px: 10.0,
            clear: false,
            fitted: false,
            rect: RectPoint {
                x: blob.x,
                y: blob.y,
            },
        }];
        let wanted = |detection, p: PixelPoint| Wanted {
            detection,
            predicted_px: Some(p),
            predicted_rect: RectPoint { x: p.x, y: p.y },
            disparity_px: 10.0,
            relearn: false,
        };
        let wanted = [
            wanted(Some(0), at(20.8, 15.2)),
            wanted(None, at(23.8, 16.6)),
        ];
        let mut shapes = [Some(truth[0].shape), Some(truth[1].shape)];
        learnt_camera().measure(image, &seen, &wanted, &mut shapes, &[None, None])
    }

    #[test]
    fn a_particle_hidden_in_its_neighbours_image_is_found_where_its_track_puts_it() {
        let measured = merged(true);
        let truth = [at(20.3, 15.6), at(24.4, 16.1)];
        for (m, t) in measured.iter().zip(truth) {
            let Measured::Refitted(c) = m else {
                panic!("{measured:?}");
            };
            assert!((c.x - t.x).hypot(c.y - t.y) < 0.05, "{c:?} vs {t:?}");
        }
    }

    #[test]
    fn an_undetected_particle_is_judged_on_its_own_pixels() {
        // The merged pair of `merged`, with a faint third particle no track knows touching the
        // detected one from the other side: its light is in the group's window, not in the
        // undetected particle's own pixels.
        let faint = Member {
            shape: Shape {
                amplitude: 20.0,
                ..disc(0.0, 0.0).shape
            },
            ..disc(14.0, 15.4)
        };
        let truth = [disc(20.3, 15.6), disc(24.4, 16.1), faint];
        let measured = measure_merged(&draw(44, 30, &truth));
        let Measured::Refitted(c) = measured[1] else {
            panic!("{measured:?}");
        };
        assert!((c.x - 24.4).hypot(c.y - 16.1) < 0.1, "{c:?}");
    }

    #[test]
    fn a_detected_particle_is_measured_where_an_undetected_one_is_not_believed() {
        // Residuals a little above what a lone particle leaves (the camera's bound is 2 grey
        // levels): the detected particle's centre is still measured by the group fit, but the
        // fit is no proof that the undetected one is there.
        let measured = merged_in_noise(true, 2.2);
        let Measured::Refitted(c) = measured[0] else {
            panic!("{measured:?}");
        };
        assert!((c.x - 20.3).hypot(c.y - 15.6) < 0.1, "{c:?}");
        assert_eq!(measured[1], Measured::Missing, "{measured:?}");
    }

    #[test]
    fn overlapping_particles_swept_in_turn_are_pinned_where_they_are() {
        // On a floor sloping along both axes, seeded most of a pixel off: each particle's
        // fit sees the other's light only as its model, so they are pinned only once both
        // have settled.
        let truth = [disc(20.3, 15.6), disc(24.4, 16.1)];
        let pixels = draw_on(44, 30, &truth, (0.8, -0.5));
        let image = ImageView::new(44, 30, &pixels).expect("sized");
        let mut sweep = sweep::Sweep::default();
        sweep.add(7, disc(21.0, 15.0));
        sweep.add(3, disc(23.6, 16.8));
        sweep.add(7, disc(30.0, 30.0));
        sweep.run(image);
        for (id, t) in [(7, truth[0]), (3, truth[1])] {
            let i = sweep.element(id).expect("added");
            let c = sweep.member(i).at;
            assert!(sweep.fitted(i) && sweep.settled(i));
            assert!((c.x - t.at.x).hypot(c.y - t.at.y) < 0.03, "{c:?} vs {t:?}");
            assert!(sweep.rms_on(i) < 1.0, "{}", sweep.rms_on(i));
        }
        assert!(sweep.element(5).is_none());
    }

    #[test]
    fn a_row_of_overlapping_particles_is_fitted_together_and_each_pinned() {
        // Three cut detections in a row: each particle's light reaches both of its neighbours'
        // pixels, the first's and the last's through the middle one's, which is pinned only
        // with both of them taken out.
        let truth = [disc(14.3, 15.6), disc(18.4, 16.1), disc(22.6, 15.2)];
        let pixels = draw(38, 30, &truth);
        let image = ImageView::new(38, 30, &pixels).expect("sized");
        let seen = seen_at(
            &[at(14.0, 15.8), at(18.5, 16.0), at(22.9, 15.4)],
            5.0,
            false,
        );
        let wanted = wanted_at(&[at(14.8, 15.1), at(17.9, 16.6), at(23.2, 14.7)]);
        let mut shapes = truth.map(|t| Some(t.shape));
        let measured =
            learnt_camera().measure(image, &seen, &wanted, &mut shapes, &[None, None, None]);
        for (m, t) in measured.iter().zip(&truth) {
            let Measured::Refitted(c) = m else {
                panic!("{measured:?}");
            };
            assert!((c.x - t.at.x).hypot(c.y - t.at.y) < 0.05, "{c:?} vs {t:?}");
        }
    }

    #[test]
    fn touching_particles_parted_at_a_dip_are_measured_apart_from_each_others_light() {
        // Two particles 5 px apart, each detected clear (the detector parted them at the dip
        // between their peaks), their centroids pulled towards each other by the light of the
        // other in their regions; a third stands alone, its detection left as it is.
        let truth = [disc(14.3, 15.6), disc(19.3, 15.9), disc(30.0, 8.0)];
        let pixels = draw(38, 30, &truth);
        let image = ImageView::new(38, 30, &pixels).expect("sized");
        let centroids = [at(14.6, 15.6), at(19.0, 15.9), at(30.0, 8.0)];
        let seen = seen_at(&centroids, 4.0, true);
        let wanted = wanted_at(&centroids);
        let mut shapes = truth.map(|t| Some(t.shape));
        let measured =
            learnt_camera().measure(image, &seen, &wanted, &mut shapes, &[None, None, None]);
        for (m, t) in measured.iter().zip(&truth).take(2) {
            let Measured::Refitted(c) = m else {
                panic!("{measured:?}");
            };
            assert!((c.x - t.at.x).hypot(c.y - t.at.y) < 0.05, "{c:?} vs {t:?}");
        }
        assert_eq!(measured[2], Measured::AsDetected, "{measured:?}");
    }

    #[test]
    fn a_track_whose_particle_is_gone_finds_nothing_in_its_neighbours_image() {
        let measured = merged(false);
        assert_eq!(measured[1], Measured::Missing, "{measured:?}");
        let Measured::Refitted(c) = measured[0] else {
            panic!("{measured:?}");
        };
        assert!((c.x - 20.3).hypot(c.y - 15.6) < 0.05, "{c:?}");
    }

    /// Every pixel of `image` as a fit sample.
    fn all_pixels(image: ImageView<'_>) -> Vec<(f64, f64, f64)> {
        (0..image.width * image.height)
            .map(|i| {
                let (x, y) = (i % image.width, i / image.width);
                (x as f64, y as f64, f64::from(image.pixels[i]))
            })
            .collect()
    }

    /// Two discs 4 px apart in one region.
    fn touching() -> [Member; 2] {
        [disc(20.3, 15.6), disc(24.4, 16.1)]
    }

    /// The region of [`touching`] parted by `camera`, each track predicting its particle most
    /// of a pixel off, with the shape it knows (`shapes`).
    fn part_touching(camera: &CameraShake, shapes: [Option<Shape>; 2]) -> Option<Vec<PixelPoint>> {
        let pixels = draw(44, 30, &touching());
        let image = ImageView::new(44, 30, &pixels).expect("sized");
        let expected = [(at(21.0, 15.0), shapes[0]), (at(23.6, 16.8), shapes[1])];
        camera.part(image, &all_pixels(image), &expected, 6.0)
    }

    /// Asserts that `centres` are within 0.05 px of [`touching`]'s discs, one each.
    fn assert_on_touching(centres: &[PixelPoint]) {
        let truth = touching();
        assert_eq!(centres.len(), truth.len());
        for (c, t) in centres.iter().zip(&truth) {
            assert!((c.x - t.at.x).hypot(c.y - t.at.y) < 0.05, "{c:?} vs {t:?}");
        }
    }

    /// Particle 1 of [`touching`] fitted from most of a pixel off, with particle 0 held at
    /// `held_at`: where particle 1 ends, and where particle 0 stands after the sweeps.
    fn fit_beside_held(held_at: PixelPoint) -> (PixelPoint, PixelPoint) {
        let truth = touching();
        let pixels = draw(44, 30, &truth);
        let image = ImageView::new(44, 30, &pixels).expect("sized");
        let mut sweep = sweep::Sweep::default();
        sweep.hold(
            0,
            Member {
                at: held_at,
                ..truth[0]
            },
        );
        sweep.add(
            1,
            Member {
                at: at(23.8, 16.7),
                ..truth[1]
            },
        );
        sweep.run(image);
        let (held, fitted) = (
            sweep.element(0).expect("held"),
            sweep.element(1).expect("added"),
        );
        assert!(sweep.fitted(fitted) && sweep.settled(held));
        (sweep.member(fitted).at, sweep.member(held).at)
    }

    #[test]
    fn a_held_particle_without_light_touches_nothing_however_far_it_was_thrown() {
        // One an earlier sweep pushed off is held dark wherever its last step threw it.
        let truth = touching();
        let pixels = draw(44, 30, &truth[1..]);
        let image = ImageView::new(44, 30, &pixels).expect("sized");
        let mut sweep = sweep::Sweep::default();
        let dark = Shape {
            amplitude: 0.0,
            ..truth[0].shape
        };
        sweep.hold(
            0,
            Member {
                at: at(1e12, -1e12),
                shape: dark,
            },
        );
        sweep.add(
            1,
            Member {
                at: at(23.8, 16.7),
                ..truth[1]
            },
        );
        sweep.run(image);
        let fitted = sweep.member(sweep.element(1).expect("added")).at;
        assert!(
            (fitted.x - truth[1].at.x).hypot(fitted.y - truth[1].at.y) < 0.05,
            "{fitted:?}"
        );
    }

    #[test]
    fn a_held_particle_lends_its_light_and_stays_where_it_was_put() {
        let truth = touching();
        let (fitted, held) = fit_beside_held(truth[0].at);
        assert_eq!(held, truth[0].at);
        assert!(
            (fitted.x - truth[1].at.x).hypot(fitted.y - truth[1].at.y) < 0.05,
            "{fitted:?}"
        );
        // Held a pixel off, its light pulls the other's fit off too: it is not fitted again.
        let off = at(truth[0].at.x - 1.0, truth[0].at.y);
        let (fitted, held) = fit_beside_held(off);
        assert_eq!(held, off);
        assert!(
            (fitted.x - truth[1].at.x).hypot(fitted.y - truth[1].at.y) > 0.05,
            "{fitted:?}"
        );
    }

    #[test]
    fn a_region_two_tracks_expect_is_parted_with_their_shapes() {
        // Each track predicts its particle most of a pixel off: the shapes the tracks learnt
        // pin both centres.
        let truth = touching();
        let known = [Some(truth[0].shape), Some(truth[1].shape)];
        let camera = learnt_camera();
        assert_on_touching(&part_touching(&camera, known).expect("parted"));
        // Shapes half the particles' size explain no centres: the region is not parted.
        let mut small = truth[0].shape;
        small.radius_px = 1.5;
        assert_eq!(part_touching(&camera, [Some(small); 2]), None);
        // A camera that has not learnt from lone particles parts nothing.
        assert_eq!(part_touching(&CameraShake::default(), known), None);
    }

    #[test]
    fn a_particle_no_track_knows_is_parted_with_a_shape_from_its_share_of_the_region() {
        // The second particle has only a 2D track: its shape is guessed from its share of the
        // region's area (6 px across: a radius of 3 px at one learnt radius per half size).
        let known = [Some(touching()[0].shape), None];
        let camera = CameraShake {
            radius_per_half_diameter: Some(1.0),
            ..learnt_camera()
        };
        assert_on_touching(&part_touching(&camera, known).expect("parted"));
        // Without a learnt radius per size there is no shape to part it with.
        assert_eq!(part_touching(&learnt_camera(), known), None);
    }

    #[test]
    fn no_guessed_shape_is_wider_than_the_widest_lone_particle() {
        // A ghost pair 10 cm in front of the rig has a disparity of hundreds of pixels.
        let camera = CameraShake {
            radius_per_disparity: Some(0.05),
            ..learnt_camera()
        };
        let pixels = vec![0u8; 64 * 48];
        let image = ImageView::new(64, 48, &pixels).expect("sized");
        let wanted = |disparity_px| Wanted {
            detection: None,
            predicted_px: Some(at(30.0, 20.0)),
            predicted_rect: RectPoint { x: 30.0, y: 20.0 },
            disparity_px,
            relearn: false,
        };
        let radius = |w| camera.guess(image, &[], &w).expect("guessed").radius_px;
        assert!((radius(wanted(40.0)) - 2.0).abs() < 1e-12);
        assert_eq!(radius(wanted(300.0)), 3.0);
        let blob = Seen {
            centroid: at(30.0, 20.0),
            diameter_px: 40.0,
            clear: true,
            fitted: false,
            rect: RectPoint { x: 30.0, y: 20.0 },
        };
        assert_eq!(group::guessed(image, &blob, 0.6, 3.0).shape.radius_px, 3.0);
    }
}
