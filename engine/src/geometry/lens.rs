//! The camera lens model: pinhole intrinsics and OpenCV's radial-tangential distortion.

use nalgebra::Point3;

use super::{invalid, CalibrationError, PixelPoint};

/// OpenCV's radial-tangential model with the optional rational terms.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Distortion {
    /// Radial coefficient of r^2.
    pub k1: f64,
    /// Radial coefficient of r^4.
    pub k2: f64,
    /// Tangential coefficient.
    pub p1: f64,
    /// Tangential coefficient.
    pub p2: f64,
    /// Radial coefficient of r^6.
    pub k3: f64,
    /// Rational denominator coefficient of r^2.
    pub k4: f64,
    /// Rational denominator coefficient of r^4.
    pub k5: f64,
    /// Rational denominator coefficient of r^6.
    pub k6: f64,
}

impl Distortion {
    pub(super) fn from_coefficients(field: &str, d: &[f64]) -> Result<Self, CalibrationError> {
        let mut c = [0.0; 8];
        match d.len() {
            0 | 4 | 5 | 8 => c[..d.len()].copy_from_slice(d),
            n => {
                return Err(invalid(
                    field,
                    format!(
                        "expected 0, 4, 5 or 8 coefficients [k1,k2,p1,p2,k3,k4,k5,k6], got {n}"
                    ),
                ))
            }
        }
        Ok(Self {
            k1: c[0],
            k2: c[1],
            p1: c[2],
            p2: c[3],
            k3: c[4],
            k4: c[5],
            k5: c[6],
            k6: c[7],
        })
    }

    pub(super) fn coefficients(&self) -> Vec<f64> {
        let all = [
            self.k1, self.k2, self.p1, self.p2, self.k3, self.k4, self.k5, self.k6,
        ];
        if all[5..].iter().any(|&v| v != 0.0) {
            all.to_vec()
        } else if all == [0.0; 8] {
            Vec::new()
        } else {
            all[..5].to_vec()
        }
    }

    /// Distorts an ideal normalized image point (x/z, y/z).
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        let r2 = x * x + y * y;
        let radial = (1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3)))
            / (1.0 + r2 * (self.k4 + r2 * (self.k5 + r2 * self.k6)));
        (
            x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x),
            y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y,
        )
    }

    /// Inverts [`Self::distort`] by fixed-point iteration (as OpenCV's `undistortPoints`), but
    /// iterates to convergence and checks the result, so a point outside the model's invertible
    /// region yields `None` instead of a silently wrong position.
    pub fn undistort(&self, xd: f64, yd: f64) -> Option<(f64, f64)> {
        let (mut x, mut y) = (xd, yd);
        for _ in 0..200 {
            let r2 = x * x + y * y;
            let inv_radial = (1.0 + r2 * (self.k4 + r2 * (self.k5 + r2 * self.k6)))
                / (1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3)));
            let dx = 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x);
            let dy = self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y;
            let (nx, ny) = ((xd - dx) * inv_radial, (yd - dy) * inv_radial);
            let step = (nx - x).abs() + (ny - y).abs();
            x = nx;
            y = ny;
            if step < 1e-14 {
                break;
            }
        }
        let (cx, cy) = self.distort(x, y);
        ((cx - xd).abs() < 1e-9 && (cy - yd).abs() < 1e-9 && x.is_finite() && y.is_finite())
            .then_some((x, y))
    }
}

/// One camera's intrinsics.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraModel {
    /// Focal length along x, pixels.
    pub fx: f64,
    /// Focal length along y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// Skew (`K[0][1]`).
    pub skew: f64,
    /// Lens distortion.
    pub distortion: Distortion,
}

impl CameraModel {
    /// An undistorted pinhole of focal length `f_px` and principal point (`cx`, `cy`).
    pub fn pinhole(f_px: f64, cx: f64, cy: f64) -> Self {
        Self {
            fx: f_px,
            fy: f_px,
            cx,
            cy,
            skew: 0.0,
            distortion: Distortion::default(),
        }
    }

    /// Projects a point in this camera's frame; `None` behind the camera.
    pub fn project(&self, p: &Point3<f64>) -> Option<PixelPoint> {
        if p.z <= 1e-12 {
            return None;
        }
        let (xd, yd) = self.distortion.distort(p.x / p.z, p.y / p.z);
        Some(PixelPoint {
            x: self.fx * xd + self.skew * yd + self.cx,
            y: self.fy * yd + self.cy,
        })
    }

    /// The ideal normalized coordinates (x/z, y/z) seen at a pixel.
    pub fn unproject(&self, p: PixelPoint) -> Option<(f64, f64)> {
        let yd = (p.y - self.cy) / self.fy;
        let xd = (p.x - self.cx - self.skew * yd) / self.fx;
        self.distortion.undistort(xd, yd)
    }

    pub(super) fn matrix(&self) -> [[f64; 3]; 3] {
        [
            [self.fx, self.skew, self.cx],
            [0.0, self.fy, self.cy],
            [0.0, 0.0, 1.0],
        ]
    }
}
