//! Overlapping particles measured with what their tracks know. Each track learns its
//! particle's image shape in each camera from the frames where the particle stands alone: a
//! soft-edged disc, `a / (1 + exp((r - radius) / edge))`, which is a blurred spot for a small
//! radius and a sharp disc for a large one. Where the particle overlaps a neighbour, the group's
//! pixels are fitted with every member's shape held at what its track learnt and only the
//! centres and amplitudes free. A free fit of two overlapping images trades width against
//! position (the reason a cut's centroids are not measured); with the widths known, the
//! centres are pinned.

use nalgebra::{DMatrix, DVector};

use crate::geometry::{PixelPoint, RectPoint};
use crate::spatial::{median, PointGrid, GRID_CELL_PX};
use crate::ImageView;

/// Gauss-Newton steps at most; a step that moves no centre by more than
/// [`CONVERGED_STEP_PX`] ends the fit.
const MAX_ITERATIONS: usize = 12;
const CONVERGED_STEP_PX: f64 = 5e-3;
/// A group fit explains its pixels when their RMS residual is within this many times what the
/// camera's lone particles leave (noise and one disc's mismatch, learnt): a group adds each
/// neighbour's mismatch, and a neighbour no track knows has only a guessed shape.
const MAX_RESIDUAL_RATIO: f64 = 4.0;
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
}

impl Shape {
    /// Distance within which the image holds nearly all its light, pixels.
    fn reach_px(&self) -> f64 {
        self.radius_px + 3.0 * self.edge_px
    }

    /// The height at distance `r` from the centre, per unit amplitude, and its derivative
    /// with respect to `r`, radius and edge.
    fn profile(&self, r: f64) -> (f64, f64, f64, f64) {
        let z = (r - self.radius_px) / self.edge_px;
        let g = 1.0 / (1.0 + z.exp());
        let dg_dz = -g * (1.0 - g);
        let dg_dr = dg_dz / self.edge_px;
        (g, dg_dr, -dg_dr, -dg_dz * z / self.edge_px)
    }
}

/// A particle in a fit: its centre and shape (a fit that learns may change the shape's radius
/// and edge; one that measures only its centre and amplitude).
#[derive(Debug, Clone, Copy)]
struct Member {
    at: PixelPoint,
    shape: Shape,
}

/// The outcome of a fit: the members as fitted and the RMS residual, grey levels.
struct Fitted {
    members: Vec<Member>,
    rms: f64,
}

/// The shape of a particle standing alone at `at` (equivalent diameter `diameter_px`), and
/// the RMS residual the fit left; `None` where the fit fails or ends implausibly.
pub(crate) fn learn_shape(
    image: ImageView<'_>,
    at: PixelPoint,
    diameter_px: f64,
) -> Option<(Shape, f64)> {
    let radius_px = (0.5 * diameter_px).max(0.5);
    let samples = window(image, &[(at, radius_px + 1.0 + MARGIN_PX)]);
    let low = samples.iter().map(|s| s.2).fold(f64::MAX, f64::min);
    let peak = image.bilinear(at) - low;
    let seed = Member {
        at,
        shape: Shape {
            radius_px,
            edge_px: 0.5,
            amplitude: peak.max(1.0),
        },
    };
    let fitted = fit(&samples, &[seed], true)?;
    let m = fitted.members[0];
    let plausible = m.shape.edge_px > 0.05
        && m.shape.radius_px > 0.0
        && m.shape.radius_px < 2.0 * radius_px + 1.0
        && (m.at.x - at.x).hypot(m.at.y - at.y) < radius_px;
    plausible.then_some((m.shape, fitted.rms))
}

/// Refits a group of overlapping particles, each seeded at `at` with the shape its track
/// learnt (only centres and amplitudes free): the fitted centres, in order, and the RMS
/// residual; `None` where the fit fails or moves a centre further than its radius.
fn refit(image: ImageView<'_>, seeds: &[Member]) -> Option<(Vec<PixelPoint>, f64)> {
    let reach: Vec<(PixelPoint, f64)> = seeds
        .iter()
        .map(|m| (m.at, m.shape.radius_px + MARGIN_PX))
        .collect();
    let samples = window(image, &reach);
    let fitted = fit(&samples, seeds, false)?;
    let stayed = fitted.members.iter().zip(seeds).all(|(f, s)| {
        f.shape.amplitude > 0.0 && (f.at.x - s.at.x).hypot(f.at.y - s.at.y) <= s.shape.radius_px
    });
    stayed.then(|| (fitted.members.iter().map(|m| m.at).collect(), fitted.rms))
}

/// Gauss-Newton on a floor plus the members' discs; with `free_shape`, radius and edge are
/// fitted too.
fn fit(samples: &[(f64, f64, f64)], seeds: &[Member], free_shape: bool) -> Option<Fitted> {
    let per = if free_shape { 5 } else { 3 };
    let n = 1 + per * seeds.len();
    if samples.len() <= 2 * n {
        return None;
    }
    let floor = samples.iter().map(|s| s.2).fold(f64::MAX, f64::min);
    let mut members = seeds.to_vec();
    let mut params = DVector::zeros(n);
    params[0] = floor;
    let mut cost = f64::INFINITY;
    for _ in 0..MAX_ITERATIONS {
        let (jtj, jtr, c) = normal_equations(samples, params[0], &members, free_shape);
        cost = c;
        let step = jtj.cholesky()?.solve(&jtr);
        params[0] += step[0];
        let mut moved: f64 = 0.0;
        for (k, m) in members.iter_mut().enumerate() {
            let s = &step.as_slice()[1 + per * k..1 + per * (k + 1)];
            m.at.x += s[0];
            m.at.y += s[1];
            m.shape.amplitude += s[2];
            if free_shape {
                m.shape.radius_px = (m.shape.radius_px + s[3]).max(0.0);
                m.shape.edge_px = (m.shape.edge_px + s[4]).clamp(0.05, 5.0);
            }
            moved = moved.max(s[0].abs() + s[1].abs());
        }
        if !moved.is_finite() {
            return None;
        }
        if moved < CONVERGED_STEP_PX {
            break;
        }
    }
    let rms = (cost / samples.len() as f64).sqrt();
    Some(Fitted { members, rms })
}

/// `J^T J`, `J^T r` and the sum of squared residuals of the model (`floor` plus the members'
/// discs) over `samples`; per member the unknowns are x, y, amplitude (and radius, edge).
fn normal_equations(
    samples: &[(f64, f64, f64)],
    floor: f64,
    members: &[Member],
    free_shape: bool,
) -> (DMatrix<f64>, DVector<f64>, f64) {
    let per = if free_shape { 5 } else { 3 };
    let n = 1 + per * members.len();
    let mut jtj = DMatrix::zeros(n, n);
    let mut jtr = DVector::zeros(n);
    let mut row = DVector::zeros(n);
    let mut cost = 0.0;
    for &(x, y, value) in samples {
        row.fill(0.0);
        row[0] = 1.0;
        let mut model = floor;
        for (k, m) in members.iter().enumerate() {
            let (dx, dy) = (x - m.at.x, y - m.at.y);
            let r = dx.hypot(dy);
            if r > m.shape.reach_px() + MARGIN_PX {
                continue;
            }
            let (g, dg_dr, dg_dradius, dg_dedge) = m.shape.profile(r);
            let a = m.shape.amplitude;
            model += a * g;
            let j = 1 + per * k;
            if r > 1e-9 {
                // r grows as the centre moves away from the pixel.
                row[j] = -a * dg_dr * dx / r;
                row[j + 1] = -a * dg_dr * dy / r;
            }
            row[j + 2] = g;
            if free_shape {
                row[j + 3] = a * dg_dradius;
                row[j + 4] = a * dg_dedge;
            }
        }
        let residual = value - model;
        cost += residual * residual;
        jtj.ger(1.0, &row, &row, 1.0);
        jtr.axpy(residual, &row, 1.0);
    }
    // Levenberg's touch of damping keeps a group whose members nearly coincide solvable.
    for i in 0..n {
        jtj[(i, i)] = jtj[(i, i)] * (1.0 + 1e-3) + 1e-9;
    }
    (jtj, jtr, cost)
}

/// The pixels (x, y, grey level) within `half` of any of the centres (a box), each once.
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
    let mut samples = Vec::new();
    for y in y0..=y1 {
        for x in x0..=x1 {
            let near = around.iter().any(|(c, half)| {
                (x as f64 - c.x).abs() <= *half && (y as f64 - c.y).abs() <= *half
            });
            if near {
                let value = image.pixels[(y * w + x) as usize] as f64;
                samples.push((x as f64, y as f64, value));
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
    /// Its centroid, rectified (where neighbours are looked for).
    pub(crate) rect: RectPoint,
}

/// A found particle in one camera: its detection (an index into the camera's [`Seen`]s),
/// where its track predicted it (raw pixels), and whether its track should learn its shape
/// again.
#[derive(Debug, Clone, Copy)]
pub(crate) struct FoundIn {
    pub(crate) detection: usize,
    pub(crate) predicted_px: PixelPoint,
    pub(crate) relearn: bool,
}

/// What one camera's shake learns across frames: the RMS residual its lone particles' fits
/// leave (noise and the model's mismatch), the scale a group fit is judged by, and their
/// typical edge width, the shape guessed for a neighbour no track knows.
#[derive(Debug, Clone, Default)]
pub(crate) struct CameraShake {
    lone_rms: Option<f64>,
    edge_px: Option<f64>,
}

impl CameraShake {
    /// One camera's found particles measured: each one standing alone (clear, and no other
    /// detection within reach) teaches its track's shape (where the track has none, or
    /// `relearn` says so); each overlapped one whose track knows its shape is refitted with
    /// the detections around it, each seeded where its track puts it (a lone one at its
    /// centroid, an overlapped one at its prediction; one no track knows at its centroid, as
    /// a disc of its diameter). A track that has not learnt its shape in this camera borrows
    /// the one it learnt in the other (`other_camera`): the two see the particle from nearly
    /// the same distance. Returns, per found particle, the refitted centre, raw pixels,
    /// where its detection overlapped and the group fit explained the pixels.
    pub(crate) fn measure(
        &mut self,
        image: ImageView<'_>,
        seen: &[Seen],
        found: &[FoundIn],
        shapes: &mut [Option<Shape>],
        other_camera: &[Option<Shape>],
    ) -> Vec<Option<PixelPoint>> {
        let grid = PointGrid::new(
            seen.iter().enumerate().map(|(i, s)| (s.rect, i)),
            GRID_CELL_PX,
        );
        let widest = seen.iter().map(|s| s.diameter_px).fold(0.0, f64::max);
        let alone = |i: usize| {
            let (c, d) = (seen[i].rect, seen[i].diameter_px);
            seen[i].clear
                && grid.near(c.x, c.y, d + widest).all(|&(p, j)| {
                    j == i
                        || (p.x - c.x).hypot(p.y - c.y)
                            > 0.5 * (d + seen[j].diameter_px) + 2.0 * MARGIN_PX
                })
        };
        self.learn(image, seen, found, &alone, shapes);
        let (Some(lone_rms), Some(edge_px)) = (self.lone_rms, self.edge_px) else {
            return vec![None; found.len()];
        };
        let mut tracked: Vec<Option<(Member, bool)>> = vec![None; seen.len()];
        for ((f, shape), other) in found.iter().zip(shapes.iter()).zip(other_camera) {
            tracked[f.detection] = shape.or(*other).map(|shape| {
                let clear = seen[f.detection].clear;
                let at = if clear {
                    seen[f.detection].centroid
                } else {
                    f.predicted_px
                };
                (Member { at, shape }, clear)
            });
        }
        let member = |j: usize| -> Member {
            tracked[j].map_or_else(|| guessed(image, &seen[j], edge_px), |(m, _)| m)
        };
        found
            .iter()
            .map(|f| {
                let i = f.detection;
                let (own, clear) = tracked[i]?;
                if clear {
                    return None;
                }
                let c = seen[i].rect;
                let mut members = vec![own];
                for &(p, j) in grid.near(c.x, c.y, own.shape.reach_px() + widest) {
                    let other = member(j);
                    let apart = (p.x - c.x).hypot(p.y - c.y);
                    if j != i && apart <= own.shape.reach_px() + other.shape.reach_px() {
                        members.push(other);
                    }
                }
                let (centres, rms) = refit(image, &members)?;
                (rms <= MAX_RESIDUAL_RATIO * lone_rms).then_some(centres[0])
            })
            .collect()
    }

    /// Lone found particles teach their tracks' shapes, and the camera the residual they
    /// leave and the edge they have.
    fn learn(
        &mut self,
        image: ImageView<'_>,
        seen: &[Seen],
        found: &[FoundIn],
        alone: &impl Fn(usize) -> bool,
        shapes: &mut [Option<Shape>],
    ) {
        let (mut residuals, mut edges) = (Vec::new(), Vec::new());
        for (f, shape) in found.iter().zip(shapes.iter_mut()) {
            if !(shape.is_none() || f.relearn) || !alone(f.detection) {
                continue;
            }
            let s = &seen[f.detection];
            if let Some((learnt, rms)) = learn_shape(image, s.centroid, s.diameter_px) {
                *shape = Some(learnt);
                residuals.push(rms);
                edges.push(learnt.edge_px);
            }
        }
        if !residuals.is_empty() {
            let blend = |old: Option<f64>, now: f64| Some(old.map_or(now, |o| 0.9 * o + 0.1 * now));
            self.lone_rms = blend(self.lone_rms, median(&mut residuals));
            self.edge_px = blend(self.edge_px, median(&mut edges));
        }
    }
}

/// A detection no track knows, as a fit member: a disc of its diameter with the camera's edge,
/// at its centroid.
fn guessed(image: ImageView<'_>, s: &Seen, edge_px: f64) -> Member {
    Member {
        at: s.centroid,
        shape: Shape {
            radius_px: 0.5 * s.diameter_px,
            edge_px,
            amplitude: image.bilinear(s.centroid).max(1.0),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Discs drawn on a floor of 10 with a ramp, rounded to grey levels.
    fn draw(w: usize, h: usize, discs: &[Member]) -> Vec<u8> {
        (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f64, (i / w) as f64);
                let v: f64 = discs
                    .iter()
                    .map(|m| m.shape.amplitude * m.shape.profile((x - m.at.x).hypot(y - m.at.y)).0)
                    .sum();
                (10.0 + 0.1 * x + v).round().clamp(0.0, 255.0) as u8
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
            },
        }
    }

    #[test]
    fn a_lone_particle_teaches_its_shape() {
        let truth = disc(15.4, 12.7);
        let pixels = draw(30, 25, &[truth]);
        let image = ImageView::new(30, 25, &pixels).expect("sized");
        let (shape, rms) =
            learn_shape(image, PixelPoint { x: 15.0, y: 13.0 }, 6.0).expect("learnt");
        assert!((shape.radius_px - 3.0).abs() < 0.05, "{shape:?}");
        assert!((shape.edge_px - 0.6).abs() < 0.05, "{shape:?}");
        assert!(rms < 1.0, "{rms}");
    }

    #[test]
    fn two_overlapping_particles_of_known_shape_are_pinned_where_they_are() {
        let truth = [disc(20.3, 15.6), disc(24.4, 16.1)];
        let pixels = draw(44, 30, &truth);
        let image = ImageView::new(44, 30, &pixels).expect("sized");
        // Seeded most of a pixel off each, the fit lands within a few hundredths of a pixel.
        let seeds = [disc(21.0, 15.0), disc(23.6, 16.8)];
        let (centres, rms) = refit(image, &seeds).expect("fits");
        assert!(rms < 1.0, "{rms}");
        for (c, t) in centres.iter().zip(&truth) {
            assert!(
                (c.x - t.at.x).hypot(c.y - t.at.y) < 0.05,
                "{c:?} vs {:?}",
                t.at
            );
        }
    }
}
