//! # mrptv-engine: the MR-PTV algorithm
//!
//! Two synchronized grayscale cameras in, 3D particle velocities out (Chivers 2023, MR-PTV).
//! Pure and synchronous: no I/O, no clock, no async.

pub mod detect;
pub mod eval;
pub mod field;
mod frame;
mod spatial;
pub mod geometry;
pub mod kinematics;
pub mod link;
pub mod pipeline;
pub mod stereo;
pub mod synth;

pub use detect::{Detection, Detector};
pub use frame::{ImageView, StereoFrame};
pub use pipeline::{
    FrameOutput, FrameStats, MatchedPoint, Pipeline, PipelineConfig, PipelineError, VelocityVector,
};
pub use stereo::StereoSearch;
