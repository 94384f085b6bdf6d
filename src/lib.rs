//! # mrptv: the MR-PTV host service
//!
//! The algorithm is the `mrptv_engine` crate (detection, linking, stereo, 3D tracks, velocity,
//! the mean-flow field; geometry, synthesis and scoring): pure, synchronous, no I/O. This crate
//! is what surrounds it: files, the wire, the live service, Rerun and the command line.
//!
//! ## Layout
//! - [`recording`], [`tables`], [`config`]: the on-disk contract (recording directory, CSV files,
//!   TOML config), read and written with errors that name file, line and field; [`vtk`] writes
//!   tracks and fields for ParaView.
//! - [`offline`]: the offline commands' work (`synth`, `process`, `demo`), shared by the binary
//!   and the tests.
//! - [`protocol`]: the live wire protocol (`protocol/README.md`): JSON control messages, binary
//!   stereo frames and vector batches, coordinate conventions. Pure encode/decode; the `sparse`
//!   image encoding (particles exact, background coarse) is what fits a headset's Wi-Fi.
//! - [`server`]: `mrptv serve` (axum + tokio). A headset connection hands frames to its session's
//!   pipeline thread through a bounded drop-oldest queue; the pipeline thread sends the headset
//!   its [`protocol::Batch`]es, publishes them to viewers and feeds the session's recorder thread.
//! - [`client`]: the reference headset client (`mrptv replay`, and `serve --demo`'s synthetic
//!   headset).
//! - [`hl2ss`]: the hl2ss HoloLens 2 streaming app's wire formats, its row-vector poses, frame
//!   pairing, and a `rig.json` lens model fitted to its unprojection tables. [`hl2ss::bridge`]
//!   (`mrptv hl2ss`) turns its streams into a headset session; [`hl2ss::holograms`] draws the
//!   vectors back through its Unity plugin's message queue; [`video`] decodes its H.264.
//! - [`rerun_log`]: `--rerun` logging of runs and sessions to `.rrd` files, a viewer or a
//!   served gRPC log, on a logging thread behind a bounded queue.
//! - [`tls`]: certificates and TLS configurations of `serve --tls` and of wss:// clients.
//! - [`load`]: `mrptv load`, a bounded load test of a `serve` child process on loopback.
//!
//! What the binary, the tests and the fuzz targets use is `pub`; the rest is `pub(crate)`.
//!
//! Threads: a pipeline detects and links the left and right images of a frame in parallel, on
//! rayon's pool (one thread per core, shared by all sessions; `RAYON_NUM_THREADS` limits it);
//! everything after that runs on the caller's thread. Offline, a reader decodes PNGs one frame
//! ahead on a helper thread. Live, the tokio runtime runs the sockets; each session's pipeline
//! and recorder have their own OS threads, so CPU-bound work never stalls the network.
//! `docs/architecture.md` draws the whole.

pub mod client;
pub mod config;
#[doc(hidden)]
pub mod fuzzing;
pub mod hl2ss;
pub mod load;
pub mod offline;
pub mod protocol;
pub mod recording;
pub mod rerun_log;
pub mod server;
mod sparse;
pub mod tables;
pub mod tls;
pub mod video;
pub mod vtk;
