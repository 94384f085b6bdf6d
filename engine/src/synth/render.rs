//! Rendering particles, the room and the sensor into a camera's image.

use std::f64::consts::PI;

use nalgebra::{Matrix2, Point3, Vector2};

use super::{Clutter, Particle, Rng, ScenarioSpec};
use crate::geometry::CameraModel;

/// The room and the sensor's fixed pattern for each camera: posters with print on the wall,
/// LEDs seen by both cameras, hot pixels. Empty when the scene has no clutter.
pub(super) fn fixed_layers(spec: &ScenarioSpec, rng: &mut Rng) -> (Vec<f32>, Vec<f32>) {
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
pub(super) struct Disc {
    x: f64,
    y: f64,
    radius: f64,
}

/// How many of the discs touch or overlap another.
pub(super) fn touching(discs: &mut [Disc]) -> usize {
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
pub(super) fn render_particle(
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

pub(super) fn finish_image(
    spec: &ScenarioSpec,
    signal: &[f32],
    fixed: &[f32],
    noise: &mut Rng,
) -> Vec<u8> {
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
}
