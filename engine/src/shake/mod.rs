//! Track-first step 2: each predicted particle is looked for in both images at once. Its
//! detections are the left and right features nearest its two projections, within its gate,
//! settled for all tracks together (globally cheapest first, each feature used once): the two
//! projections are consistent by construction, so no pair has to be chosen among epipolar
//! candidates; the two features must still lie on rows within the epipolar band of each other
//! (a track that drifted onto two different particles is not found). Touching images were
//! already parted by fits seeded at the predictions
//! ([`crate::Detector::separate_expected`]); [`refine`] measures the found particles whose
//! images still overlap with the shapes their tracks learnt.
//!
//! A track found in one image only is looked for again in the other where the first image's
//! detection puts it (a track that missed its path misses it alike in both images); one still
//! found in one image only claims that detection (it is explained, and must not pair with
//! another particle's), and [`refine`] looks for its particle in the other image itself.
//! A track found in neither coasts: a particle neither detector saw near its projections is not
//! looked for by fits alone, as fits free to take light wherever it lies keep a ghost (a wrong
//! pair, a room's texture) going on light no particle made. A track carried by its
//! neighbours' flow (too young for a motion of its own) is looked for the same way: left to
//! the per-frame chain, a young track broke wherever a neighbour hid its particle in one image.

pub(crate) mod refine;

use crate::geometry::RectPoint;
use crate::link::LinkedFeature;
use crate::predict::Prediction;
use crate::spatial::{assign, Assignment, PointGrid, GRID_CELL_PX};

/// A predicted particle found in both images.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Found {
    /// The prediction's index.
    pub(crate) prediction: usize,
    /// The left feature's index.
    pub(crate) left: usize,
    /// The right feature's index.
    pub(crate) right: usize,
    /// Distance of the two features from the two projections, root of the summed squares,
    /// rectified pixels.
    pub(crate) miss_px: f64,
}

/// What the predictions found in this frame's features.
#[derive(Debug, Default)]
pub(crate) struct Shaken {
    /// Particles found in both images.
    pub(crate) found: Vec<Found>,
    /// Per left feature, whether a prediction claimed it.
    pub(crate) claimed_left: Vec<bool>,
    /// Per right feature, whether a prediction claimed it.
    pub(crate) claimed_right: Vec<bool>,
    /// Every prediction found in one image only, with the feature it claimed in each (left,
    /// right): [`refine`] looks for it in the other image itself.
    pub(crate) partial: Vec<(usize, [Option<usize>; 2])>,
}

/// Looks for every prediction among the left and right features (fixtures never count); a
/// left and a right feature are one particle only on rows within `band_px` of each other, as
/// for a stereo pair.
pub(crate) fn find(
    predictions: &[Prediction],
    left: &[LinkedFeature],
    right: &[LinkedFeature],
    band_px: f64,
) -> Shaken {
    if predictions.is_empty() {
        return Shaken {
            claimed_left: vec![false; left.len()],
            claimed_right: vec![false; right.len()],
            ..Default::default()
        };
    }
    let left_near = near_each(predictions, left, |p| p.left);
    let right_near = near_each(predictions, right, |p| p.right);
    let mut both: Vec<(f64, usize, usize, usize)> = Vec::new();
    for (i, (ls, rs)) in left_near.iter().zip(&right_near).enumerate() {
        for &(dl, l) in ls {
            let row = left[l].feature.rect.y;
            for &(dr, r) in rs {
                if (right[r].feature.rect.y - row).abs() <= band_px {
                    both.push((dl + dr, i, l, r));
                }
            }
        }
    }
    both.sort_by(|a, b| {
        a.0.total_cmp(&b.0)
            .then((a.1, a.2, a.3).cmp(&(b.1, b.2, b.3)))
    });
    let mut done = vec![false; predictions.len()];
    let mut shaken = Shaken {
        claimed_left: vec![false; left.len()],
        claimed_right: vec![false; right.len()],
        ..Default::default()
    };
    for (cost, i, l, r) in both {
        if done[i] || shaken.claimed_left[l] || shaken.claimed_right[r] {
            continue;
        }
        done[i] = true;
        shaken.claimed_left[l] = true;
        shaken.claimed_right[r] = true;
        let miss_px = cost.sqrt();
        shaken.found.push(Found {
            prediction: i,
            left: l,
            right: r,
            miss_px,
        });
    }
    let left_single = claim_single(&left_near, &done, &mut shaken.claimed_left);
    let right_single = claim_single(&right_near, &done, &mut shaken.claimed_right);
    let again = look_again(
        predictions,
        [left, right],
        [&left_single, &right_single],
        band_px,
        [&mut shaken.claimed_left, &mut shaken.claimed_right],
    );
    for f in again {
        done[f.prediction] = true;
        shaken.found.push(f);
    }
    shaken.partial = (0..predictions.len())
        .filter(|&i| !done[i])
        .map(|i| (i, [left_single[i], right_single[i]]))
        .filter(|(_, features)| features.iter().any(Option::is_some))
        .collect();
    shaken.found.sort_by_key(|f| f.prediction);
    shaken
}

/// Per prediction, the features within its gate of its projection (`at`), with their squared
/// distances.
fn near_each(
    predictions: &[Prediction],
    features: &[LinkedFeature],
    at: impl Fn(&Prediction) -> crate::geometry::RectPoint,
) -> Vec<Vec<(f64, usize)>> {
    let grid = PointGrid::new(
        features
            .iter()
            .enumerate()
            .filter(|(_, f)| !f.fixed)
            .map(|(i, f)| (f.feature.rect, i)),
        GRID_CELL_PX,
    );
    predictions
        .iter()
        .map(|p| {
            let c = at(p);
            let gate_sq = p.gate_px * p.gate_px;
            grid.near(c.x, c.y, p.gate_px)
                .map(|(q, i)| ((q.x - c.x).powi(2) + (q.y - c.y).powi(2), *i))
                .filter(|(d, _)| *d <= gate_sq)
                .collect()
        })
        .collect()
}

/// Predictions found in one image only (`singles`, per camera: the feature each claimed there)
/// looked for again in the other image where the first image's feature puts them: on its row
/// (the rectified rows of one particle agree), and as far along it from the projection there
/// as the first feature lies from its own projection, within the prediction's gate. A track's
/// miss of its path (a turn, a speed change) moves its particle alike in both images; what
/// differs between them is its error in depth. Settled cheapest first, each free feature once;
/// the features found are claimed.
fn look_again(
    predictions: &[Prediction],
    features: [&[LinkedFeature]; 2],
    singles: [&[Option<usize>]; 2],
    band_px: f64,
    claimed: [&mut [bool]; 2],
) -> Vec<Found> {
    let grids = features.map(|fs| {
        PointGrid::new(
            fs.iter()
                .enumerate()
                .filter(|(_, f)| !f.fixed)
                .map(|(i, f)| (f.feature.rect, i)),
            GRID_CELL_PX,
        )
    });
    // The camera each prediction was seen in and the feature it claimed there.
    let seen_in = |i: usize| match (singles[0][i], singles[1][i]) {
        (Some(l), None) => Some((0, l)),
        (None, Some(r)) => Some((1, r)),
        _ => None,
    };
    // Candidates (squared distance from the shifted projection, prediction, the other camera's
    // feature), the right image's features numbered after the left's so that one assignment
    // settles both cameras.
    let offset = [0, features[0].len()];
    let mut candidates: Vec<(f64, usize, usize)> = Vec::new();
    for (i, p) in predictions.iter().enumerate() {
        let Some((c, seen)) = seen_in(i) else {
            continue;
        };
        let at = features[c][seen].feature.rect;
        let (own, other) = (p.at(c), p.at(1 - c));
        let shifted = RectPoint {
            x: other.x + at.x - own.x,
            y: other.y + at.y - own.y,
        };
        for &(q, j) in grids[1 - c].near(shifted.x, shifted.y, p.gate_px) {
            let d_sq = q.distance_sq(shifted);
            if !claimed[1 - c][j] && d_sq <= p.gate_px * p.gate_px && (q.y - at.y).abs() <= band_px
            {
                candidates.push((d_sq, i, offset[1 - c] + j));
            }
        }
    }
    let columns = features[0].len() + features[1].len();
    assign(candidates, predictions.len(), columns, Assignment::OneToOne)
        .into_iter()
        .filter_map(|(i, column)| {
            let (c, seen) = seen_in(i)?;
            let other = column - offset[1 - c];
            claimed[1 - c][other] = true;
            let p = &predictions[i];
            let miss_sq = features[c][seen].feature.rect.distance_sq(p.at(c))
                + features[1 - c][other].feature.rect.distance_sq(p.at(1 - c));
            let [left, right] = if c == 0 { [seen, other] } else { [other, seen] };
            Some(Found {
                prediction: i,
                left,
                right,
                miss_px: miss_sq.sqrt(),
            })
        })
        .collect()
}

/// Predictions found in one image only claim their nearest free feature there: per
/// prediction, the feature it claimed.
fn claim_single(
    near: &[Vec<(f64, usize)>],
    done: &[bool],
    claimed: &mut [bool],
) -> Vec<Option<usize>> {
    let mut single: Vec<(f64, usize, usize)> = near
        .iter()
        .enumerate()
        .filter(|(i, _)| !done[*i])
        .flat_map(|(i, fs)| fs.iter().map(move |&(d, f)| (d, i, f)))
        .collect();
    single.sort_by(|a, b| a.0.total_cmp(&b.0).then((a.1, a.2).cmp(&(b.1, b.2))));
    let mut taken = vec![None; near.len()];
    for (_, i, f) in single {
        if taken[i].is_none() && !claimed[f] {
            taken[i] = Some(f);
            claimed[f] = true;
        }
    }
    taken
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::RectPoint;
    use crate::link::Feature;

    fn feature(x: f64, y: f64) -> LinkedFeature {
        LinkedFeature {
            feature: Feature {
                rect: RectPoint { x, y },
                diameter_px: 4.0,
                brightness: 100.0,
            },
            track_id: 1,
            motion_px: None,
            age: 1,
            fixed: false,
        }
    }

    fn prediction(key: u64, lx: f64, rx: f64, y: f64) -> Prediction {
        Prediction {
            key,
            left: RectPoint { x: lx, y },
            right: RectPoint { x: rx, y },
            gate_px: 2.0,
        }
    }

    #[test]
    fn each_feature_serves_one_track_the_closest_first() {
        // Two tracks predicted half a pixel apart in the left image, one feature there:
        // the closer track takes it in both images; the other finds only its right feature.
        let predictions = [prediction(1, 10.0, 0.0, 5.0), prediction(2, 10.5, 6.0, 5.0)];
        let left = [feature(10.1, 5.0)];
        let right = [feature(0.2, 5.1), feature(6.0, 5.0), feature(30.0, 5.0)];
        let s = find(&predictions, &left, &right, 2.0);
        assert_eq!(s.found.len(), 1);
        assert_eq!(
            (s.found[0].prediction, s.found[0].left, s.found[0].right),
            (0, 0, 0)
        );
        assert!((s.found[0].miss_px - (0.01f64 + 0.04 + 0.01).sqrt()).abs() < 1e-12);
        assert_eq!(s.claimed_left, [true]);
        assert_eq!(
            s.claimed_right,
            [true, true, false],
            "the second track's own detection"
        );
        assert_eq!(s.partial, [(1, [None, Some(1)])]);
    }

    #[test]
    fn nothing_outside_the_gate_and_no_fixture_is_found() {
        let predictions = [prediction(1, 10.0, 0.0, 5.0)];
        let mut fixture = feature(10.0, 5.0);
        fixture.fixed = true;
        let s = find(
            &predictions,
            &[fixture, feature(13.0, 5.0)],
            &[feature(0.0, 5.0)],
            2.0,
        );
        assert!(s.found.is_empty());
        assert_eq!(s.claimed_left, [false, false]);
        assert_eq!(s.claimed_right, [true]);
    }

    #[test]
    fn a_track_no_detector_saw_is_not_looked_for() {
        // One prediction near a right feature only, one near nothing at all.
        let predictions = [
            prediction(1, 10.0, 0.0, 5.0),
            prediction(2, 40.0, 30.0, 5.0),
        ];
        let s = find(
            &predictions,
            &[feature(20.0, 5.0)],
            &[feature(0.5, 5.0)],
            2.0,
        );
        assert!(s.found.is_empty());
        assert_eq!(s.partial, [(0, [None, Some(0)])], "the second coasts");
    }

    #[test]
    fn a_track_that_missed_its_path_is_found_where_its_first_image_puts_it() {
        // The particle turned off its predicted path: its left feature lies 1.5 px from the
        // left projection (within the gate of 2 px), its right one 3 px from the right
        // projection (beyond the gate), 1.5 px from where the left offset puts it.
        let predictions = [prediction(1, 10.0, 0.0, 5.0)];
        let left = [feature(11.5, 5.0)];
        let right = [feature(3.0, 5.0)];
        let s = find(&predictions, &left, &right, 2.0);
        assert_eq!(s.found.len(), 1, "{s:?}");
        assert_eq!((s.found[0].left, s.found[0].right), (0, 0));
        assert!((s.found[0].miss_px - (1.5f64.powi(2) + 3.0f64.powi(2)).sqrt()).abs() < 1e-12);
        assert!(s.partial.is_empty());
        assert_eq!((s.claimed_left, s.claimed_right), (vec![true], vec![true]));
    }

    #[test]
    fn a_second_look_keeps_to_the_row_and_to_free_features() {
        let predictions = [prediction(1, 10.0, 0.0, 5.0)];
        let left = [feature(11.5, 5.0)];
        // Within the gate of the shifted projection, but on a row 1.9 px from the left
        // feature's, outside a band of 1 px: another particle.
        let s = find(&predictions, &left, &[feature(1.5, 6.9)], 1.0);
        assert!(s.found.is_empty());
        assert_eq!(s.partial, [(0, [Some(0), None])]);
        // Two tracks, the first found in both images; the second's shifted projection lands on
        // the first's right feature, which is not free.
        let predictions = [
            prediction(1, 10.0, 0.0, 5.0),
            prediction(2, 20.0, -3.0, 5.0),
        ];
        let left = [feature(10.0, 5.0), feature(21.5, 5.0)];
        let right = [feature(0.0, 5.0)];
        let s = find(&predictions, &left, &right, 2.0);
        assert_eq!(s.found.len(), 1);
        assert_eq!(s.found[0].prediction, 0);
        assert_eq!(s.partial, [(1, [Some(1), None])]);
    }

    #[test]
    fn a_left_and_a_right_feature_on_rows_apart_are_not_one_particle() {
        let mut p = prediction(1, 10.0, 0.0, 5.0);
        p.gate_px = 3.0;
        let (left, right) = ([feature(10.0, 4.0)], [feature(0.0, 6.5)]);
        assert!(find(&[p], &left, &right, 2.0).found.is_empty());
        assert_eq!(find(&[p], &left, &right, 3.0).found.len(), 1);
    }
}
