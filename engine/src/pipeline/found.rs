//! Track-first: the predicted particles measured in both images, and their tracks continued.
//! A prediction found by detections in both images is measured at them (refitted where its
//! image overlaps a neighbour's); one found in one image is looked for in the other image
//! itself, fitted where its track puts it among its neighbours, and continues its track where
//! both images show it on rows within the epipolar band (one found in neither coasts). A
//! particle one image shows and the other hides continues its track with a partial sample on
//! the first image's line of sight at its predicted depth, for at most M frames in a row:
//! measured across that line of sight, only predicted along it.

use super::{CameraOutput, FrameOutput, Pipeline, Spot, RELEARN_SHAPE_SAMPLES};
use crate::detect::{Detection, Separation};
use crate::geometry::{RectPoint, Rectification};
use crate::predict::Prediction;
use crate::shake::refine::{self, CameraShake, Measured, Shape};
use crate::shake::Shaken;
use crate::tracks::FoundSample;
use crate::{ImageView, StereoFrame};

/// A prediction and the feature it claimed in each image (left, right), if any.
type Looked = (usize, [Option<usize>; 2]);

/// What the predictions found (index for index with `looked`, `None` where the measurement did
/// not confirm the particle); the features of those not confirmed are left to the per-camera
/// chain, which may still pair them.
fn release_unconfirmed(
    looked: &[Looked],
    found: Vec<Option<FoundSample>>,
    shaken: &mut Shaken,
) -> Vec<FoundSample> {
    let mut confirmed = Vec::with_capacity(found.len());
    for (&(_, [l, r]), found) in looked.iter().zip(found) {
        match found {
            Some(sample) => confirmed.push(sample),
            None => {
                if let Some(l) = l {
                    shaken.claimed_left[l] = false;
                }
                if let Some(r) = r {
                    shaken.claimed_right[r] = false;
                }
            }
        }
    }
    confirmed
}

impl Pipeline {
    /// Continues the tracks whose predicted particles were measured in both images on rows
    /// within `band_px` of each other (or in one, with a partial sample), and marks every
    /// claimed detection as continuing a track; a prediction whose measurement did not confirm
    /// its particle leaves the detections it claimed to the per-camera chain.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn take_found(
        &mut self,
        frame: &StereoFrame<'_>,
        seq: u64,
        (left, right): (&CameraOutput, &CameraOutput),
        predictions: &[Prediction],
        shaken: &mut Shaken,
        band_px: f64,
        out: &mut FrameOutput,
    ) {
        let looked: Vec<Looked> = shaken
            .found
            .iter()
            .map(|f| (f.prediction, [Some(f.left), Some(f.right)]))
            .chain(shaken.partial.iter().copied())
            .collect();
        let measured = if looked.is_empty() {
            Vec::new()
        } else {
            self.measure_looked(frame, (left, right), predictions, &looked, out)
        };
        let found: Vec<Option<FoundSample>> = looked
            .iter()
            .zip(measured)
            .map(|(&(i, features), measured)| {
                let p = &predictions[i];
                let spots = self.spots(left, right, features, measured, out);
                // A particle hidden in one image continues its track for at most M frames in a
                // row: the reach of a velocity window centred on its last sample seen in both.
                let most = self.config.velocity.half_window_frames;
                if spots.iter().any(Option::is_none) && self.tracks.hidden_run(p.key) >= most {
                    return None;
                }
                let spots = partial(spots, p, &self.rectification)?;
                if (spots[0].rect.y - spots[1].rect.y).abs() > band_px {
                    return None;
                }
                let miss_px =
                    (spots[0].rect.distance_sq(p.left) + spots[1].rect.distance_sq(p.right)).sqrt();
                let (sample, point) = self.sample_at(frame, seq, spots)?;
                let camera_tracks = match features {
                    [Some(l), Some(r)] => Some((left.linked[l].track_id, right.linked[r].track_id)),
                    _ => None,
                };
                Some(FoundSample {
                    key: p.key,
                    sample,
                    miss_px,
                    point,
                    camera_tracks,
                })
            })
            .collect();
        out.stats.predicted = predictions.len();
        out.continued_left = left.continued(out.detections_left.len(), &shaken.claimed_left);
        out.continued_right = right.continued(out.detections_right.len(), &shaken.claimed_right);
        out.stats.linked_left = out.continued_left.iter().filter(|c| **c).count();
        out.stats.linked_right = out.continued_right.iter().filter(|c| **c).count();
        let found = release_unconfirmed(&looked, found, shaken);
        out.stats.found = found.len();
        self.tracks
            .take_found(found, (&mut out.points, &mut out.partial_points));
    }

    /// Where a looked-for particle is seen in each image: at its claimed feature as detected,
    /// or at its refitted centre (see [`refitted_separation`]); `None` where it is missing.
    fn spots(
        &self,
        left: &CameraOutput,
        right: &CameraOutput,
        features: [Option<usize>; 2],
        measured: [Measured; 2],
        out: &FrameOutput,
    ) -> [Option<Spot>; 2] {
        let cameras: [(&CameraOutput, &[Detection]); 2] =
            [(left, &out.detections_left), (right, &out.detections_right)];
        let spot = |c: usize| -> Option<Spot> {
            let (camera, detections) = cameras[c];
            let detection = features[c].map(|i| &detections[camera.detection_of[i]]);
            match measured[c] {
                Measured::Refitted(at) => Some(Spot {
                    rect: self.rectification.pixel_to_rect(c, at)?,
                    px: detection.map_or(at, |d| d.centroid),
                    separation: refitted_separation(detection),
                }),
                Measured::AsDetected => Some(camera.spot(features[c]?, detections)),
                Measured::Missing => None,
            }
        };
        [spot(0), spot(1)]
    }

    /// The looked-for particles measured in both images (`shake::refine::measure`), and the
    /// shapes their tracks learnt.
    fn measure_looked(
        &mut self,
        frame: &StereoFrame<'_>,
        (left, right): (&CameraOutput, &CameraOutput),
        predictions: &[Prediction],
        looked: &[Looked],
        out: &FrameOutput,
    ) -> Vec<[Measured; 2]> {
        let keys: Vec<u64> = looked.iter().map(|l| predictions[l.0].key).collect();
        let mut shapes: Vec<[Option<Shape>; 2]> =
            keys.iter().map(|&k| self.tracks.shapes(k)).collect();
        let relearn: Vec<bool> = keys
            .iter()
            .map(|&k| self.tracks.relearns(k, RELEARN_SHAPE_SAMPLES))
            .collect();
        let cameras = cameras(frame, (left, right), out);
        let wanted = |c: usize| wanted_in(c, &self.rectification, predictions, looked, &relearn);
        let (wanted_left, wanted_right) = (wanted(0), wanted(1));
        // Each camera borrows the other's shapes as its tracks knew them before this frame,
        // so the two cameras are measured at once, one core each.
        let column = |c: usize| -> Vec<Option<Shape>> { shapes.iter().map(|s| s[c]).collect() };
        let (mut own_left, mut own_right) = (column(0), column(1));
        let (other_left, other_right) = (own_right.clone(), own_left.clone());
        let measure =
            |shake: &mut CameraShake,
             (image, camera, detections): (ImageView<'_>, &CameraOutput, &[Detection]),
             wanted: &[refine::Wanted],
             own: &mut [Option<Shape>],
             other: &[Option<Shape>]| {
                shake.measure(image, &seen_by(camera, detections), wanted, own, other)
            };
        let [shake_left, shake_right] = &mut self.shake;
        let [left_camera, right_camera] = cameras;
        let (measured_left, measured_right) = rayon::join(
            || {
                measure(
                    shake_left,
                    left_camera,
                    &wanted_left,
                    &mut own_left,
                    &other_left,
                )
            },
            || {
                measure(
                    shake_right,
                    right_camera,
                    &wanted_right,
                    &mut own_right,
                    &other_right,
                )
            },
        );
        for (k, s) in shapes.iter_mut().enumerate() {
            *s = [own_left[k], own_right[k]];
        }
        let measured: Vec<[Measured; 2]> = measured_left
            .into_iter()
            .zip(measured_right)
            .map(|(l, r)| [l, r])
            .collect();
        for (&k, s) in keys.iter().zip(shapes) {
            self.tracks.set_shapes(k, s);
        }
        measured
    }

    /// The tracks the chain continued or started this frame (its stereo `pairs`, by feature
    /// index) learn their particles' shapes where they stand alone, so that a track knows its
    /// particle's shape before its image first overlaps another's.
    pub(super) fn learn_young_shapes(
        &mut self,
        frame: &StereoFrame<'_>,
        (left, right): (&CameraOutput, &CameraOutput),
        pairs: &[(usize, usize)],
        out: &FrameOutput,
    ) {
        let unknown = |s: &[Option<Shape>; 2]| s.iter().any(Option::is_none);
        let young: Vec<(u64, [usize; 2])> = pairs
            .iter()
            .map(|&(li, ri)| (left.linked[li].track_id, [li, ri]))
            .filter(|(key, _)| unknown(&self.tracks.shapes(*key)))
            .collect();
        if young.is_empty() {
            return;
        }
        let shapes: Vec<[Option<Shape>; 2]> =
            young.iter().map(|(k, _)| self.tracks.shapes(*k)).collect();
        let disparity =
            |[li, ri]: [usize; 2]| left.linked[li].feature.rect.x - right.linked[ri].feature.rect.x;
        // Each camera learns from its own image only: one core each, as when measuring.
        let learn = |shake: &mut CameraShake,
                     c: usize,
                     (image, camera, detections): (ImageView<'_>, &CameraOutput, &[Detection])|
         -> Vec<Option<Shape>> {
            let seen = seen_by(camera, detections);
            let wanted: Vec<refine::Wanted> = young
                .iter()
                .map(|&(_, features)| refine::Wanted {
                    detection: Some(features[c]),
                    predicted_px: None,
                    predicted_rect: seen[features[c]].rect,
                    disparity_px: disparity(features),
                    relearn: false,
                })
                .collect();
            let mut own: Vec<Option<Shape>> = shapes.iter().map(|s| s[c]).collect();
            shake.learn_shapes(image, &seen, &wanted, &mut own);
            own
        };
        let [left_camera, right_camera] = cameras(frame, (left, right), out);
        let [shake_left, shake_right] = &mut self.shake;
        let (own_left, own_right) = rayon::join(
            || learn(shake_left, 0, left_camera),
            || learn(shake_right, 1, right_camera),
        );
        let shapes = own_left.into_iter().zip(own_right).map(|(l, r)| [l, r]);
        for ((k, _), s) in young.iter().zip(shapes) {
            self.tracks.set_shapes(*k, s);
        }
    }
}

/// How a particle refitted among its neighbours was told apart: a clear detection stays clear
/// (the fit only took its neighbours' light out of its own pixels; which particle it is was
/// never in doubt, and the velocity fits may narrow their windows on it as on any clear
/// sample); any other, or one without a detection, was [`Separation::Fitted`].
fn refitted_separation(detection: Option<&Detection>) -> Separation {
    match detection {
        Some(d) if d.separation == Separation::Clear => Separation::Clear,
        _ => Separation::Fitted,
    }
}

/// A particle seen in both images, or in one: then it is placed on that image's line of sight
/// at its prediction's disparity (its predicted depth) in the other, [`Separation::Hidden`].
/// `None` where neither image shows it.
fn partial(
    [left, right]: [Option<Spot>; 2],
    p: &Prediction,
    rect: &Rectification,
) -> Option<[Spot; 2]> {
    let (seen, c) = match (left, right) {
        (Some(l), Some(r)) => return Some([l, r]),
        (Some(l), None) => (l, 0),
        (None, Some(r)) => (r, 1),
        (None, None) => return None,
    };
    // The hidden view is on the same rectified row, the predicted disparity to the left of a
    // left view (in the right image) or to the right of a right view (in the left image).
    let disparity = p.left.x - p.right.x;
    let at = RectPoint {
        x: seen.rect.x + if c == 0 { -disparity } else { disparity },
        ..seen.rect
    };
    let hidden = Spot {
        rect: at,
        px: rect.rect_to_pixel(1 - c, at)?,
        separation: Separation::Hidden,
    };
    Some(if c == 0 {
        [seen, hidden]
    } else {
        [hidden, seen]
    })
}

/// What camera `c`'s shake looks for: each looked-for prediction (`looked`) with the feature
/// it claimed there, where it is predicted, and whether its track learns its shape again
/// (`relearn`, index for index with `looked`).
fn wanted_in(
    c: usize,
    rect: &Rectification,
    predictions: &[Prediction],
    looked: &[Looked],
    relearn: &[bool],
) -> Vec<refine::Wanted> {
    looked
        .iter()
        .zip(relearn)
        .map(|(&(i, features), &relearn)| {
            let p = &predictions[i];
            refine::Wanted {
                detection: features[c],
                predicted_px: rect.rect_to_pixel(c, p.at(c)),
                predicted_rect: p.at(c),
                disparity_px: p.left.x - p.right.x,
                relearn,
            }
        })
        .collect()
}

/// Each camera's image, linked features and detections (left, right).
fn cameras<'a>(
    frame: &StereoFrame<'a>,
    (left, right): (&'a CameraOutput, &'a CameraOutput),
    out: &'a FrameOutput,
) -> [(ImageView<'a>, &'a CameraOutput, &'a [Detection]); 2] {
    [
        (frame.left, left, &out.detections_left),
        (frame.right, right, &out.detections_right),
    ]
}

/// One camera's linked features as its shake sees them.
fn seen_by(camera: &CameraOutput, detections: &[Detection]) -> Vec<refine::Seen> {
    camera
        .linked
        .iter()
        .zip(&camera.detection_of)
        .map(|(feature, &d)| {
            let d = &detections[d];
            refine::Seen {
                centroid: d.centroid,
                diameter_px: d.diameter_px,
                clear: d.separation == Separation::Clear,
                fitted: d.separation == Separation::Fitted,
                rect: feature.feature.rect,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::PixelPoint;
    use crate::synth::{Scenario, ScenarioSpec};

    fn spot(x: f64, y: f64) -> Spot {
        Spot {
            rect: RectPoint { x, y },
            px: PixelPoint { x, y },
            separation: Separation::Clear,
        }
    }

    #[test]
    fn a_particle_one_image_hides_is_placed_on_the_other_ones_line_of_sight_at_its_predicted_depth()
    {
        let rect = Rectification::new(&ScenarioSpec::new(Scenario::Flume).rig).expect("rectifies");
        let p = Prediction {
            key: 1,
            left: RectPoint { x: 12.0, y: 5.0 },
            right: RectPoint { x: -18.0, y: 5.0 },
            gate_px: 1.0,
        };
        let [l, r] = partial([Some(spot(13.0, 6.0)), None], &p, &rect).expect("one image");
        assert_eq!(
            (l.separation, r.separation),
            (Separation::Clear, Separation::Hidden)
        );
        assert_eq!((r.rect.x, r.rect.y), (13.0 - 30.0, 6.0));
        let [l, r] = partial([None, Some(spot(-17.0, 4.0))], &p, &rect).expect("one image");
        assert_eq!(
            (l.separation, r.separation),
            (Separation::Hidden, Separation::Clear)
        );
        assert_eq!((l.rect.x, l.rect.y), (-17.0 + 30.0, 4.0));
        assert!(partial([None, None], &p, &rect).is_none());
        let both = partial([Some(spot(13.0, 6.0)), Some(spot(-17.0, 6.0))], &p, &rect);
        assert!(both.is_some_and(|s| s.iter().all(|s| s.separation == Separation::Clear)));
    }
}
