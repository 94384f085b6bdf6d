//! The causal per-camera background model ([`DetectConfig::background_rise_per_frame`]): each
//! pixel's background follows its darkest recent value in the blurred image and rises slowly
//! where the pixel stays bright, so what stands still in the image fades out of the detection.
//!
//! [`DetectConfig::background_rise_per_frame`]: super::DetectConfig::background_rise_per_frame

/// Frames a pixel must stay brighter than its background model before the model rises there.
const DELAY_FRAMES: u16 = 10;

/// The model, in the blurred image's units (grey levels x 256); empty when the model is off.
#[derive(Debug, Default)]
pub(super) struct Background {
    /// Per pixel: the model as it stood before the current image.
    model: Vec<u16>,
    /// The model once the current image is in it.
    next: Vec<u16>,
    /// Per pixel: frames in a row it has been brighter than its model (as wide as the model, so
    /// the row update vectorises in one lane width).
    bright_frames: Vec<u16>,
}

impl Background {
    /// Readies the model for an image of `pixels` pixels and returns the rise per frame in the
    /// blurred image's units: at least one unit so the model can rise, 0 when the model is off
    /// (`rise_per_frame` grey levels, 0 or less), which also forgets it.
    pub(super) fn prepare(&mut self, pixels: usize, rise_per_frame: f64) -> u16 {
        if rise_per_frame <= 0.0 {
            self.model.clear();
            return 0;
        }
        if self.model.len() != pixels {
            self.model.clear();
            self.model.resize(pixels, 0);
            self.next.resize(pixels, 0);
            self.bright_frames.clear();
            self.bright_frames.resize(pixels, 0);
        }
        (rise_per_frame * 256.0).round().clamp(1.0, 65535.0) as u16
    }

    /// Updates the model of the pixels `row` with their blurred values `blurred` and takes the
    /// model out of them.
    ///
    /// The image is compared with the model as it stood before this frame, so a particle
    /// arriving at a pixel keeps its whole contrast; the updated model takes its place once the
    /// image is measured ([`Self::commit`]). A pixel brighter than its model raises it only
    /// after `DELAY_FRAMES` frames in a row, so a particle passing over it leaves the model (and
    /// its own centroid) untouched.
    pub(super) fn subtract_row(
        &mut self,
        row: std::ops::Range<usize>,
        blurred: &mut [u16],
        rise: u16,
    ) {
        let model = &self.model[row.clone()];
        let next = &mut self.next[row.clone()];
        let bright = &mut self.bright_frames[row];
        let n = blurred
            .len()
            .min(model.len())
            .min(next.len())
            .min(bright.len());
        let (blurred, model, next, bright) = (
            &mut blurred[..n],
            &model[..n],
            &mut next[..n],
            &mut bright[..n],
        );
        // Branch-free on equal-length slices, so the compiler vectorises the row.
        for i in 0..n {
            let (d, b) = (blurred[i], model[i]);
            let raised = b.saturating_add(rise);
            let above = u16::from(d > raised);
            // Counts up while above (0 otherwise); saturating, as only `> DELAY_FRAMES` matters.
            let frames = bright[i].saturating_add(1) * above;
            bright[i] = frames;
            let keep = above & u16::from(frames <= DELAY_FRAMES);
            next[i] = if keep == 1 { b } else { raised.min(d) };
            blurred[i] = d.saturating_sub(b);
        }
    }

    /// Makes the model updated by the current image the one the next image is compared with.
    pub(super) fn commit(&mut self, rise: u16) {
        if rise > 0 {
            std::mem::swap(&mut self.model, &mut self.next);
        }
    }

    /// The model at pixel `i`, grey levels (0 when the model is off).
    #[inline]
    pub(super) fn at(&self, i: usize) -> f64 {
        self.model.get(i).map_or(0.0, |&b| b as f64 / 256.0)
    }
}
