//! Rerun logging (`--rerun`): the calibration, poses, images, detections, 3D particles, track
//! histories, velocity arrows and per-frame figures of a run, to an `.rrd` file, a running
//! viewer over gRPC, or both.
//!
//! The pipeline never waits for Rerun: frames go to a logging thread through a bounded channel
//! and are dropped (counted) when it is full; a failing sink is reported once.
//!
//! Entity paths (all positions in metres; the world and rig frames use OpenCV axes, RDF):
//! - `world`: view coordinates (static)
//! - `world/rig`: the head pose `world_from_rig` per frame
//! - `world/rig/left`, `world/rig/right`: camera transforms and pinholes (static);
//!   `.../image` (every Nth frame), `.../detections` (2D centroids, radius D/2)
//! - `world/points`: matched particles; `world/tracks`: recent track histories
//! - `world/vectors`: refined velocity arrows, logged at the frame they describe;
//!   `world/vectors_live`: causal arrows; both coloured by speed (see `legend`), each labelled
//!   (labels hidden; shown on hover) with its 1-sigma velocity errors
//! - `world/field`: the mean-flow field, an arrow per grid cell at its centre (mean velocity,
//!   coloured by speed; cells of fewer than 20 samples faded), logged as it updates
//! - `plots/*`: detections per camera, matches, tracks, vectors, processing and latency times
//! - `legend`: the speed colour map and arrow scale, as text
//!
//! Timelines: `frame` (frame index) and `sensor_time` (the frames' timestamps, seconds).

use std::collections::{BTreeMap, VecDeque};
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{sync_channel, SyncSender, TrySendError};
use std::sync::Arc;

use nalgebra::{Isometry3, Point3};
use rerun::RecordingStream;

use mrptv_engine::field::CellSummary;
use mrptv_engine::geometry::{CameraModel, StereoRig};
use mrptv_engine::{Detection, FrameOutput, FrameStats, MatchedPoint, VelocityVector};

/// Where a run is logged.
#[derive(Debug, Clone, PartialEq)]
pub enum RerunSink {
    /// An `.rrd` file (for the server: a directory, one file per session).
    File(PathBuf),
    /// A running viewer, e.g. `rerun+http://127.0.0.1:9876/proxy` (start one with `rerun`).
    Connect(String),
    /// Serve the log over gRPC on this port of 127.0.0.1 for viewers to connect to
    /// (`rerun --connect rerun+http://127.0.0.1:PORT/proxy`); see [`RerunProxy`].
    Serve(u16),
}

pub(crate) const DEFAULT_VIEWER_URL: &str = "rerun+http://127.0.0.1:9876/proxy";
pub(crate) const DEFAULT_SERVE_PORT: u16 = 9876;

/// A Rerun gRPC server (Rerun's message proxy) on 127.0.0.1, alive as long as this value.
/// Viewers connect to it; mrptv's recordings are sent to it like to any viewer, so one server
/// carries every session and keeps their history for viewers that connect later (within its
/// memory limit, a quarter of RAM by default).
pub struct RerunProxy {
    server: Option<rerun::grpc_server::GrpcServerSink>,
    port: u16,
    url: String,
}

impl RerunProxy {
    pub fn start(port: u16) -> Result<Self, RerunError> {
        // The server binds on its own thread, where a failure could only be logged: try first.
        std::net::TcpListener::bind(("127.0.0.1", port))
            .map_err(|e| RerunError::Stream(format!("cannot serve on 127.0.0.1:{port}: {e}")))?;
        let server = rerun::grpc_server::GrpcServerSink::new(
            "127.0.0.1",
            port,
            rerun::ServerOptions::default(),
        )
        .map_err(|e| RerunError::Stream(e.to_string()))?;
        // Serving once it accepts connections, so that logs sent right away are taken.
        if !accepts_within(port, true) {
            return Err(RerunError::Stream(format!(
                "the Rerun gRPC server did not start on 127.0.0.1:{port}"
            )));
        }
        Ok(Self {
            server: Some(server),
            port,
            url: format!("rerun+http://127.0.0.1:{port}/proxy"),
        })
    }

    /// For viewers: `rerun --connect URL`.
    pub fn url(&self) -> &str {
        &self.url
    }
}

impl Drop for RerunProxy {
    /// Rerun's server is told to stop and stops on its own thread: a dropped proxy waits until
    /// its port refuses connections, so nothing sent afterwards is taken.
    fn drop(&mut self) {
        drop(self.server.take());
        accepts_within(self.port, false);
    }
}

/// Whether 127.0.0.1:`port` comes to accept connections (`accepting`), or to refuse them,
/// within 5 s.
fn accepts_within(port: u16, accepting: bool) -> bool {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(5);
    loop {
        if std::net::TcpStream::connect(("127.0.0.1", port)).is_ok() == accepting {
            return true;
        }
        if std::time::Instant::now() > deadline {
            return false;
        }
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
}

/// Replaces every `Serve` sink by a connection to one [`RerunProxy`], started here; the proxy
/// must be kept alive as long as the logs are to be served.
pub fn start_proxy(sinks: &mut [RerunSink]) -> Result<Option<RerunProxy>, RerunError> {
    let Some(port) = sinks.iter().find_map(|s| match s {
        RerunSink::Serve(port) => Some(*port),
        _ => None,
    }) else {
        return Ok(None);
    };
    let proxy = RerunProxy::start(port)?;
    for sink in sinks.iter_mut() {
        if matches!(sink, RerunSink::Serve(_)) {
            *sink = RerunSink::Connect(proxy.url().to_string());
        }
    }
    Ok(Some(proxy))
}

impl std::str::FromStr for RerunSink {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s.split_once(':') {
            Some(("file", path)) if !path.is_empty() => Ok(RerunSink::File(path.into())),
            Some(("connect", url)) if !url.is_empty() => Ok(RerunSink::Connect(url.into())),
            None if s == "connect" => Ok(RerunSink::Connect(DEFAULT_VIEWER_URL.into())),
            None if s == "serve" => Ok(RerunSink::Serve(DEFAULT_SERVE_PORT)),
            Some(("serve", port)) => port
                .parse()
                .map(RerunSink::Serve)
                .map_err(|_| format!("{s:?}: serve:PORT needs a port number")),
            _ => Err(format!(
                "{s:?}: expected file:PATH, connect, connect:URL (e.g. connect:{DEFAULT_VIEWER_URL}), serve or serve:PORT"
            )),
        }
    }
}

/// What is logged, and how.
#[derive(Debug, Clone, PartialEq)]
pub struct RerunOptions {
    pub sinks: Vec<RerunSink>,
    /// Log the camera images every this many frames; 0: never.
    pub images_every: u64,
    /// Frames of history kept for each track's line strip.
    pub track_history_frames: usize,
    /// Arrow length = velocity x this many seconds.
    pub arrow_seconds: f64,
    /// Frames waiting for the logging thread before new ones are dropped.
    pub queue_frames: usize,
}

impl Default for RerunOptions {
    fn default() -> Self {
        Self {
            sinks: Vec::new(),
            images_every: 0,
            track_history_frames: 30,
            arrow_seconds: 0.2,
            queue_frames: 64,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum RerunError {
    #[error("rerun: cannot open {path}: {error}")]
    File { path: PathBuf, error: String },
    #[error("rerun: bad viewer URL {url:?}: {error}")]
    Url { url: String, error: String },
    #[error("rerun: {0}")]
    Stream(String),
}

/// Left and right 8-bit pixels, rig-sized.
pub(crate) type ImagePair = (Arc<[u8]>, Arc<[u8]>);

/// One frame's worth of data to log.
#[derive(Debug, Clone, Default)]
pub(crate) struct FrameLog {
    pub(crate) frame_index: u64,
    pub(crate) t_s: f64,
    pub(crate) world_from_rig: Option<Isometry3<f64>>,
    pub(crate) detections_left: Vec<Detection>,
    pub(crate) detections_right: Vec<Detection>,
    pub(crate) points: Vec<MatchedPoint>,
    pub(crate) causal_vectors: Vec<VelocityVector>,
    /// The centred vectors and the frame they describe.
    pub(crate) refined: Option<(u64, f64, Vec<VelocityVector>)>,
    pub(crate) stats: FrameStats,
    pub(crate) processing_ms: f64,
    /// Frame received -> its causal vectors sent (live only).
    pub(crate) latency_ms: Option<f64>,
    /// Left and right pixels, when this frame's images are logged.
    pub(crate) images: Option<ImagePair>,
}

/// What the logging thread is handed.
enum Entry {
    Frame(Box<FrameLog>),
    /// The mean-flow field's cells (world frame) as of this frame.
    Field {
        frame_index: u64,
        t_s: f64,
        cells: Vec<CellSummary>,
    },
}

impl FrameLog {
    /// Everything but timing and images, copied from a pipeline output.
    pub(crate) fn from_output(
        output: &FrameOutput,
        world_from_rig: Option<Isometry3<f64>>,
    ) -> Self {
        Self {
            frame_index: output.frame_index,
            t_s: output.t_s,
            world_from_rig,
            detections_left: output.detections_left.clone(),
            detections_right: output.detections_right.clone(),
            points: output.points.clone(),
            causal_vectors: output.causal_vectors.clone(),
            refined: output
                .centred_frame
                .map(|c| (c.index, c.t_s, output.vectors.clone())),
            stats: output.stats,
            ..Default::default()
        }
    }
}

/// What the logging thread did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RerunSummary {
    pub frames_logged: u64,
    /// Every sink took everything (a viewer that never answered makes this false).
    pub flushed: bool,
    /// Frames dropped because the logging thread was behind.
    pub(crate) frames_dropped: u64,
    pub errors: u64,
}

/// Field cells with fewer samples than this are drawn faded: their mean is still noisy.
pub(crate) const FIELD_FULL_SAMPLES: usize = 20;

/// A running logger: hand it frames with `log`, close it with
/// [`RerunLogger::finish`] (which completes the `.rrd` files).
pub struct RerunLogger {
    frames: Option<SyncSender<Entry>>,
    thread: Option<std::thread::JoinHandle<RerunSummary>>,
    dropped: Arc<AtomicU64>,
    images_every: u64,
}

impl RerunLogger {
    /// Opens the sinks and logs the static scene (calibration, view coordinates, layout).
    /// `recording_name` names the recording in the viewer (e.g. the session id).
    pub fn start(
        recording_name: &str,
        sinks: &[RerunSink],
        rig: &StereoRig,
        options: &RerunOptions,
    ) -> Result<Self, RerunError> {
        let mut boxed: Vec<Box<dyn rerun::sink::LogSink>> = Vec::new();
        for sink in sinks {
            match sink {
                RerunSink::File(path) => {
                    let file =
                        rerun::sink::FileSink::new(path.clone()).map_err(|e| RerunError::File {
                            path: path.clone(),
                            error: e.to_string(),
                        })?;
                    boxed.push(Box::new(file));
                }
                RerunSink::Connect(url) => {
                    let uri = url
                        .parse::<rerun::external::re_uri::ProxyUri>()
                        .map_err(|e| RerunError::Url {
                            url: url.clone(),
                            error: e.to_string(),
                        })?;
                    boxed.push(Box::new(rerun::sink::GrpcSink::new(uri)));
                }
                RerunSink::Serve(port) => {
                    return Err(RerunError::Stream(format!(
                        "serve:{port} must be turned into a connection with start_proxy first"
                    )))
                }
            }
        }
        let rec = rerun::RecordingStreamBuilder::new("mrptv")
            .recording_name(recording_name)
            .with_default_blueprint(blueprint())
            .set_sinks(boxed)
            .map_err(|e| RerunError::Stream(e.to_string()))?;
        let mut scene = Scene::new(rec, options.clone(), rig);
        scene.log_static(rig);
        let (tx, rx) = sync_channel::<Entry>(options.queue_frames.max(1));
        let dropped = Arc::new(AtomicU64::new(0));
        let dropped_in_thread = Arc::clone(&dropped);
        let thread = std::thread::Builder::new()
            .name("rerun".into())
            .spawn(move || {
                for entry in rx {
                    match entry {
                        Entry::Frame(frame) => scene.log_frame(&frame),
                        Entry::Field {
                            frame_index,
                            t_s,
                            cells,
                        } => {
                            scene.set_time(frame_index, t_s);
                            scene.log_field(&cells);
                        }
                    }
                }
                scene.finish(dropped_in_thread.load(Ordering::Relaxed))
            })
            .map_err(|e| RerunError::Stream(e.to_string()))?;
        Ok(Self {
            frames: Some(tx),
            thread: Some(thread),
            dropped,
            images_every: options.images_every,
        })
    }

    /// Whether this frame's images should be attached.
    pub(crate) fn wants_images(&self, frame_number: u64) -> bool {
        self.images_every > 0 && frame_number.is_multiple_of(self.images_every)
    }

    /// Queues a frame, waiting for room: offline runs log every frame.
    pub(crate) fn log_all(&self, frame: FrameLog) {
        self.send_waiting(Entry::Frame(Box::new(frame)));
    }

    fn send_waiting(&self, entry: Entry) {
        if let Some(tx) = &self.frames {
            let _ = tx.send(entry);
        }
    }

    /// Queues a frame; never waits (live sessions). A frame the logging thread has no room for
    /// is dropped.
    pub(crate) fn log(&self, frame: FrameLog) {
        self.send_or_drop(Entry::Frame(Box::new(frame)));
    }

    /// Logs the mean-flow field as of `frame_index` (`world/field`); `wait`: for room in the
    /// queue (offline), else dropped when the logging thread is behind (live).
    pub fn log_field(&self, frame_index: u64, t_s: f64, cells: Vec<CellSummary>, wait: bool) {
        let entry = Entry::Field {
            frame_index,
            t_s,
            cells,
        };
        if wait {
            self.send_waiting(entry);
        } else {
            self.send_or_drop(entry);
        }
    }

    fn send_or_drop(&self, entry: Entry) {
        let Some(tx) = &self.frames else {
            return;
        };
        match tx.try_send(entry) {
            Ok(()) => {}
            Err(TrySendError::Full(_)) => {
                if self.dropped.fetch_add(1, Ordering::Relaxed) == 0 {
                    tracing::warn!("rerun logging is behind: dropping frames from the log");
                }
            }
            Err(TrySendError::Disconnected(_)) => {}
        }
    }

    /// Logs what is queued, flushes and closes the sinks (`.rrd` files complete).
    pub fn finish(mut self) -> RerunSummary {
        self.close()
    }

    fn close(&mut self) -> RerunSummary {
        self.frames = None;
        match self.thread.take().map(|t| t.join()) {
            Some(Ok(summary)) => summary,
            _ => RerunSummary {
                frames_dropped: self.dropped.load(Ordering::Relaxed),
                errors: 1,
                ..Default::default()
            },
        }
    }
}

impl Drop for RerunLogger {
    fn drop(&mut self) {
        if self.thread.is_some() {
            self.close();
        }
    }
}

/// The default layout: the 3D scene, both camera views, the plots.
fn blueprint() -> rerun::blueprint::Blueprint {
    use rerun::blueprint::{
        Blueprint, Horizontal, Spatial2DView, Spatial3DView, TimeSeriesView, Vertical,
    };
    Blueprint::new(Horizontal::new([
        Spatial3DView::new("3D: particles, tracks, velocity")
            .with_origin("world")
            .into(),
        Vertical::new([
            Spatial2DView::new("left camera")
                .with_origin("world/rig/left")
                .into(),
            Spatial2DView::new("right camera")
                .with_origin("world/rig/right")
                .into(),
            TimeSeriesView::new("per frame").with_origin("plots").into(),
        ])
        .into(),
    ]))
}

/// Speed colour map: a perceptually ordered ramp (viridis' end points and middle), from 0 to
/// `max` m/s, saturating above.
pub(crate) fn speed_color(speed: f64, max: f64) -> [u8; 3] {
    const STOPS: [[f64; 3]; 5] = [
        [68.0, 1.0, 84.0],
        [59.0, 82.0, 139.0],
        [33.0, 145.0, 140.0],
        [94.0, 201.0, 98.0],
        [253.0, 231.0, 37.0],
    ];
    let x = if max > 0.0 {
        (speed / max).clamp(0.0, 1.0)
    } else {
        0.0
    } * 4.0;
    let i = (x.floor() as usize).min(3);
    let f = x - i as f64;
    let c = |k: usize| (STOPS[i][k] * (1.0 - f) + STOPS[i + 1][k] * f).round() as u8;
    [c(0), c(1), c(2)]
}

/// A "nice" upper bound (1, 2 or 5 x 10^k) at or above `x`.
pub(crate) fn nice_ceiling(x: f64) -> f64 {
    if !(x > 0.0 && x.is_finite()) {
        return 1.0;
    }
    let decade = 10f64.powf(x.log10().floor());
    [1.0, 2.0, 5.0, 10.0]
        .iter()
        .map(|m| m * decade)
        .find(|&v| v >= x)
        .unwrap_or(10.0 * decade)
}

fn f32x3(p: &Point3<f64>) -> [f32; 3] {
    [p.x as f32, p.y as f32, p.z as f32]
}

/// The logging thread's state.
struct Scene {
    rec: RecordingStream,
    options: RerunOptions,
    /// Fixed from the first vectors seen so colours mean the same all run long.
    speed_max: Option<f64>,
    tracks: BTreeMap<u64, VecDeque<(u64, [f32; 3])>>,
    image_size: [u32; 2],
    frames_logged: u64,
    errors: u64,
}

impl Scene {
    fn new(rec: RecordingStream, options: RerunOptions, rig: &StereoRig) -> Self {
        Self {
            rec,
            options,
            speed_max: None,
            tracks: BTreeMap::new(),
            image_size: [rig.width, rig.height],
            frames_logged: 0,
            errors: 0,
        }
    }

    fn check(&mut self, result: rerun::RecordingStreamResult<()>) {
        if let Err(e) = result {
            self.errors += 1;
            if self.errors == 1 {
                tracing::warn!("rerun logging failed (reported once): {e}");
            }
        }
    }

    fn log_static(&mut self, rig: &StereoRig) {
        let pinhole = |camera: &CameraModel| {
            rerun::Pinhole::new(
                rerun::components::PinholeProjection::from_focal_length_and_principal_point(
                    [camera.fx as f32, camera.fy as f32],
                    [camera.cx as f32 + 0.5, camera.cy as f32 + 0.5],
                ),
            )
            .with_resolution([rig.width as f32, rig.height as f32])
            .with_image_plane_distance(0.1)
        };
        let r = self.rec.log_static("world", &rerun::ViewCoordinates::RDF());
        self.check(r);
        let r = self
            .rec
            .log_static("world/rig/left", &transform(&Isometry3::identity()));
        self.check(r);
        let r = self.rec.log_static("world/rig/left", &pinhole(&rig.left));
        self.check(r);
        let rig_from_right = rig.right_from_left.inverse();
        let r = self
            .rec
            .log_static("world/rig/right", &transform(&rig_from_right));
        self.check(r);
        let r = self.rec.log_static("world/rig/right", &pinhole(&rig.right));
        self.check(r);
        for (name, color) in [
            ("detections/left", [31, 119, 180]),
            ("detections/right", [255, 127, 14]),
            ("matches", [44, 160, 44]),
            ("tracks", [148, 103, 189]),
            ("vectors", [214, 39, 40]),
            ("processing_ms", [127, 127, 127]),
            ("latency_ms", [23, 190, 207]),
        ] {
            let r = self.rec.log_static(
                format!("plots/{name}"),
                &rerun::SeriesLines::new()
                    .with_names([name])
                    .with_colors([color]),
            );
            self.check(r);
        }
    }

    fn log_legend(&mut self, speed_max: f64) {
        let text = format!(
            "## mrptv\n\nArrows: velocity; length = velocity x {} s.\n\nColour = speed, \
             0 m/s (dark purple) -> {:.3} m/s (yellow), through blue and green; faster is \
             yellow too.\n\n`world/vectors`: refined (centred) estimates, at the frame they \
             describe; `world/vectors_live`: causal estimates of the newest frame; hover an \
             arrow for its 1-sigma velocity errors (u, v, w).\n\n`world/field`: the mean-flow \
             field, one arrow per grid cell at its centre, the mean of the vectors measured in \
             it; cells with fewer than {} samples are faded.",
            self.options.arrow_seconds, speed_max, FIELD_FULL_SAMPLES
        );
        let r = self.rec.log_static(
            "legend",
            &rerun::TextDocument::new(text).with_media_type(rerun::MediaType::markdown()),
        );
        self.check(r);
    }

    fn set_time(&self, frame: u64, t_s: f64) {
        self.rec.set_time_sequence("frame", frame as i64);
        self.rec.set_duration_secs("sensor_time", t_s);
    }

    fn arrows(&mut self, vectors: &[VelocityVector]) -> rerun::Arrows3D {
        if self.speed_max.is_none() && vectors.len() >= 5 {
            let mut speeds: Vec<f64> = vectors.iter().map(|v| v.velocity_in_world.norm()).collect();
            speeds.sort_by(f64::total_cmp);
            let max = nice_ceiling(2.0 * speeds[speeds.len() / 2]);
            self.speed_max = Some(max);
            self.log_legend(max);
        }
        let max = self.speed_max.unwrap_or(1.0);
        let scale = self.options.arrow_seconds;
        rerun::Arrows3D::from_vectors(vectors.iter().map(|v| {
            let d = v.velocity_in_world * scale;
            [d.x as f32, d.y as f32, d.z as f32]
        }))
        .with_origins(vectors.iter().map(|v| f32x3(&v.position_in_world)))
        .with_colors(vectors.iter().map(|v| {
            let [r, g, b] = speed_color(v.velocity_in_world.norm(), max);
            rerun::Color::from_rgb(r, g, b)
        }))
        .with_labels(vectors.iter().map(|v| {
            let s = v.velocity_sigma;
            format!("sigma u {:.4} v {:.4} w {:.4} m/s", s.x, s.y, s.z)
        }))
        .with_show_labels(false)
    }

    fn log_field(&mut self, cells: &[CellSummary]) {
        let max = self.speed_max.unwrap_or(1.0);
        let scale = self.options.arrow_seconds;
        let arrows = rerun::Arrows3D::from_vectors(cells.iter().map(|c| {
            let d = c.mean * scale;
            [d.x as f32, d.y as f32, d.z as f32]
        }))
        .with_origins(cells.iter().map(|c| f32x3(&c.centre)))
        .with_colors(cells.iter().map(|c| {
            let [r, g, b] = speed_color(c.mean.norm(), max);
            let alpha = if c.samples >= FIELD_FULL_SAMPLES {
                255
            } else {
                70
            };
            rerun::Color::from_unmultiplied_rgba(r, g, b, alpha)
        }))
        .with_labels(cells.iter().map(|c| {
            format!(
                "n {} tracks {}; std u {:.4} v {:.4} w {:.4} m/s",
                c.samples, c.tracks, c.std.x, c.std.y, c.std.z
            )
        }))
        .with_show_labels(false);
        let r = self.rec.log("world/field", &arrows);
        self.check(r);
    }

    fn log_frame(&mut self, f: &FrameLog) {
        self.set_time(f.frame_index, f.t_s);
        let pose = f.world_from_rig.unwrap_or_else(Isometry3::identity);
        let r = self.rec.log("world/rig", &transform(&pose));
        self.check(r);
        if let Some((left, right)) = &f.images {
            for (side, pixels) in [("left", left), ("right", right)] {
                let image = rerun::Image::from_l8(pixels.to_vec(), self.image_size);
                let r = self.rec.log(format!("world/rig/{side}/image"), &image);
                self.check(r);
            }
        }
        for (side, detections) in [("left", &f.detections_left), ("right", &f.detections_right)] {
            let points = rerun::Points2D::new(
                detections
                    .iter()
                    .map(|d| [d.centroid.x as f32 + 0.5, d.centroid.y as f32 + 0.5]),
            )
            .with_radii(detections.iter().map(|d| (d.diameter_px / 2.0) as f32));
            let r = self
                .rec
                .log(format!("world/rig/{side}/detections"), &points);
            self.check(r);
        }
        let points = rerun::Points3D::new(f.points.iter().map(|p| f32x3(&p.point_in_world)))
            .with_radii([0.002]);
        let r = self.rec.log("world/points", &points);
        self.check(r);
        self.log_tracks(f);
        let live = self.arrows(&f.causal_vectors);
        let r = self.rec.log("world/vectors_live", &live);
        self.check(r);
        if let Some((index, t_s, vectors)) = &f.refined {
            self.set_time(*index, *t_s);
            let arrows = self.arrows(vectors);
            let r = self.rec.log("world/vectors", &arrows);
            self.check(r);
            self.set_time(f.frame_index, f.t_s);
        }
        let s = &f.stats;
        let mut scalars = vec![
            ("detections/left", s.detections_left as f64),
            ("detections/right", s.detections_right as f64),
            ("matches", s.matches as f64),
            ("tracks", s.tracks as f64),
            ("vectors", s.vectors as f64),
            ("processing_ms", f.processing_ms),
        ];
        if let Some(latency) = f.latency_ms {
            scalars.push(("latency_ms", latency));
        }
        for (name, value) in scalars {
            let r = self
                .rec
                .log(format!("plots/{name}"), &rerun::Scalars::single(value));
            self.check(r);
        }
        self.frames_logged += 1;
    }

    fn log_tracks(&mut self, f: &FrameLog) {
        let keep = self.options.track_history_frames as u64;
        for p in &f.points {
            let history = self.tracks.entry(p.track_id).or_default();
            history.push_back((f.frame_index, f32x3(&p.point_in_world)));
            while history
                .front()
                .is_some_and(|(frame, _)| frame + keep < f.frame_index)
            {
                history.pop_front();
            }
        }
        self.tracks.retain(|_, h| {
            h.back()
                .is_some_and(|(frame, _)| frame + keep >= f.frame_index)
        });
        let strips: Vec<Vec<[f32; 3]>> = self
            .tracks
            .values()
            .filter(|h| h.len() >= 2)
            .map(|h| h.iter().map(|(_, p)| *p).collect())
            .collect();
        let r = self.rec.log(
            "world/tracks",
            &rerun::LineStrips3D::new(strips).with_radii([0.0005]),
        );
        self.check(r);
    }

    fn finish(self, dropped: u64) -> RerunSummary {
        let flushed = match self.rec.flush_blocking() {
            Ok(()) => true,
            Err(e) => {
                tracing::warn!("rerun: flushing failed: {e}");
                false
            }
        };
        let summary = RerunSummary {
            frames_logged: self.frames_logged,
            flushed,
            frames_dropped: dropped,
            errors: self.errors,
        };
        // Dropping the stream closes the sinks; a file sink writes its footer then.
        drop(self.rec);
        summary
    }
}

/// A rigid transform as Rerun's parent-from-child `Transform3D`.
fn transform(parent_from_child: &Isometry3<f64>) -> rerun::Transform3D {
    let t = parent_from_child.translation.vector;
    let q = parent_from_child.rotation.coords;
    rerun::Transform3D::from_translation_rotation(
        [t.x as f32, t.y as f32, t.z as f32],
        rerun::Quaternion::from_xyzw([q.x as f32, q.y as f32, q.z as f32, q.w as f32]),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sinks_parse_and_bad_ones_are_explained() {
        assert_eq!(
            "file:run.rrd".parse::<RerunSink>(),
            Ok(RerunSink::File("run.rrd".into()))
        );
        assert_eq!(
            "connect".parse::<RerunSink>(),
            Ok(RerunSink::Connect(DEFAULT_VIEWER_URL.into()))
        );
        assert_eq!("serve".parse::<RerunSink>(), Ok(RerunSink::Serve(9876)));
        assert_eq!(
            "serve:9000".parse::<RerunSink>(),
            Ok(RerunSink::Serve(9000))
        );
        assert!("serve:x".parse::<RerunSink>().is_err());
        assert!("viewer".parse::<RerunSink>().is_err());
        assert!("file:".parse::<RerunSink>().is_err());
    }

    #[test]
    fn colours_run_from_dark_to_yellow_and_saturate() {
        assert_eq!(speed_color(0.0, 1.0), [68, 1, 84]);
        assert_eq!(speed_color(1.0, 1.0), [253, 231, 37]);
        assert_eq!(speed_color(5.0, 1.0), [253, 231, 37]);
        assert_eq!(nice_ceiling(0.13), 0.2);
        assert_eq!(nice_ceiling(3.0), 5.0);
        assert_eq!(nice_ceiling(1.0), 1.0);
    }
}
