//! One camera's own stages: detection, rectification and per-camera linking.

use super::{PipelineConfig, Spot};
use crate::detect::{Detection, Detector, Parting};
use crate::geometry::{PixelPoint, RectPoint};
use crate::link::{CameraLinker, CostScale, Feature, LinkedFeature};
use crate::shake::refine::{CameraShake, Shape};
use crate::spatial::{PointGrid, GRID_CELL_PX};
use crate::ImageView;

/// One camera's stages, which need nothing from the other camera: detection, rectification and
/// per-camera linking.
pub(super) struct Camera {
    pub(super) detector: Detector,
    linker: CameraLinker,
}

/// What the 3D tracks expect in one camera's image (track-first; none otherwise): each
/// prediction (rectified) with its gate and its particle's shape in this camera, and what the
/// camera's shake has learnt, to part the regions several of them fall on.
pub(super) struct Expected<'a> {
    pub(super) predicted: Vec<(RectPoint, f64, Option<Shape>)>,
    pub(super) shake: &'a CameraShake,
}

/// A camera's linked features and, index for index, the detection each came from.
pub(super) struct CameraOutput {
    pub(super) linked: Vec<LinkedFeature>,
    pub(super) detection_of: Vec<usize>,
}

impl CameraOutput {
    /// Per detection (of `detections`), whether its feature continues a track from an earlier
    /// frame: a 2D track, or a 3D track's prediction that `claimed` it (index for index with
    /// the features).
    pub(super) fn continued(&self, detections: usize, claimed: &[bool]) -> Vec<bool> {
        let mut continued = vec![false; detections];
        for ((feature, &d), &claimed) in self.linked.iter().zip(&self.detection_of).zip(claimed) {
            continued[d] |= feature.age > 1 || claimed;
        }
        continued
    }

    /// Where feature `i` is seen, as detected (`detections`: this camera's).
    pub(super) fn spot(&self, i: usize, detections: &[Detection]) -> Spot {
        let d = &detections[self.detection_of[i]];
        Spot {
            rect: self.linked[i].feature.rect,
            px: d.centroid,
            separation: d.separation,
        }
    }
}

impl Camera {
    pub(super) fn new() -> Self {
        Self {
            detector: Detector::new(),
            linker: CameraLinker::new(),
        }
    }

    /// Detects into `detections` (regions a 3D track's predicted position falls on are left
    /// to that track's fit), looking again where the tracks expect particles (the 2D tracks'
    /// expectations and the 3D tracks' predictions, `expected`), and links the rectified
    /// features (detections whose centroid the lens model cannot undistort are left out). With
    /// tracks first, a region is parted with the tracks' shapes (without, fitted as spots).
    /// `to_rect` and `from_rect` map this camera's raw pixels to the rectified image and back.
    pub(super) fn push(
        &mut self,
        image: ImageView<'_>,
        config: &PipelineConfig,
        scale: CostScale,
        detections: &mut Vec<Detection>,
        expected: &Expected<'_>,
        (to_rect, from_rect): (
            impl Fn(PixelPoint) -> Option<RectPoint>,
            impl Fn(RectPoint) -> Option<PixelPoint>,
        ),
    ) -> CameraOutput {
        let (tracked, shapes): (Vec<PixelPoint>, Vec<Option<Shape>>) = expected
            .predicted
            .iter()
            .filter_map(|&(rect, _, shape)| Some((from_rect(rect)?, shape)))
            .unzip();
        self.detector
            .detect_tracked(image, &config.detect, &tracked, detections);
        if config.detect.separate_expected {
            // The 3D tracks' predictions first, then the 2D tracks' own expectations.
            let mut points = tracked;
            points.extend(
                uncovered_expectations(&self.linker, &expected.predicted).filter_map(&from_rect),
            );
            let part = |group: &[usize], pixels: &[(f64, f64, f64)], share_px: f64| {
                let seeds: Vec<(PixelPoint, Option<Shape>)> = group
                    .iter()
                    .map(|&i| (points[i], shapes.get(i).copied().flatten()))
                    .collect();
                expected.shake.part(image, pixels, &seeds, share_px)
            };
            let parting: Option<Parting<'_>> = config.tracks.track_first.then_some(&part);
            self.detector
                .separate_expected(image, &config.detect, &points, parting, detections);
        }
        let (features, detection_of): (Vec<Feature>, Vec<usize>) = detections
            .iter()
            .enumerate()
            .filter_map(|(i, d)| {
                to_rect(d.centroid).map(|rect| {
                    (
                        Feature {
                            rect,
                            diameter_px: d.diameter_px,
                            brightness: d.brightness,
                        },
                        i,
                    )
                })
            })
            .unzip();
        CameraOutput {
            linked: self.linker.push(&features, scale, &config.link),
            detection_of,
        }
    }
}

/// The 2D tracks' expectations (rectified) that no 3D track's prediction (`(point, gate)`)
/// covers: two expectations of one particle would be fitted as two particles.
fn uncovered_expectations<'a>(
    linker: &'a CameraLinker,
    predicted: &'a [(RectPoint, f64, Option<Shape>)],
) -> impl Iterator<Item = RectPoint> + 'a {
    let largest_gate = predicted.iter().map(|p| p.1).fold(0.0, f64::max);
    let grid = PointGrid::new(
        predicted.iter().enumerate().map(|(i, p)| (p.0, i)),
        GRID_CELL_PX,
    );
    let covered = move |e: &RectPoint| {
        grid.near(e.x, e.y, largest_gate).any(|(p, i)| {
            let gate = predicted[*i].1;
            (p.x - e.x).powi(2) + (p.y - e.y).powi(2) <= gate * gate
        })
    };
    linker.expected_positions().filter(move |e| !covered(e))
}
