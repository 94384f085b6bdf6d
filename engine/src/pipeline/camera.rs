//! One camera's own stages: detection, rectification and per-camera linking.

use super::PipelineConfig;
use crate::detect::{Detection, Detector};
use crate::geometry::{PixelPoint, RectPoint};
use crate::link::{CameraLinker, CostScale, Feature, LinkedFeature};
use crate::ImageView;

/// One camera's stages, which need nothing from the other camera: detection, rectification and
/// per-camera linking.
pub(super) struct Camera {
    pub(super) detector: Detector,
    linker: CameraLinker,
}

/// A camera's linked features and, index for index, the detection each came from.
pub(super) struct CameraOutput {
    pub(super) linked: Vec<LinkedFeature>,
    pub(super) detection_of: Vec<usize>,
}

impl CameraOutput {
    /// Per detection (of `detections`), whether its feature continues a track from an earlier
    /// frame.
    pub(super) fn continued(&self, detections: usize) -> Vec<bool> {
        let mut continued = vec![false; detections];
        for (feature, &d) in self.linked.iter().zip(&self.detection_of) {
            continued[d] |= feature.age > 1;
        }
        continued
    }
}

impl Camera {
    pub(super) fn new() -> Self {
        Self {
            detector: Detector::new(),
            linker: CameraLinker::new(),
        }
    }

    /// Detects into `detections`, looking again where the tracks expect particles, and links
    /// the rectified features (detections whose centroid the lens model cannot undistort are
    /// left out).
    pub(super) fn push(
        &mut self,
        image: ImageView<'_>,
        config: &PipelineConfig,
        scale: CostScale,
        detections: &mut Vec<Detection>,
        to_rect: impl Fn(PixelPoint) -> Option<RectPoint>,
        from_rect: impl Fn(RectPoint) -> Option<PixelPoint>,
    ) -> CameraOutput {
        self.detector.detect(image, &config.detect, detections);
        if config.detect.separate_expected {
            let expected: Vec<PixelPoint> = self
                .linker
                .expected_positions()
                .filter_map(&from_rect)
                .collect();
            self.detector
                .separate_expected(image, &config.detect, &expected, detections);
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
