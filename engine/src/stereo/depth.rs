//! The stereo search narrowed to the depths where confirmed 3D tracks are.

use std::collections::VecDeque;

use super::StereoSearch;

/// Bins of the disparity histogram a [`DepthLearner`] keeps.
const LEARN_BINS: usize = 512;
/// Frames of confirmed tracks a [`DepthLearner`] looks back over (3 s at 30 Hz).
const LEARN_WINDOW_FRAMES: u64 = 90;
/// Confirmed samples within the window before the search is narrowed.
const LEARN_MIN_SAMPLES: usize = 200;

/// Learns where the measurement volume lies from the tracks themselves. A rig's views overlap
/// from a few centimetres to infinity, so at 0.005 particles per pixel a left particle has
/// seven candidates in its band, and the wrong ones become ghosts or break tracks. Disparities
/// of confirmed 3D tracks (real particles, seen for several frames) are kept for the last
/// `LEARN_WINDOW_FRAMES`; once there are `LEARN_MIN_SAMPLES`, the search is narrowed to their
/// 5th to 95th percentile widened by that span (and 2 px) on each side: a ghost minority
/// cannot stretch it, and the volume's tails stay inside. The window slides, so the search
/// follows a volume that moves; where confirmed tracks stop coming (the wearer turned to
/// another flow), it falls back to the full search within the window and learns again.
#[derive(Debug, Clone)]
pub struct DepthLearner {
    full: StereoSearch,
    focal_baseline: f64,
    recent: VecDeque<(u64, usize)>,
    counts: Vec<usize>,
    /// What `recent` says, settled once per frame by `add`.
    narrowed: Option<StereoSearch>,
}

impl DepthLearner {
    /// `focal_baseline`: the rectified pair's focal length times baseline, px m.
    pub fn new(full: StereoSearch, focal_baseline: f64) -> Self {
        Self {
            full,
            focal_baseline,
            recent: VecDeque::new(),
            counts: vec![0; LEARN_BINS],
            narrowed: None,
        }
    }

    fn bin_width(&self) -> f64 {
        (self.full.max_disparity_px - self.full.min_disparity_px).max(1e-9) / LEARN_BINS as f64
    }

    /// Adds the depths (m) of frame `seq`'s confirmed tracks, forgets those that left the
    /// window, and settles the search for the next frame.
    pub fn add(&mut self, seq: u64, depths_m: impl Iterator<Item = f64>) {
        let width = self.bin_width();
        for depth_m in depths_m {
            let d = self.focal_baseline / depth_m;
            if !d.is_finite() {
                continue;
            }
            let bin = ((d - self.full.min_disparity_px) / width).floor();
            let bin = bin.clamp(0.0, (LEARN_BINS - 1) as f64) as usize;
            self.counts[bin] += 1;
            self.recent.push_back((seq, bin));
        }
        while let Some(&(oldest, bin)) = self.recent.front() {
            if oldest + LEARN_WINDOW_FRAMES > seq {
                break;
            }
            self.counts[bin] -= 1;
            self.recent.pop_front();
        }
        self.narrowed = self.learnt();
    }

    /// The search narrowed to the learnt volume, or `None` while too few tracks confirm it.
    pub fn search(&self) -> Option<StereoSearch> {
        self.narrowed
    }

    fn learnt(&self) -> Option<StereoSearch> {
        let total = self.recent.len();
        if total < LEARN_MIN_SAMPLES {
            return None;
        }
        let width = self.bin_width();
        let percentile = |fraction: f64| {
            let wanted = (fraction * total as f64).ceil() as usize;
            let mut seen = 0;
            for (bin, &count) in self.counts.iter().enumerate() {
                seen += count;
                if seen >= wanted.max(1) {
                    return bin;
                }
            }
            LEARN_BINS - 1
        };
        let low = self.full.min_disparity_px + percentile(0.05) as f64 * width;
        let high = self.full.min_disparity_px + (percentile(0.95) + 1) as f64 * width;
        let margin = (high - low) + 2.0;
        Some(
            self.full
                .narrowed(low - margin, high + margin, self.focal_baseline),
        )
    }
}
