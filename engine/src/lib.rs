//! # mrptv-engine: the MR-PTV algorithm
//!
//! Two synchronized grayscale cameras in, 3D particle velocities out (Chivers 2023, MR-PTV).
//! Pure and synchronous: no I/O, no clock, no async.

pub mod config;
pub mod detect;
pub mod eval;
pub mod field;
mod frame;
pub mod geometry;
pub mod health;
pub mod link;
pub mod pipeline;
mod spatial;
pub mod stereo;
pub mod synth;
pub mod tracks;
pub mod velocity;

pub use detect::{Detection, Detector};
pub use frame::{ImageView, StereoFrame};
pub use pipeline::{
    FrameOutput, FrameStats, MatchedPoint, Pipeline, PipelineConfig, PipelineError,
};
pub use stereo::StereoSearch;
pub use velocity::VelocityVector;
