//! Stereo calibration and the virtual co-directional camera pair the method runs in.
//!
//! `rig.json` follows OpenCV's `stereoCalibrate` conventions: `x_in_right = R * x_in_left + T`
//! (metres), camera frames x right / y down / z forward, pixel (0,0) at the centre of the top-left
//! pixel, distortion `[k1, k2, p1, p2[, k3[, k4, k5, k6]]]`. The rig frame is the left camera frame.
//!
//! The MR-PTV equations assume two co-directional pinholes with the baseline along image x. A real
//! headset is not that (lens distortion, toed or rolled cameras, baseline along image y in raw
//! HoloLens 2 frames), so [`Rectification`] maps each particle *centroid* (never a whole image)
//! through undistortion and a rotation into a virtual pair that is exactly co-directional. Linking,
//! stereo matching and triangulation all happen in that virtual pair.

use nalgebra::{Isometry3, Matrix3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// A position in a raw camera image, in pixels (OpenCV convention).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct PixelPoint {
    pub x: f64,
    pub y: f64,
}

/// A position in the rectified virtual camera image, in pixels relative to its principal point
/// (the method's "image plane origin at the image centre").
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct RectPoint {
    pub x: f64,
    pub y: f64,
}

/// What is wrong with a calibration, naming the offending field.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum CalibrationError {
    #[error("{field} is not a finite number")]
    NotFinite { field: String },
    #[error("{field}: {reason}")]
    Invalid { field: String, reason: String },
}

fn invalid(field: &str, reason: impl Into<String>) -> CalibrationError {
    CalibrationError::Invalid {
        field: field.to_string(),
        reason: reason.into(),
    }
}

/// `rig.json` exactly as written on disk (OpenCV `stereoCalibrate` names).
#[allow(non_snake_case)]
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct RigFile {
    pub image_size: [u32; 2],
    pub K1: [[f64; 3]; 3],
    pub D1: Vec<f64>,
    pub K2: [[f64; 3]; 3],
    pub D2: Vec<f64>,
    pub R: [[f64; 3]; 3],
    pub T: [f64; 3],
}

/// OpenCV's radial-tangential model with the optional rational terms.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Distortion {
    pub k1: f64,
    pub k2: f64,
    pub p1: f64,
    pub p2: f64,
    pub k3: f64,
    pub k4: f64,
    pub k5: f64,
    pub k6: f64,
}

impl Distortion {
    fn from_coefficients(field: &str, d: &[f64]) -> Result<Self, CalibrationError> {
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

    fn coefficients(&self) -> Vec<f64> {
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
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub skew: f64,
    pub distortion: Distortion,
}

impl CameraModel {
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

    fn matrix(&self) -> [[f64; 3]; 3] {
        [
            [self.fx, self.skew, self.cx],
            [0.0, self.fy, self.cy],
            [0.0, 0.0, 1.0],
        ]
    }
}

/// A validated stereo rig.
#[derive(Debug, Clone, PartialEq)]
pub struct StereoRig {
    pub width: u32,
    pub height: u32,
    pub left: CameraModel,
    pub right: CameraModel,
    /// `point_in_right = right_from_left * point_in_left` (OpenCV's R, T).
    pub right_from_left: Isometry3<f64>,
}

fn check_finite(field: &str, values: &[f64]) -> Result<(), CalibrationError> {
    for (i, v) in values.iter().enumerate() {
        if !v.is_finite() {
            return Err(CalibrationError::NotFinite {
                field: format!("{field}[{i}]"),
            });
        }
    }
    Ok(())
}

fn camera_from_file(
    k_name: &str,
    k: &[[f64; 3]; 3],
    d_name: &str,
    d: &[f64],
) -> Result<CameraModel, CalibrationError> {
    for (r, row) in k.iter().enumerate() {
        check_finite(&format!("{k_name}[{r}]"), row)?;
    }
    check_finite(d_name, d)?;
    if k[1][0] != 0.0 || k[2] != [0.0, 0.0, 1.0] {
        return Err(invalid(
            k_name,
            "must be [[fx,s,cx],[0,fy,cy],[0,0,1]] (bottom row [0,0,1])",
        ));
    }
    if k[0][0] <= 0.0 || k[1][1] <= 0.0 {
        return Err(invalid(k_name, "focal lengths fx, fy must be positive"));
    }
    Ok(CameraModel {
        fx: k[0][0],
        fy: k[1][1],
        cx: k[0][2],
        cy: k[1][2],
        skew: k[0][1],
        distortion: Distortion::from_coefficients(d_name, d)?,
    })
}

/// Builds a rotation from a matrix that must already be orthonormal with determinant +1.
pub fn rotation_from_matrix(
    field: &str,
    m: &Matrix3<f64>,
) -> Result<Rotation3<f64>, CalibrationError> {
    if m.iter().any(|v| !v.is_finite()) {
        return Err(CalibrationError::NotFinite {
            field: field.to_string(),
        });
    }
    let orthogonality = (m.transpose() * m - Matrix3::identity()).abs().max();
    if orthogonality > 1e-5 {
        return Err(invalid(
            field,
            format!("is not a rotation (|R^T R - I| = {orthogonality:.2e})"),
        ));
    }
    if m.determinant() < 0.0 {
        return Err(invalid(
            field,
            "is a reflection (determinant -1), not a rotation",
        ));
    }
    if orthogonality <= 1e-12 {
        // A rotation up to rounding (as written from a quaternion): renormalised through a
        // quaternion, which gives such a matrix back bit for bit. (`Rotation3::from_matrix`
        // iterates from the identity and lands on the identity for exact 180-degree turns such
        // as diag(-1, 1, -1).)
        let unit = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(*m));
        return Ok(unit.to_rotation_matrix());
    }
    // Within tolerance but visibly off: the nearest rotation (polar decomposition, R = U V^T),
    // so that decoding what was decoded and re-encoded changes nothing (quaternion
    // renormalisation alone drifted by 2e-8: found by fuzzing the frame decoder).
    let svd = m.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Err(invalid(field, "has no singular value decomposition"));
    };
    let nearest = u * v_t;
    if nearest.determinant() < 0.0 {
        return Err(invalid(
            field,
            "is a reflection (determinant -1), not a rotation",
        ));
    }
    let unit = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(nearest));
    Ok(unit.to_rotation_matrix())
}

impl StereoRig {
    pub fn from_file(rig: &RigFile) -> Result<Self, CalibrationError> {
        let [width, height] = rig.image_size;
        if width < 2 || height < 2 {
            return Err(invalid(
                "image_size",
                "width and height must be at least 2 pixels",
            ));
        }
        let left = camera_from_file("K1", &rig.K1, "D1", &rig.D1)?;
        let right = camera_from_file("K2", &rig.K2, "D2", &rig.D2)?;
        let r = Matrix3::from_fn(|i, j| rig.R[i][j]);
        let rotation = rotation_from_matrix("R", &r)?;
        check_finite("T", &rig.T)?;
        let t = Vector3::from(rig.T);
        if t.norm() < 1e-6 {
            return Err(invalid("T", "baseline is zero: the cameras coincide"));
        }
        let rig = Self {
            width,
            height,
            left,
            right,
            right_from_left: Isometry3::from_parts(
                Translation3::from(t),
                UnitQuaternion::from_rotation_matrix(&rotation),
            ),
        };
        Rectification::new(&rig)?;
        Ok(rig)
    }

    pub fn to_file(&self) -> RigFile {
        let r = self.right_from_left.rotation.to_rotation_matrix();
        let t = self.right_from_left.translation.vector;
        RigFile {
            image_size: [self.width, self.height],
            K1: self.left.matrix(),
            D1: self.left.distortion.coefficients(),
            K2: self.right.matrix(),
            D2: self.right.distortion.coefficients(),
            R: [0, 1, 2].map(|i| [0, 1, 2].map(|j| r[(i, j)])),
            T: [t.x, t.y, t.z],
        }
    }

    /// Projects a point given in the rig (left camera) frame into both raw images.
    pub fn project(&self, point_in_rig: &Point3<f64>) -> (Option<PixelPoint>, Option<PixelPoint>) {
        (
            self.left.project(point_in_rig),
            self.right.project(&(self.right_from_left * point_in_rig)),
        )
    }

    pub fn contains(&self, p: PixelPoint) -> bool {
        p.x >= -0.5
            && p.y >= -0.5
            && p.x < self.width as f64 - 0.5
            && p.y < self.height as f64 - 0.5
    }
}

/// The virtual co-directional pair: both cameras rotated to a common orientation whose x axis runs
/// along the baseline, with one focal length. The left virtual camera sits at the rig origin and
/// the right one at `+baseline_m` along the rectified x axis, so disparity `X_L - X_R` is positive.
#[derive(Debug, Clone, PartialEq)]
pub struct Rectification {
    left: CameraModel,
    right: CameraModel,
    rect_from_left: Rotation3<f64>,
    rect_from_right: Rotation3<f64>,
    pub focal_px: f64,
    pub baseline_m: f64,
    /// Half the rectified image extent along x and y (the method's X_image, Y_image).
    pub half_width_px: f64,
    pub half_height_px: f64,
    /// See [`Self::overlap_disparity_px`].
    overlap_disparity_px: (f64, f64),
}

impl Rectification {
    pub fn new(rig: &StereoRig) -> Result<Self, CalibrationError> {
        let left_from_right_rot = rig.right_from_left.rotation.inverse();
        let right_centre_in_left = -(left_from_right_rot * rig.right_from_left.translation.vector);
        let baseline_m = right_centre_in_left.norm();
        let x_axis = right_centre_in_left / baseline_m;
        let right_axis = left_from_right_rot * Vector3::z();
        if right_axis.z <= 0.0 {
            return Err(invalid(
                "R",
                "the optical axes are 90 degrees or more apart: the cameras cannot share a view",
            ));
        }
        let mean_axis = Vector3::z() + right_axis;
        let z_axis = mean_axis - x_axis * mean_axis.dot(&x_axis);
        if z_axis.norm() < 1e-3 {
            return Err(invalid(
                "R, T",
                "the cameras look along the baseline; no common viewing direction",
            ));
        }
        let z_axis = z_axis.normalize();
        let y_axis = z_axis.cross(&x_axis);
        let rect_from_left = Rotation3::from_matrix_unchecked(Matrix3::from_rows(&[
            x_axis.transpose(),
            y_axis.transpose(),
            z_axis.transpose(),
        ]));
        let rect_from_right = rect_from_left * left_from_right_rot.to_rotation_matrix();
        let focal_px = (rig.left.fx + rig.left.fy + rig.right.fx + rig.right.fy) / 4.0;
        let mut rect = Self {
            left: rig.left,
            right: rig.right,
            rect_from_left,
            rect_from_right,
            focal_px,
            baseline_m,
            half_width_px: 0.0,
            half_height_px: 0.0,
            overlap_disparity_px: (0.0, 0.0),
        };
        let left = Self::rectified_border(rig, |p| rect.left_to_rect(p));
        let right = Self::rectified_border(rig, |p| rect.right_to_rect(p));
        let (Some(left), Some(right)) = (left, right) else {
            return Err(invalid(
                "K1, D1, K2, D2",
                "the image border cannot be undistorted",
            ));
        };
        // The method normalises by half the image size; in the virtual camera that is half the
        // extent of the left image's border once rectified.
        rect.half_width_px = (left.max_x - left.min_x) / 2.0;
        rect.half_height_px = (left.max_y - left.min_y) / 2.0;
        // From the left image's near edge against the right image's far edge, and back.
        let (min_disparity, max_disparity) = (left.min_x - right.max_x, left.max_x - right.min_x);
        rect.overlap_disparity_px = (min_disparity, max_disparity);
        if max_disparity <= min_disparity.max(0.0) {
            return Err(invalid(
                "R, T",
                "the two cameras' views do not overlap at any depth in front of them",
            ));
        }
        Ok(rect)
    }

    /// The bounding box of one image's border once rectified; `None` when it cannot be mapped.
    fn rectified_border(
        rig: &StereoRig,
        to_rect: impl Fn(PixelPoint) -> Option<RectPoint>,
    ) -> Option<RectBox> {
        let (w, h) = (rig.width as f64 - 1.0, rig.height as f64 - 1.0);
        let mut b = RectBox {
            min_x: f64::MAX,
            max_x: f64::MIN,
            min_y: f64::MAX,
            max_y: f64::MIN,
        };
        let steps = 64;
        for i in 0..=steps {
            let s = i as f64 / steps as f64;
            for p in [(s * w, 0.0), (s * w, h), (0.0, s * h), (w, s * h)] {
                if let Some(r) = to_rect(PixelPoint { x: p.0, y: p.1 }) {
                    b.min_x = b.min_x.min(r.x);
                    b.max_x = b.max_x.max(r.x);
                    b.min_y = b.min_y.min(r.y);
                    b.max_y = b.max_y.max(r.y);
                }
            }
        }
        (b.min_x < b.max_x && b.min_y < b.max_y).then_some(b)
    }

    /// The disparities `X_L - X_R` a point seen by both cameras can have, `(min, max)` pixels.
    /// The minimum is negative when the views overlap out to infinity (a parallel or diverging
    /// pair).
    pub fn overlap_disparity_px(&self) -> (f64, f64) {
        self.overlap_disparity_px
    }

    fn to_rect(
        &self,
        camera: &CameraModel,
        rect_from_cam: &Rotation3<f64>,
        p: PixelPoint,
    ) -> Option<RectPoint> {
        let (x, y) = camera.unproject(p)?;
        let ray = rect_from_cam * Vector3::new(x, y, 1.0);
        (ray.z > 1e-9).then(|| RectPoint {
            x: self.focal_px * ray.x / ray.z,
            y: self.focal_px * ray.y / ray.z,
        })
    }

    fn rect_to_camera(
        &self,
        camera: &CameraModel,
        rect_from_cam: &Rotation3<f64>,
        p: RectPoint,
    ) -> Option<PixelPoint> {
        let ray = rect_from_cam.inverse() * Vector3::new(p.x, p.y, self.focal_px);
        camera.project(&Point3::from(ray))
    }

    /// Where a rectified point lies in the raw left image; `None` behind the camera.
    pub fn rect_to_left(&self, p: RectPoint) -> Option<PixelPoint> {
        self.rect_to_camera(&self.left, &self.rect_from_left, p)
    }

    pub fn rect_to_right(&self, p: RectPoint) -> Option<PixelPoint> {
        self.rect_to_camera(&self.right, &self.rect_from_right, p)
    }

    pub fn left_to_rect(&self, p: PixelPoint) -> Option<RectPoint> {
        self.to_rect(&self.left, &self.rect_from_left, p)
    }

    pub fn right_to_rect(&self, p: PixelPoint) -> Option<RectPoint> {
        self.to_rect(&self.right, &self.rect_from_right, p)
    }

    /// Depth from disparity (method eqs. 10-12) in the virtual pair, returned in the rig frame.
    /// `None` for a non-positive disparity (a point at or beyond infinity).
    pub fn triangulate(&self, left: RectPoint, right: RectPoint) -> Option<Triangulated> {
        let disparity = left.x - right.x;
        if disparity <= 0.0 {
            return None;
        }
        let depth_m = self.focal_px * self.baseline_m / disparity;
        // The method's origin is half-way between the cameras; the rig origin is the left camera.
        let point_in_rect = Point3::new(
            depth_m * (left.x + right.x) / (2.0 * self.focal_px) + self.baseline_m / 2.0,
            depth_m * (left.y + right.y) / (2.0 * self.focal_px),
            depth_m,
        );
        Some(Triangulated {
            point_in_rig: self.rect_from_left.inverse() * point_in_rect,
            depth_m,
        })
    }

    /// Standard deviation of depth caused by a disparity error of `disparity_sigma_px`.
    pub fn depth_sigma_m(&self, depth_m: f64, disparity_sigma_px: f64) -> f64 {
        depth_m * depth_m * disparity_sigma_px / (self.focal_px * self.baseline_m)
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
struct RectBox {
    min_x: f64,
    max_x: f64,
    min_y: f64,
    max_y: f64,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Triangulated {
    pub point_in_rig: Point3<f64>,
    /// Depth along the rectified viewing direction.
    pub depth_m: f64,
}

/// Parses a row-major 4x4 rigid transform (`world_from_rig`), checking that it is rigid.
pub fn isometry_from_row_major(
    field: &str,
    m: &[f64; 16],
) -> Result<Isometry3<f64>, CalibrationError> {
    check_finite(field, m)?;
    let bottom = [m[12], m[13], m[14], m[15]];
    if bottom != [0.0, 0.0, 0.0, 1.0] {
        return Err(invalid(field, "bottom row must be 0,0,0,1"));
    }
    let r = Matrix3::new(m[0], m[1], m[2], m[4], m[5], m[6], m[8], m[9], m[10]);
    let rotation = rotation_from_matrix(field, &r)?;
    Ok(Isometry3::from_parts(
        Translation3::new(m[3], m[7], m[11]),
        UnitQuaternion::from_rotation_matrix(&rotation),
    ))
}

pub fn isometry_to_row_major(pose: &Isometry3<f64>) -> [f64; 16] {
    let m = pose.to_homogeneous();
    let mut out = [0.0; 16];
    for (i, v) in out.iter_mut().enumerate() {
        *v = m[(i / 4, i % 4)];
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn parallel_rig() -> StereoRig {
        crate::synth::parallel_rig(640, 480, 500.0, 0.1)
    }

    fn hololens_like_rig() -> StereoRig {
        crate::synth::hololens_raw_rig()
    }

    #[test]
    fn a_nearly_rigid_pose_is_projected_once_and_for_all() {
        // Off by 2e-6 from a rotation about z: accepted, and the projection is idempotent.
        let (c, s) = (0.8f64, 0.6f64);
        let m = [
            c + 2e-6,
            -s,
            0.0,
            1.0, //
            s,
            c,
            0.0,
            2.0, //
            0.0,
            0.0,
            1.0,
            3.0, //
            0.0,
            0.0,
            0.0,
            1.0,
        ];
        let once = isometry_from_row_major("pose", &m).expect("within tolerance");
        let twice = isometry_from_row_major("pose", &isometry_to_row_major(&once)).expect("rigid");
        let d = (once.to_homogeneous() - twice.to_homogeneous()).abs().max();
        assert!(d < 1e-12, "{d}");
        let r = once.rotation.to_rotation_matrix();
        assert!((r.matrix()[(0, 0)] - c).abs() < 2e-6);
        // An exact half turn stays one.
        let half = Matrix3::from_diagonal(&Vector3::new(-1.0, 1.0, -1.0));
        let r = rotation_from_matrix("R", &half).expect("a rotation");
        assert!((r.matrix() - half).abs().max() < 1e-12);
    }

    #[test]
    fn parallel_rig_rectification_is_identity() {
        let rect = Rectification::new(&parallel_rig()).expect("valid");
        assert!((rect.baseline_m - 0.1).abs() < 1e-12);
        let r = rect
            .left_to_rect(PixelPoint { x: 419.5, y: 139.5 })
            .expect("in view");
        assert!((r.x - 100.0).abs() < 1e-9 && (r.y + 100.0).abs() < 1e-9);
        assert!((rect.half_width_px - 319.5).abs() < 1e-9);
    }

    #[test]
    fn rectified_points_map_back_to_the_raw_pixels_they_came_from() {
        let rig = hololens_like_rig();
        let rect = Rectification::new(&rig).expect("valid");
        for &(x, y) in &[(3.0, 4.0), (320.5, 240.25), (600.0, 30.0), (17.0, 470.0)] {
            let p = PixelPoint { x, y };
            for (to, from) in [
                (
                    rect.left_to_rect(p).expect("maps"),
                    rect.rect_to_left(rect.left_to_rect(p).expect("maps")),
                ),
                (
                    rect.right_to_rect(p).expect("maps"),
                    rect.rect_to_right(rect.right_to_rect(p).expect("maps")),
                ),
            ] {
                let back = from.expect("in front");
                assert!(
                    (back.x - x).abs() < 1e-6 && (back.y - y).abs() < 1e-6,
                    "{to:?}"
                );
            }
        }
    }

    #[test]
    fn undistort_inverts_distort() {
        let d = hololens_like_rig().left.distortion;
        for &(x, y) in &[(0.0, 0.0), (0.5, -0.3), (-0.8, 0.6), (0.9, 0.65)] {
            let (xd, yd) = d.distort(x, y);
            let (ux, uy) = d.undistort(xd, yd).expect("invertible");
            assert!((ux - x).abs() < 1e-10 && (uy - y).abs() < 1e-10, "{x},{y}");
        }
    }

    #[test]
    fn rig_file_round_trips() {
        let rig = hololens_like_rig();
        let back = StereoRig::from_file(&rig.to_file()).expect("valid");
        assert!(
            (back.right_from_left.to_homogeneous() - rig.right_from_left.to_homogeneous())
                .abs()
                .max()
                < 1e-12
        );
        assert_eq!(back.left, rig.left);
    }

    #[test]
    fn exact_half_turns_survive_and_opposed_cameras_are_refused() {
        let half_turn = Matrix3::new(-1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0);
        let r = rotation_from_matrix("R", &half_turn).expect("a rotation");
        assert!((r.matrix() - half_turn).abs().max() < 1e-12, "{r:?}");
        let mut file = parallel_rig().to_file();
        file.R = [[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]];
        let e = StereoRig::from_file(&file).unwrap_err().to_string();
        assert!(
            e.contains("optical axes are 90 degrees or more apart"),
            "{e}"
        );
        let yawed = [
            -1.0, 0.0, 0.0, 0.5, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 2.0, 0.0, 0.0, 0.0, 1.0,
        ];
        let pose = isometry_from_row_major("pose", &yawed).expect("rigid");
        assert_eq!(
            isometry_to_row_major(&pose).map(|v| (v * 1e9).round() / 1e9),
            yawed
        );
    }

    #[test]
    fn bad_calibration_names_the_field() {
        let mut file = parallel_rig().to_file();
        file.K2[0][0] = f64::NAN;
        assert_eq!(
            StereoRig::from_file(&file).unwrap_err().to_string(),
            "K2[0][0] is not a finite number"
        );
        let mut file = parallel_rig().to_file();
        file.R[0][0] = 2.0;
        assert!(StereoRig::from_file(&file)
            .unwrap_err()
            .to_string()
            .starts_with("R: is not a rotation"));
        let mut file = parallel_rig().to_file();
        file.T = [0.0; 3];
        assert!(StereoRig::from_file(&file)
            .unwrap_err()
            .to_string()
            .contains("baseline is zero"));
        let mut file = parallel_rig().to_file();
        file.D1 = vec![0.1, 0.2, 0.3];
        assert!(StereoRig::from_file(&file)
            .unwrap_err()
            .to_string()
            .starts_with("D1: expected 0, 4, 5 or 8"));
    }

    proptest! {
        #[test]
        fn triangulating_a_projected_point_returns_it(
            x in -0.3f64..0.3, y in -0.2f64..0.2, z in 0.3f64..1.5, hololens in any::<bool>()
        ) {
            let rig = if hololens { hololens_like_rig() } else { parallel_rig() };
            let rect = Rectification::new(&rig).expect("valid");
            let p = Point3::new(x, y, z);
            let (l, r) = rig.project(&p);
            let (l, r) = (l.expect("in front"), r.expect("in front"));
            let lr = rect.left_to_rect(l).expect("undistortable");
            let rr = rect.right_to_rect(r).expect("undistortable");
            prop_assert!((lr.y - rr.y).abs() < 1e-6, "rectified rows differ: {} vs {}", lr.y, rr.y);
            let t = rect.triangulate(lr, rr).expect("positive disparity");
            prop_assert!((t.point_in_rig - p).norm() < 1e-8, "{:?} vs {:?}", t.point_in_rig, p);
        }

        #[test]
        fn pose_round_trips_through_row_major(yaw in -3.0f64..3.0, pitch in -1.5f64..1.5, tx in -1.0f64..1.0) {
            let pose = Isometry3::from_parts(Translation3::new(tx, 0.5, -0.2), UnitQuaternion::from_euler_angles(0.1, pitch, yaw));
            let back = isometry_from_row_major("pose", &isometry_to_row_major(&pose)).expect("rigid");
            prop_assert!((back.to_homogeneous() - pose.to_homogeneous()).abs().max() < 1e-9);
        }
    }
}
