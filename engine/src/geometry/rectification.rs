//! The virtual co-directional pair the method runs in: each centroid undistorted and rotated
//! into two pinholes with the baseline along x, and triangulated there.

use nalgebra::{Matrix3, Point3, Rotation3, Vector3};

use super::{invalid, CalibrationError, CameraModel, PixelPoint, RectPoint, StereoRig};

/// The virtual co-directional pair: both cameras rotated to a common orientation whose x axis runs
/// along the baseline, with one focal length. The left virtual camera sits at the rig origin and
/// the right one at `+baseline_m` along the rectified x axis, so disparity `X_L - X_R` is positive.
#[derive(Debug, Clone, PartialEq)]
pub struct Rectification {
    left: CameraModel,
    right: CameraModel,
    rect_from_left: Rotation3<f64>,
    rect_from_right: Rotation3<f64>,
    /// The virtual pair's focal length, pixels.
    pub focal_px: f64,
    /// The baseline, metres.
    pub baseline_m: f64,
    /// Half the rectified image extent along x and y (the method's X_image, Y_image).
    pub half_width_px: f64,
    /// See `half_width_px`.
    pub half_height_px: f64,
    /// See [`Self::overlap_disparity_px`].
    overlap_disparity_px: (f64, f64),
}

impl Rectification {
    /// The virtual pair of `rig`, refused where its cameras do not share a view.
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

    /// A rectified point in the raw right image.
    pub fn rect_to_right(&self, p: RectPoint) -> Option<PixelPoint> {
        self.rect_to_camera(&self.right, &self.rect_from_right, p)
    }

    /// A raw left pixel in the rectified pair.
    pub fn left_to_rect(&self, p: PixelPoint) -> Option<RectPoint> {
        self.to_rect(&self.left, &self.rect_from_left, p)
    }

    /// A raw right pixel in the rectified pair.
    pub fn right_to_rect(&self, p: PixelPoint) -> Option<RectPoint> {
        self.to_rect(&self.right, &self.rect_from_right, p)
    }

    /// [`Self::left_to_rect`] for camera 0, [`Self::right_to_rect`] for camera 1.
    pub(crate) fn pixel_to_rect(&self, camera: usize, p: PixelPoint) -> Option<RectPoint> {
        if camera == 0 {
            self.left_to_rect(p)
        } else {
            self.right_to_rect(p)
        }
    }

    /// [`Self::rect_to_left`] for camera 0, [`Self::rect_to_right`] for camera 1.
    pub(crate) fn rect_to_pixel(&self, camera: usize, p: RectPoint) -> Option<PixelPoint> {
        if camera == 0 {
            self.rect_to_left(p)
        } else {
            self.rect_to_right(p)
        }
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

    /// Where a point of the rig frame lies in the rectified left and right images (what
    /// [`Self::triangulate`] inverts); `None` at or behind the cameras' plane.
    pub fn project(&self, point_in_rig: &Point3<f64>) -> Option<(RectPoint, RectPoint)> {
        let p = self.rect_from_left * point_in_rig;
        (p.z > 1e-9).then(|| {
            let y = self.focal_px * p.y / p.z;
            (
                RectPoint {
                    x: self.focal_px * p.x / p.z,
                    y,
                },
                RectPoint {
                    x: self.focal_px * (p.x - self.baseline_m) / p.z,
                    y,
                },
            )
        })
    }

    /// Camera `camera`'s centre (0 left, 1 right) in the rig frame: the left camera is its
    /// origin, the right one `baseline_m` along the rectified x axis.
    pub(crate) fn camera_in_rig(&self, camera: usize) -> Point3<f64> {
        match camera {
            0 => Point3::origin(),
            _ => self.rect_from_left.inverse() * Point3::new(self.baseline_m, 0.0, 0.0),
        }
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

/// A triangulated particle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Triangulated {
    /// Its position in the rig frame, metres.
    pub point_in_rig: Point3<f64>,
    /// Depth along the rectified viewing direction.
    pub depth_m: f64,
}
