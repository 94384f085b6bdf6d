//! Stage 3: stereo matching in the rectified pair (method section 3.3).
//!
//! Hard filter (eq. 7): the right particle must lie on the left one's epipolar row within S and at
//! a disparity inside the search range. Beyond the method, both come from geometry rather than
//! image fractions ([`StereoSearch`]): the disparity range from the depths where the two views
//! overlap (or the measurement volume's depth range, when given), since in the rectified pair
//! disparity = f h / z; S in pixels, from how well a calibrated, rectified pair keeps a true pair
//! on one row. Among the survivors the cost F (eq. 8) mixes diameter, apparent
//! speed U, brightness and the row difference; x is left out because it carries the depth.
//!
//! Beyond the method: one-to-one assignment (a right particle serves one left particle), and
//! track-level matching: the cost of pairing a left track with a right track is averaged over the
//! frames both have been candidates (an exponential moving average), so a pair is judged on the
//! tracks' whole shared history rather than on one frame. A wrong pair that looked best for a frame
//! (its true partner hidden by an overlap) loses as soon as the true partner is back, while a true
//! pair survives a single noisy frame.

use crate::config::{check_non_negative, ConfigError};
use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::geometry::Rectification;
use crate::link::{CostScale, Feature, LinkedFeature};
use crate::spatial::{assign, normalising_mean, Assignment, SortedByX};

mod depth;

pub use depth::DepthLearner;

/// Stereo matching parameters.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StereoConfig {
    /// The measurement volume's depth range, `[near, far]` metres along the rectified viewing
    /// direction (`far` may be `inf`). Absent: every depth at which the two views overlap.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub depth_range_m: Option<[f64; 2]>,
    /// S: how far, in rectified pixels, the rows of a true pair may differ: calibration error
    /// plus centroid noise. A calibrated pair keeps them well inside 1 px; 2 leaves room for a
    /// fair calibration without letting many ghosts in.
    pub epipolar_band_px: f64,
    /// The method's K as a fraction of the rectified image width (method: 0.25). When set, it
    /// replaces the disparity range from geometry (and `depth_range_m`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub disparity_range_fraction: Option<f64>,
    /// The method's S as a fraction of the rectified image height (method: 0.01). When set, it
    /// replaces `epipolar_band_px`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub epipolar_band_fraction: Option<f64>,
    /// c1, c2, c3: weights of the diameter, speed and brightness terms (published: 0.100, 0.036,
    /// 0.018).
    pub weight_diameter: f64,
    /// See `weight_diameter`.
    pub weight_speed: f64,
    /// See `weight_diameter`.
    pub weight_brightness: f64,
    /// Weight of the row-difference term (method: 1). After rectification the rows of a true
    /// pair agree to a fraction of a pixel, far better than diameters agree; at weight 1 a
    /// 4 px row offset on a 720 px image costs less than diameter noise, so two particles at
    /// similar depth can be cross-matched. 100 makes a 1 px row offset cost about as much as
    /// a 10 % diameter mismatch.
    pub weight_row: f64,
    /// Weight of the row difference measured in epipolar bands, `(row difference / S)^2`: how
    /// far off its row a candidate lies against how far a true pair may be. It is the same for
    /// every image size, unlike `weight_row`'s image-height normalisation, which makes a pixel
    /// of row error cost less the taller the image.
    pub weight_epipolar: f64,
    /// How claims on a right feature are settled.
    pub assignment: Assignment,
    /// Weight of a track pair's past cost in its effective cost, 0..1: `effective = w * past +
    /// (1 - w) * now`. 0 decides every frame afresh (the method). Above 0, a left track that
    /// changes partner also starts a new 3D track.
    pub pair_memory: f64,
    /// Narrow the disparity search to the depths where the 3D tracks are (see
    /// [`DepthLearner`]) while no `depth_range_m` or `disparity_range_fraction` sets it.
    pub learn_depth_range: bool,
}

impl Default for StereoConfig {
    fn default() -> Self {
        Self {
            depth_range_m: None,
            epipolar_band_px: 2.0,
            disparity_range_fraction: None,
            epipolar_band_fraction: None,
            weight_diameter: 0.100,
            weight_speed: 0.036,
            weight_brightness: 0.018,
            weight_row: 0.0,
            weight_epipolar: WEIGHT_EPIPOLAR,
            assignment: Assignment::OneToOne,
            pair_memory: 0.8,
            learn_depth_range: true,
        }
    }
}

impl StereoConfig {
    /// The published method: search ranges as image fractions (K = 0.25, S = 0.01), each
    /// particle its own cheapest candidate, every frame decided afresh, rows weighed as the
    /// other terms.
    pub fn method() -> Self {
        Self {
            assignment: Assignment::PerParticle,
            pair_memory: 0.0,
            weight_row: 1.0,
            weight_epipolar: 0.0,
            disparity_range_fraction: Some(0.25),
            epipolar_band_fraction: Some(0.01),
            learn_depth_range: false,
            ..Self::default()
        }
    }

    /// Refuses values no run can use, naming the key as the config file spells it.
    pub fn validate(&self) -> Result<(), ConfigError> {
        check_non_negative(
            "stereo",
            &[
                (
                    "disparity_range_fraction",
                    self.disparity_range_fraction.unwrap_or(0.0),
                ),
                (
                    "epipolar_band_fraction",
                    self.epipolar_band_fraction.unwrap_or(0.0),
                ),
                ("weight_diameter", self.weight_diameter),
                ("weight_speed", self.weight_speed),
                ("weight_brightness", self.weight_brightness),
                ("pair_memory", self.pair_memory),
                ("weight_row", self.weight_row),
                ("weight_epipolar", self.weight_epipolar),
            ],
        )?;
        let bad = |key, reason| Err(ConfigError::invalid("stereo", key, reason));
        if !(self.epipolar_band_px.is_finite() && self.epipolar_band_px > 0.0) {
            return bad("epipolar_band_px", "must be a finite number of pixels > 0");
        }
        if let Some([near_m, far_m]) = self.depth_range_m {
            if !(near_m.is_finite() && near_m > 0.0 && far_m > near_m) {
                return bad(
                    "depth_range_m",
                    "must be [near, far] metres with 0 < near < far (far may be inf)",
                );
            }
        }
        if self.pair_memory >= 1.0 {
            return bad("pair_memory", "must be below 1 (1 would never update)");
        }
        Ok(())
    }
}

/// `weight_epipolar`'s default: a candidate a whole band off its row costs 1, more than the
/// diameter, speed and brightness terms add up to for any but a grossly mismatched pair
/// (each is its weight times a squared relative difference). The rows of a true pair agree to
/// the centroid noise in every image size, so the row decides between candidates, and diameter,
/// speed and brightness settle the candidates on one row.
const WEIGHT_EPIPOLAR: f64 = 1.0;

/// The hard filter's bounds in the rectified pair, settled once per rig and config.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct StereoSearch {
    /// A right particle matches only at a disparity `X_L - X_R` in this open interval, pixels;
    /// the minimum is never negative (a point in front of both cameras).
    pub min_disparity_px: f64,
    /// See `min_disparity_px`.
    pub max_disparity_px: f64,
    /// ... and on a row within this many pixels of the left particle's.
    pub epipolar_band_px: f64,
    /// The depths those disparities stand for, metres (`far` is infinite for a zero minimum).
    pub near_m: f64,
    /// See `near_m`.
    pub far_m: f64,
}

/// Why no stereo search can be set up for a rig and config.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SearchError {
    #[error(
        "stereo.depth_range_m {near_m}..{far_m} m lies outside the depths at which the two cameras \
         see the same points ({overlap_near_m:.3}..{overlap_far_m:.3} m)"
    )]
    /// The given depth range and the cameras' shared view do not overlap.
    DepthRangeOutsideOverlap {
        /// The range asked for, metres.
        near_m: f64,
        /// See `near_m`.
        far_m: f64,
        /// The depths the views share, metres.
        overlap_near_m: f64,
        /// See `overlap_near_m`.
        overlap_far_m: f64,
    },
}

impl StereoSearch {
    /// The hard filter for `config` on the rectified pair `rect`.
    pub fn new(config: &StereoConfig, rect: &Rectification) -> Result<Self, SearchError> {
        let fh = rect.focal_px * rect.baseline_m;
        let depth = |disparity: f64| depth_at(fh, disparity);
        let (overlap_min, overlap_max) = rect.overlap_disparity_px();
        let (min_disparity_px, max_disparity_px) =
            match (config.disparity_range_fraction, config.depth_range_m) {
                (Some(fraction), _) => (0.0, fraction * 2.0 * rect.half_width_px),
                (None, Some([near_m, far_m])) => {
                    let (min, max) = (
                        (fh / far_m).max(overlap_min).max(0.0),
                        (fh / near_m).min(overlap_max),
                    );
                    if min >= max {
                        return Err(SearchError::DepthRangeOutsideOverlap {
                            near_m,
                            far_m,
                            overlap_near_m: depth(overlap_max),
                            overlap_far_m: depth(overlap_min),
                        });
                    }
                    (min, max)
                }
                (None, None) => (overlap_min.max(0.0), overlap_max),
            };
        let epipolar_band_px = match config.epipolar_band_fraction {
            Some(fraction) => fraction * 2.0 * rect.half_height_px,
            None => config.epipolar_band_px,
        };
        Ok(Self {
            min_disparity_px,
            max_disparity_px,
            epipolar_band_px,
            near_m: depth(max_disparity_px),
            far_m: depth(min_disparity_px),
        })
    }
}

impl StereoSearch {
    /// This search with the disparity interval narrowed to `min_px..max_px` (kept inside its
    /// own); `focal_baseline` (f h, px m) turns disparities into depths.
    pub fn narrowed(&self, min_px: f64, max_px: f64, focal_baseline: f64) -> Self {
        let min_disparity_px = min_px.max(self.min_disparity_px);
        let max_disparity_px = max_px.min(self.max_disparity_px).max(min_disparity_px);
        Self {
            min_disparity_px,
            max_disparity_px,
            near_m: depth_at(focal_baseline, max_disparity_px),
            far_m: depth_at(focal_baseline, min_disparity_px),
            ..*self
        }
    }
}

/// The depth a disparity stands for in a rectified pair with focal length times baseline
/// `focal_baseline` (px m): infinite at zero disparity or below.
fn depth_at(focal_baseline: f64, disparity_px: f64) -> f64 {
    if disparity_px > 0.0 {
        focal_baseline / disparity_px
    } else {
        f64::INFINITY
    }
}

impl std::fmt::Display for StereoSearch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "depths {:.3}..{:.3} m (disparity {:.1}..{:.1} px), epipolar band {:.2} px",
            self.near_m,
            self.far_m,
            self.min_disparity_px,
            self.max_disparity_px,
            self.epipolar_band_px
        )
    }
}

/// Effective costs of (left track, right track) pairs that were candidates in the previous frame.
pub type PairHistory = BTreeMap<(u64, u64), f64>;

/// What stereo matching found in one frame.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct StereoMatch {
    /// `(left index, right index)`, sorted by left index.
    pub pairs: Vec<(usize, usize)>,
    /// Pairs that passed the hard filter, before assignment.
    pub candidates: usize,
    /// Left features with at least one candidate.
    pub left_with_candidates: usize,
}

/// Matches left to right features. `history` holds last frame's effective pair costs and is
/// replaced by this frame's.
pub fn match_stereo(
    left: &[LinkedFeature],
    right: &[LinkedFeature],
    scale: CostScale,
    search: &StereoSearch,
    history: &mut PairHistory,
    config: &StereoConfig,
) -> StereoMatch {
    let (min_disparity, max_disparity) = (search.min_disparity_px, search.max_disparity_px);
    let band = search.epipolar_band_px;
    let all = || left.iter().chain(right);
    let d_ave = normalising_mean(all().map(|f| f.feature.diameter_px));
    let b_ave = normalising_mean(all().map(|f| f.feature.brightness));
    let u_ave = normalising_mean(all().filter_map(LinkedFeature::speed_px));
    let passes = |l: &Feature, r: &Feature| {
        let disparity = l.rect.x - r.rect.x;
        disparity > min_disparity
            && disparity < max_disparity
            && (l.rect.y - r.rect.y).abs() <= band
    };

    let sorted = SortedByX::new(right.iter().map(|r| r.feature.rect));
    let memory = config.pair_memory;
    let mut next_history = PairHistory::new();
    let mut candidates = Vec::new();
    let mut left_with_candidates = 0;
    for (li, l) in left.iter().enumerate() {
        let before = candidates.len();
        let x = l.feature.rect.x;
        for ri in sorted.within(x - max_disparity, x - min_disparity) {
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
                    * ((l.feature.rect.y - r.feature.rect.y) / scale.half_height_px).powi(2)
                + config.weight_epipolar * ((l.feature.rect.y - r.feature.rect.y) / band).powi(2);
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
        left_with_candidates += usize::from(candidates.len() > before);
    }
    *history = next_history;
    let count = candidates.len();
    StereoMatch {
        pairs: assign(candidates, left.len(), right.len(), config.assignment),
        candidates: count,
        left_with_candidates,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::RectPoint;

    const SCALE: CostScale = CostScale {
        half_width_px: 320.0,
        half_height_px: 240.0,
    };

    /// The published method's search on SCALE: K = 0.25 of the width, S = 0.01 of the height.
    const SEARCH: StereoSearch = StereoSearch {
        min_disparity_px: 0.0,
        max_disparity_px: 160.0,
        epipolar_band_px: 4.8,
        near_m: 0.0,
        far_m: f64::INFINITY,
    };

    #[test]
    fn the_learnt_search_holds_the_tracks_and_not_a_ghost_minority() {
        let full = StereoSearch {
            min_disparity_px: 0.0,
            max_disparity_px: 640.0,
            epipolar_band_px: 2.0,
            near_m: 36.0 / 640.0,
            far_m: f64::INFINITY,
        };
        let mut learner = DepthLearner::new(full, 36.0);
        let mut rng = crate::synth::Rng::new(5);
        // 20 confirmed tracks a frame between 60 and 72 px, and one ghost anywhere in 3; the
        // learner is given their depths.
        let frame = |rng: &mut crate::synth::Rng, seq: u64| {
            let mut d: Vec<f64> = (0..20).map(|_| rng.range(60.0, 72.0)).collect();
            if seq.is_multiple_of(3) {
                d.push(rng.range(0.0, 640.0));
            }
            d.into_iter().map(|d| 36.0 / d).collect::<Vec<f64>>()
        };
        for seq in 1..=9 {
            let d = frame(&mut rng, seq);
            learner.add(seq, d.into_iter());
        }
        assert_eq!(learner.search(), None, "180 samples are too few");
        for seq in 10..=90 {
            let d = frame(&mut rng, seq);
            learner.add(seq, d.into_iter());
        }
        let learnt = learner.search().expect("learnt");
        // The 5th-95th percentiles (about 60.6..71.4) widened by their span and 2 px.
        assert!(
            (45.0..49.0).contains(&learnt.min_disparity_px)
                && (83.0..88.0).contains(&learnt.max_disparity_px),
            "{learnt:?}"
        );
        assert!((learnt.near_m - 36.0 / learnt.max_disparity_px).abs() < 1e-12);
        assert_eq!(learnt.epipolar_band_px, 2.0);
        // Tracks stop coming (the wearer looked elsewhere): the full search is back once
        // the window has passed.
        for seq in 91..=200 {
            learner.add(seq, std::iter::empty());
        }
        assert_eq!(learner.search(), None);
    }

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
            fixed: false,
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
            &SEARCH,
            &mut PairHistory::new(),
            &StereoConfig::default(),
        )
        .pairs;
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
            &SEARCH,
            &mut PairHistory::new(),
            &StereoConfig::default(),
        )
        .pairs;
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
                match_stereo(&left, &right, SCALE, &SEARCH, &mut history, &config).pairs,
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
            match_stereo(&left, &right, SCALE, &SEARCH, &mut fresh, &method).pairs,
            vec![(0, 1)]
        );
        assert_eq!(
            match_stereo(&left, &right, SCALE, &SEARCH, &mut history, &config).pairs,
            vec![(0, 0)]
        );
    }

    fn rectification(rig: &crate::geometry::StereoRig) -> Rectification {
        Rectification::new(rig).expect("a valid rig")
    }

    #[test]
    fn a_parallel_pair_searches_every_depth_its_views_share() {
        // f = 400 px, h = 0.1 m, 640 px wide: the views overlap from f h / 639 px = 0.063 m out.
        let rect = rectification(&crate::synth::parallel_rig(640, 480, 400.0, 0.1));
        let search = StereoSearch::new(&StereoConfig::default(), &rect).expect("search");
        assert_eq!(search.min_disparity_px, 0.0);
        assert!((search.max_disparity_px - 639.0).abs() < 1e-6, "{search}");
        assert!((search.near_m - 40.0 / 639.0).abs() < 1e-9, "{search}");
        assert!(search.far_m.is_infinite());
        assert_eq!(search.epipolar_band_px, 2.0);
    }

    #[test]
    fn a_depth_range_bounds_the_disparities_by_f_h_over_z() {
        let rect = rectification(&crate::synth::parallel_rig(640, 480, 400.0, 0.1));
        let config = StereoConfig {
            depth_range_m: Some([0.5, 2.0]),
            ..Default::default()
        };
        let search = StereoSearch::new(&config, &rect).expect("search");
        assert!((search.min_disparity_px - 20.0).abs() < 1e-9, "{search}");
        assert!((search.max_disparity_px - 80.0).abs() < 1e-9, "{search}");
        assert!((search.near_m - 0.5).abs() < 1e-12 && (search.far_m - 2.0).abs() < 1e-12);
        // A right particle 100 px left of its partner is nearer than 0.5 m: refused.
        let left = [linked(1, 50.0, 0.0, 5.0)];
        let near = [linked(2, -50.0, 0.0, 5.0)];
        let inside = [linked(3, -10.0, 0.0, 5.0)];
        let mut history = PairHistory::new();
        assert!(
            match_stereo(&left, &near, SCALE, &search, &mut history, &config)
                .pairs
                .is_empty()
        );
        assert_eq!(
            match_stereo(&left, &inside, SCALE, &search, &mut history, &config).pairs,
            vec![(0, 0)]
        );
    }

    #[test]
    fn a_depth_range_the_cameras_cannot_both_see_is_refused_with_the_range_they_can() {
        let rect = rectification(&crate::synth::parallel_rig(640, 480, 400.0, 0.1));
        let config = StereoConfig {
            depth_range_m: Some([0.01, 0.05]),
            ..Default::default()
        };
        let e = StereoSearch::new(&config, &rect).unwrap_err().to_string();
        assert!(e.contains("0.01..0.05") && e.contains("0.063..inf"), "{e}");
    }

    #[test]
    fn a_convergent_pair_searches_only_the_disparities_where_its_views_cross() {
        // Two 640x480 cameras, f = 2000 px (9 degrees half field of view), 0.3 m apart, each
        // turned 15 degrees inwards: the optical axes cross at 0.15 / tan(15 deg) = 0.56 m.
        let angle = 15f64.to_radians();
        let rig = crate::synth::convergent_rig(640, 480, 2000.0, 0.3, angle);
        let rect = rectification(&rig);
        let search = StereoSearch::new(&StereoConfig::default(), &rect).expect("search");
        // Depth along the common direction: the axes' crossing lies inside the range, and the
        // range is finite (beyond it the views part again); K as a fraction of the width
        // (0.25 x ~690 px) would have missed every particle near the crossing (~1,070 px).
        let crossing_disparity = rect.focal_px * rect.baseline_m / (0.15 / angle.tan());
        assert!(
            search.min_disparity_px < crossing_disparity
                && crossing_disparity < search.max_disparity_px,
            "{search}, crossing at {crossing_disparity:.1} px"
        );
        assert!(
            search.min_disparity_px > 0.0 && search.far_m.is_finite(),
            "{search}"
        );
        assert!(crossing_disparity > 0.25 * 2.0 * rect.half_width_px);
    }

    #[test]
    fn the_method_keeps_its_image_fractions() {
        let rect = rectification(&crate::synth::parallel_rig(640, 480, 400.0, 0.1));
        let search =
            StereoSearch::new(&crate::PipelineConfig::method().stereo, &rect).expect("search");
        assert!((search.max_disparity_px - 0.25 * 2.0 * rect.half_width_px).abs() < 1e-9);
        assert!((search.epipolar_band_px - 0.01 * 2.0 * rect.half_height_px).abs() < 1e-9);
    }
}
