//! The frames the pipeline consumes: borrowed grayscale images and synchronized stereo pairs.

use crate::geometry::PixelPoint;
use nalgebra::Isometry3;

/// A borrowed 8-bit grayscale image, row-major, no padding.
#[derive(Debug, Clone, Copy)]
pub struct ImageView<'a> {
    /// Pixels per row.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Row-major pixels, `width * height` of them.
    pub pixels: &'a [u8],
}

impl<'a> ImageView<'a> {
    /// `None` when the buffer does not hold exactly `width * height` pixels.
    pub fn new(width: usize, height: usize, pixels: &'a [u8]) -> Option<Self> {
        (width.checked_mul(height) == Some(pixels.len())).then_some(Self {
            width,
            height,
            pixels,
        })
    }

    /// Bilinear intensity at a sub-pixel position, clamped to the image.
    pub fn bilinear(&self, p: PixelPoint) -> f64 {
        let x = p.x.clamp(0.0, (self.width - 1) as f64);
        let y = p.y.clamp(0.0, (self.height - 1) as f64);
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(self.width - 1), (y0 + 1).min(self.height - 1));
        let (fx, fy) = (x - x0 as f64, y - y0 as f64);
        let at = |xx: usize, yy: usize| self.pixels[yy * self.width + xx] as f64;
        (at(x0, y0) * (1.0 - fx) + at(x1, y0) * fx) * (1.0 - fy)
            + (at(x0, y1) * (1.0 - fx) + at(x1, y1) * fx) * fy
    }
}

/// One synchronized stereo pair as the pipeline consumes it.
#[derive(Debug, Clone, Copy)]
pub struct StereoFrame<'a> {
    /// The frame's index as its source numbered it.
    pub index: u64,
    /// Sensor timestamp, seconds; must increase from frame to frame.
    pub t_s: f64,
    /// Headset pose for this frame; `None` means world = rig.
    pub world_from_rig: Option<Isometry3<f64>>,
    /// The left camera's image.
    pub left: ImageView<'a>,
    /// The right camera's image.
    pub right: ImageView<'a>,
}
