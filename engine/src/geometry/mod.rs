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

mod lens;
mod rectification;

pub use lens::{CameraModel, Distortion};
pub use rectification::{Rectification, Triangulated};

/// A position in a raw camera image, in pixels (OpenCV convention).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct PixelPoint {
    /// Column, pixels (0 at the centre of the leftmost pixel).
    pub x: f64,
    /// Row, pixels (0 at the centre of the top pixel).
    pub y: f64,
}

/// A position in the rectified virtual camera image, in pixels relative to its principal point
/// (the method's "image plane origin at the image centre").
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct RectPoint {
    /// Along the baseline, rectified pixels.
    pub x: f64,
    /// Across it (the epipolar row), rectified pixels.
    pub y: f64,
}

impl RectPoint {
    /// The squared distance to `other`, rectified pixels squared.
    pub(crate) fn distance_sq(self, other: RectPoint) -> f64 {
        (self.x - other.x).powi(2) + (self.y - other.y).powi(2)
    }
}

/// What is wrong with a calibration, naming the offending field.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum CalibrationError {
    /// A number is NaN or infinite.
    #[error("{field} is not a finite number")]
    NotFinite {
        /// The field, as `rig.json` names it.
        field: String,
    },
    /// A value is out of its range.
    #[error("{field}: {reason}")]
    Invalid {
        /// The field, as `rig.json` names it.
        field: String,
        /// What it must be.
        reason: String,
    },
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
    /// [width, height], pixels.
    pub image_size: [u32; 2],
    /// Left camera matrix.
    pub K1: [[f64; 3]; 3],
    /// Left camera distortion.
    pub D1: Vec<f64>,
    /// Right camera matrix.
    pub K2: [[f64; 3]; 3],
    /// Right camera distortion.
    pub D2: Vec<f64>,
    /// Rotation from the left camera's frame to the right's.
    pub R: [[f64; 3]; 3],
    /// Translation: `x_right = R x_left + T`, metres.
    pub T: [f64; 3],
}

/// A validated stereo rig.
#[derive(Debug, Clone, PartialEq)]
pub struct StereoRig {
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// The left camera.
    pub left: CameraModel,
    /// The right camera.
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
    /// The rig a `rig.json` describes, refused where a value is not finite or not valid.
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

    /// The rig as `rig.json` writes it.
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

    /// Whether a pixel lies on the image.
    pub fn contains(&self, p: PixelPoint) -> bool {
        p.x >= -0.5
            && p.y >= -0.5
            && p.x < self.width as f64 - 0.5
            && p.y < self.height as f64 - 0.5
    }
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

/// A pose as the 16 numbers of its 4x4 matrix, row-major.
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
