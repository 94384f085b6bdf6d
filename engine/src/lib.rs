//! # mrptv-engine: the MR-PTV algorithm
//!
//! Two synchronized grayscale cameras in, 3D particle velocities out (Chivers 2023, MR-PTV).
//! Pure and synchronous: no I/O, no clock, no async. The service crate (`mrptv`) reads
//! recordings, runs the live server and logs to Rerun around it.
//!
//! ## Layout: the stages in the order a frame goes through them
//!
//! | stage | module | in | out |
//! |---|---|---|---|
//! | prediction (`link.track_first`) | `predict` | live 3D tracks | each one's position now, projected into both rectified images, with a gate learnt from its misses |
//! | detection, per image | [`detect`] | [`ImageView`] | [`Detection`]s (centroid, diameter D, brightness B) |
//! | rectification | [`geometry`] | raw [`geometry::PixelPoint`] | [`geometry::RectPoint`] in a virtual co-directional pair |
//! | 2D linking, per camera | [`link`] | [`link::Feature`]s of a frame | [`link::LinkedFeature`]s (a 2D track id, a motion) |
//! | finding the predicted (`link.track_first`) | `shake` | predictions, both cameras' features and images | tracks continued by the features nearest their projections (overlapping ones refitted with their tracks' learnt shapes); those features claimed |
//! | stereo matching | [`stereo`] | left and right linked features no prediction claimed | pairs `(left, right)` |
//! | triangulation | [`geometry::Rectification::triangulate`] | a pair | a point in the rig frame, then `point_in_world = world_from_rig * point_in_rig` |
//! | 3D tracks | [`tracks`] | the frame's triangulated pairs | 3D tracks (continued, rejoined, new, retired) |
//! | velocity | [`velocity`] | 3D tracks | [`VelocityVector`]s with 1-sigma errors, centred (M frames late) and causal |
//! | mean-flow field | [`field`] | vectors | cells of a world-anchored grid |
//!
//! [`Pipeline`] owns every stage's state: `push(&StereoFrame) -> FrameOutput`, one frame at a
//! time; its [`PipelineConfig`] has one config per stage, each with its defaults, its
//! published-method values and its validation ([`config::ConfigError`]). Around it: [`synth`]
//! renders scenarios with known truth, [`eval`] scores vectors against truth, [`health`] puts
//! a run's figures into words. `spatial` (private) holds the grids, sorts, medians and
//! assignment the stages share.
//!
//! ## Threads
//!
//! [`Pipeline::push`] detects and links the left and right images in parallel on rayon's pool
//! (one thread per core, shared by every pipeline of a process; `RAYON_NUM_THREADS` limits
//! it); the results do not depend on which camera finishes first. Everything after that runs
//! on the caller's thread.

pub mod config;
pub mod detect;
pub mod eval;
pub mod field;
mod frame;
pub mod geometry;
pub mod health;
pub mod link;
pub mod pipeline;
mod predict;
mod shake;
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
