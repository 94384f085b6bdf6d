//! The causal per-camera background model ([`DetectConfig::background_rise_per_frame`]): each
//! pixel's background follows its darkest recent value in the blurred image and rises slowly
//! where the pixel stays bright, so what stands still in the image fades out of the detection.
//!
//! [`DetectConfig::background_rise_per_frame`]: super::DetectConfig::background_rise_per_frame

/// Frames a pixel must stay brighter than its background model before the model rises there.
const DELAY_FRAMES: u8 = 10;

/// The model, in the blurred image's units (grey levels x 256); empty when the model is off.
#[derive(Debug, Default)]
pub(super) struct Background {
    /// Per pixel: the model as it stood before the current image.
    model: Vec<u16>,
    /// The model once the current image is in it.
    next: Vec<u16>,
    /// Per pixel: frames in a row it has been brighter than its model.
    bright_frames: Vec<u8>,
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
        for (((d, &b), next), bright) in blurred
            .iter_mut()
            .zip(&self.model[row.clone()])
            .zip(&mut self.next[row.clone()])
            .zip(&mut self.bright_frames[row])
        {
            let above = *d > b.saturating_add(rise);
            *bright = if above { bright.saturating_add(1) } else { 0 };
            *next = if !above || *bright > DELAY_FRAMES {
                b.saturating_add(rise).min(*d)
            } else {
                b
            };
            *d = d.saturating_sub(b);
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
