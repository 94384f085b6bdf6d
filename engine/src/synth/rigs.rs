//! The scenarios' camera rigs.

use std::f64::consts::PI;

use nalgebra::{Isometry3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};

use crate::geometry::{CameraModel, Distortion, StereoRig};

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
pub(super) fn axes_crossing(baseline_m: f64, toe_in_rad: f64) -> Point3<f64> {
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
