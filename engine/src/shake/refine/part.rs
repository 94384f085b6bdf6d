//! A detected region several tracks expect particles on, parted with what the tracks know:
//! each expected particle seeded where its track puts it, with the shape its track learnt (a
//! particle no 3D track knows with a shape guessed from its share of the region), all fitted
//! in sweeps against the region's pixels. Cheaper than fitting free spots, and the widths are
//! the tracks' own rather than traded against the positions.

use super::sweep::Sweep;
use super::{CameraShake, Member, Shape, MAX_RESIDUAL_RATIO};
use crate::geometry::PixelPoint;
use crate::ImageView;

impl CameraShake {
    /// The centres of the particles expected on a region (`expected`: each where its track
    /// puts it, with its track's shape if it has one), fitted to the region's `pixels` (x, y,
    /// grey level); `share_px` is the diameter of each particle's share of the region's area.
    /// `None` until the camera has learnt from lone particles, or where the fit does not
    /// explain the pixels, a particle did not settle or left its place.
    pub(crate) fn part(
        &self,
        image: ImageView<'_>,
        pixels: &[(f64, f64, f64)],
        expected: &[(PixelPoint, Option<Shape>)],
        share_px: f64,
    ) -> Option<Vec<PixelPoint>> {
        let lone_rms = self.lone_rms?;
        let seeds = expected
            .iter()
            .map(|&(at, shape)| {
                let shape = shape.or_else(|| self.guess_from_size(image, at, share_px))?;
                Some(Member { at, shape })
            })
            .collect::<Option<Vec<Member>>>()?;
        let mut sweep = Sweep::default();
        for (id, seed) in seeds.iter().enumerate() {
            sweep.add(id, *seed);
        }
        sweep.run_on(pixels);
        // Each particle's residual may hold every member's mismatch, as in a group fit.
        let max_rms = MAX_RESIDUAL_RATIO * lone_rms * (seeds.len() as f64).sqrt();
        let told = (0..seeds.len()).all(|i| {
            let (fitted, seed) = (sweep.member(i), seeds[i]);
            let moved = (fitted.at.x - seed.at.x).hypot(fitted.at.y - seed.at.y);
            sweep.fitted(i)
                && sweep.settled(i)
                && fitted.shape.amplitude > 0.0
                && moved <= seed.shape.radius_px
                && sweep.rms_on(i) <= max_rms
        });
        told.then(|| (0..seeds.len()).map(|i| sweep.member(i).at).collect())
    }

    /// The shape of a particle of detected size `diameter_px` at `at`, with the camera's
    /// learnt edge and radius per size; `None` until they are learnt.
    fn guess_from_size(
        &self,
        image: ImageView<'_>,
        at: PixelPoint,
        diameter_px: f64,
    ) -> Option<Shape> {
        let radius_px = self.radius_per_half_diameter? * 0.5 * diameter_px;
        self.guessed_shape(image, at, radius_px, self.edge_px?)
    }
}
