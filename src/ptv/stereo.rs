//! Stage 3: stereo matching in the rectified pair (method section 3.3).
//!
//! Hard filter (eq. 7): the right particle must lie on the left one's epipolar row within S and at
//! a positive disparity below K. Among the survivors the cost F (eq. 8) mixes diameter, apparent
//! speed U, brightness and the row difference; x is left out because it carries the depth.
//!
//! Beyond the method: one-to-one assignment (a right particle serves one left particle), and
//! track-level matching: the cost of pairing a left track with a right track is averaged over the
//! frames both have been candidates (an exponential moving average), so a pair is judged on the
//! tracks' whole shared history rather than on one frame. A wrong pair that looked best for a frame
//! (its true partner hidden by an overlap) loses as soon as the true partner is back, while a true
//! pair survives a single noisy frame.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use super::link::{
    assign, normalising_mean, Assignment, CostScale, Feature, LinkedFeature, SortedByX,
};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StereoConfig {
    /// K as a fraction of the rectified image width (method: 0.25).
    pub disparity_range_fraction: f64,
    /// S as a fraction of the rectified image height (method: 0.01).
    pub epipolar_band_fraction: f64,
    /// c1, c2, c3: weights of the diameter, speed and brightness terms (published: 0.100, 0.036,
    /// 0.018).
    pub weight_diameter: f64,
    pub weight_speed: f64,
    pub weight_brightness: f64,
    /// Weight of the row-difference term (method: 1). After rectification the rows of a true
    /// pair agree to a fraction of a pixel, far better than diameters agree; at weight 1 a
    /// 4 px row offset on a 720 px image costs less than diameter noise, so two particles at
    /// similar depth can be cross-matched. 100 makes a 1 px row offset cost about as much as
    /// a 10 % diameter mismatch.
    pub weight_row: f64,
    pub assignment: Assignment,
    /// Weight of a track pair's past cost in its effective cost, 0..1: `effective = w * past +
    /// (1 - w) * now`. 0 decides every frame afresh (the method). Above 0, a left track that
    /// changes partner also starts a new 3D track.
    pub pair_memory: f64,
}

impl Default for StereoConfig {
    fn default() -> Self {
        Self {
            disparity_range_fraction: 0.25,
            epipolar_band_fraction: 0.01,
            weight_diameter: 0.100,
            weight_speed: 0.036,
            weight_brightness: 0.018,
            weight_row: 100.0,
            assignment: Assignment::OneToOne,
            pair_memory: 0.8,
        }
    }
}

/// Effective costs of (left track, right track) pairs that were candidates in the previous frame.
pub type PairHistory = BTreeMap<(u64, u64), f64>;

/// Matches left to right features; returns `(left index, right index)` pairs sorted by left index.
/// `history` holds last frame's effective pair costs and is replaced by this frame's.
pub fn match_stereo(
    left: &[LinkedFeature],
    right: &[LinkedFeature],
    scale: CostScale,
    history: &mut PairHistory,
    config: &StereoConfig,
) -> Vec<(usize, usize)> {
    let max_disparity = config.disparity_range_fraction * 2.0 * scale.half_width_px;
    let band = config.epipolar_band_fraction * 2.0 * scale.half_height_px;
    let all = || left.iter().chain(right);
    let d_ave = normalising_mean(all().map(|f| f.feature.diameter_px));
    let b_ave = normalising_mean(all().map(|f| f.feature.brightness));
    let u_ave = normalising_mean(all().filter_map(LinkedFeature::speed_px));
    let passes = |l: &Feature, r: &Feature| {
        let disparity = l.rect.x - r.rect.x;
        disparity > 0.0 && disparity < max_disparity && (l.rect.y - r.rect.y).abs() <= band
    };

    let right_features: Vec<Feature> = right.iter().map(|r| r.feature).collect();
    let sorted = SortedByX::new(&right_features);
    let memory = config.pair_memory;
    let mut next_history = PairHistory::new();
    let mut candidates = Vec::new();
    for (li, l) in left.iter().enumerate() {
        for ri in sorted.within(l.feature.rect.x - max_disparity, l.feature.rect.x) {
            let r = &right[ri];
            if !passes(&l.feature, &r.feature) {
                continue;
            }
            let speed_term = match (l.speed_px(), r.speed_px()) {
                (Some(a), Some(b)) => ((a - b) / u_ave).powi(2),
                _ => 0.0,
            };
            let cost = config.weight_diameter
                * ((l.feature.diameter_px - r.feature.diameter_px) / d_ave).powi(2)
                + config.weight_speed * speed_term
                + config.weight_brightness
                    * ((l.feature.brightness - r.feature.brightness) / b_ave).powi(2)
                + config.weight_row
                    * ((l.feature.rect.y - r.feature.rect.y) / scale.half_height_px).powi(2);
            let key = (l.track_id, r.track_id);
            let effective = match history.get(&key) {
                Some(past) if memory > 0.0 => memory * past + (1.0 - memory) * cost,
                _ => cost,
            };
            if memory > 0.0 {
                next_history.insert(key, effective);
            }
            candidates.push((effective, li, ri));
        }
    }
    *history = next_history;
    assign(candidates, left.len(), right.len(), config.assignment)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::RectPoint;

    const SCALE: CostScale = CostScale {
        half_width_px: 320.0,
        half_height_px: 240.0,
    };

    fn linked(track_id: u64, x: f64, y: f64, diameter_px: f64) -> LinkedFeature {
        LinkedFeature {
            feature: Feature {
                rect: RectPoint { x, y },
                diameter_px,
                brightness: 100.0,
            },
            track_id,
            motion_px: None,
            age: 1,
        }
    }

    #[test]
    fn hard_filter_rejects_negative_disparity_and_off_row() {
        let left = [linked(1, 0.0, 0.0, 5.0)];
        let right = [
            linked(9, 5.0, 0.0, 5.0),
            linked(8, -10.0, 6.0, 5.0),
            linked(7, -200.0, 0.0, 5.0),
        ];
        let pairs = match_stereo(
            &left,
            &right,
            SCALE,
            &mut PairHistory::new(),
            &StereoConfig::default(),
        );
        assert!(pairs.is_empty(), "{pairs:?}");
    }

    #[test]
    fn monocular_cue_picks_the_match_on_a_shared_row() {
        let left = [linked(1, 50.0, 10.0, 8.0)];
        let right = [linked(2, 20.0, 10.0, 4.0), linked(3, 30.0, 10.0, 8.0)];
        let pairs = match_stereo(
            &left,
            &right,
            SCALE,
            &mut PairHistory::new(),
            &StereoConfig::default(),
        );
        assert_eq!(pairs, vec![(0, 1)]);
    }

    #[test]
    fn pair_history_outweighs_one_odd_frame() {
        let config = StereoConfig::default();
        let mut history = PairHistory::new();
        // Frames where track 2 is clearly the partner of left track 1 ...
        for _ in 0..5 {
            let left = [linked(1, 50.0, 10.0, 8.0)];
            let right = [linked(2, 20.0, 10.0, 8.0), linked(3, 30.0, 10.0, 5.0)];
            assert_eq!(
                match_stereo(&left, &right, SCALE, &mut history, &config),
                vec![(0, 0)]
            );
        }
        // ... then one frame where noise makes track 3 look slightly better.
        let left = [linked(1, 50.0, 10.0, 8.0)];
        let right = [linked(2, 20.0, 10.0, 7.0), linked(3, 30.0, 10.0, 7.4)];
        let mut fresh = PairHistory::new();
        let method = StereoConfig {
            pair_memory: 0.0,
            ..config.clone()
        };
        assert_eq!(
            match_stereo(&left, &right, SCALE, &mut fresh, &method),
            vec![(0, 1)]
        );
        assert_eq!(
            match_stereo(&left, &right, SCALE, &mut history, &config),
            vec![(0, 0)]
        );
    }
}
