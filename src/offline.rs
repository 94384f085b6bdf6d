//! The offline commands' work: write a synthetic recording, process a recording, or run a
//! scenario end to end in memory. The binary adds argument parsing and progress bars only.

use std::fs;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::Instant;

use mrptv_engine::eval::{evaluate, EvalError, EvalOptions, Observation, Report};

use crate::protocol::Encoding;
use crate::recording::{FrameEntry, Recording, RecordingError, RecordingWriter};
use crate::rerun_log::{FrameLog, RerunLogger};
use crate::tables::{self, TrackRow};
pub use mrptv_engine::health::{HealthFigures, RunHealth, RunTotals};
use mrptv_engine::synth::{ScenarioSpec, SynthFrame, Synthesizer, TruthRow};
use mrptv_engine::{FrameOutput, ImageView, Pipeline, PipelineConfig, PipelineError, StereoFrame};

#[derive(Debug, thiserror::Error)]
pub enum OfflineError {
    #[error(transparent)]
    Recording(#[from] RecordingError),
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
    #[error(transparent)]
    Eval(#[from] EvalError),
    #[error("images through {wire}: {message}")]
    Wire { wire: Wire, message: String },
    #[error("{path}: {error}")]
    Io {
        path: PathBuf,
        error: std::io::Error,
    },
}

fn io_error(path: &Path) -> impl FnOnce(std::io::Error) -> OfflineError + '_ {
    move |error| OfflineError::Io {
        path: path.to_path_buf(),
        error,
    }
}

#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct SynthSummary {
    pub frames: usize,
    pub truth_rows: usize,
    /// Fraction of truth particle-frames whose centre projects into both images.
    pub visible_fraction: f64,
    visible: usize,
    /// Left-image particles per pixel, averaged over the frames.
    pub particles_per_pixel: f64,
    in_view_left: usize,
    /// Of the particles in view of the left camera, the fraction whose image there touches or
    /// overlaps another's.
    pub touching_fraction: f64,
    touching_left: usize,
}

impl SynthSummary {
    fn add(&mut self, frame: &SynthFrame, pixels: usize) {
        self.frames += 1;
        self.truth_rows += frame.truth.len();
        self.visible += frame.visible_in_both;
        self.in_view_left += frame.in_view_left;
        self.touching_left += frame.touching_left;
        let ratio = |a: usize, b: usize| if b == 0 { 0.0 } else { a as f64 / b as f64 };
        self.visible_fraction = ratio(self.visible, self.truth_rows);
        self.touching_fraction = ratio(self.touching_left, self.in_view_left);
        self.particles_per_pixel = ratio(self.in_view_left, self.frames * pixels);
    }

    /// How crowded the images are, for a person choosing a scene.
    pub fn crowding(&self) -> String {
        format!(
            "{:.4} particles per pixel, {:.0} % of particle images touching another",
            self.particles_per_pixel,
            100.0 * self.touching_fraction
        )
    }
}

/// Writes a synthetic recording plus `truth.csv`. No `mrptv.toml`: a recording is processed with
/// the defaults, as a real one is.
pub fn write_synthetic(
    spec: ScenarioSpec,
    out: &Path,
    frames: usize,
    particles: usize,
    seed: u64,
    mut progress: impl FnMut(usize),
) -> Result<SynthSummary, OfflineError> {
    let with_pose = spec.head.world_from_rig(0.0).is_some();
    let mut writer = RecordingWriter::create(out, &spec.rig, with_pose)?;
    let truth_path = out.join("truth.csv");
    let mut truth = BufWriter::new(fs::File::create(&truth_path).map_err(io_error(&truth_path))?);
    writeln!(truth, "{}", tables::TRUTH_HEADER).map_err(io_error(&truth_path))?;
    let pixels = spec.rig.width as usize * spec.rig.height as usize;
    let mut synth = Synthesizer::new(spec, particles, seed);
    let mut summary = SynthSummary::default();
    for _ in 0..frames {
        let f = synth.next_frame();
        let entry = FrameEntry {
            index: f.index,
            t_s: f.t_s,
            world_from_rig: f.world_from_rig,
        };
        writer.write_frame(&entry, &f.left, &f.right)?;
        for row in &f.truth {
            tables::write_truth_row(&mut truth, row).map_err(io_error(&truth_path))?;
        }
        summary.add(&f, pixels);
        progress(summary.frames);
    }
    truth.flush().map_err(io_error(&truth_path))?;
    Ok(summary)
}

/// An output of `process_recording`, with the path its errors are reported against.
pub struct Sink<'a> {
    pub path: &'a Path,
    pub writer: &'a mut dyn Write,
}

/// Runs one frame given as rig-sized pixel buffers through the pipeline and adds it to the
/// totals, timing only the pipeline itself.
fn push_pixels(
    pipeline: &mut Pipeline,
    totals: &mut RunTotals,
    entry: &FrameEntry,
    left: &[u8],
    right: &[u8],
) -> Result<FrameOutput, OfflineError> {
    let (w, h) = (
        pipeline.rig().width as usize,
        pipeline.rig().height as usize,
    );
    let (Some(left), Some(right)) = (ImageView::new(w, h, left), ImageView::new(w, h, right))
    else {
        unreachable!("callers pass images decoded or rendered at the rig's size");
    };
    let frame = StereoFrame {
        index: entry.index,
        t_s: entry.t_s,
        world_from_rig: entry.world_from_rig,
        left,
        right,
    };
    let started = Instant::now();
    let output = pipeline.push(&frame)?;
    totals.add(&output.stats, started.elapsed().as_secs_f64());
    if output.stats.learnt_search > 0 {
        totals.learnt_search = pipeline.learnt_search().or(totals.learnt_search);
    }
    Ok(output)
}

/// Where `process_recording` writes.
pub struct ProcessSinks<'a> {
    pub tracks: Sink<'a>,
    pub points: Option<Sink<'a>>,
    /// Every frame is also logged to Rerun.
    pub rerun: Option<&'a RerunLogger>,
}

/// Runs a recording through the pipeline, writing `tracks.csv` and optionally `points.csv` rows
/// (headers included). PNGs are decoded one frame ahead on a helper thread.
pub fn process_recording(
    recording: &Recording,
    config: PipelineConfig,
    sinks: ProcessSinks<'_>,
    mut progress: impl FnMut(usize),
) -> Result<RunTotals, OfflineError> {
    let mut pipeline = Pipeline::new(recording.rig.clone(), config)?;
    let ProcessSinks {
        tracks: Sink {
            path: tracks_path,
            writer: tracks,
        },
        mut points,
        rerun,
    } = sinks;
    let tracks_error = io_error(tracks_path);
    writeln!(tracks, "{}", tables::TRACKS_HEADER_WITH_SIGMA).map_err(io_error(tracks_path))?;
    if let Some(p) = points.as_mut() {
        writeln!(p.writer, "{}", tables::POINTS_HEADER).map_err(io_error(p.path))?;
    }
    let mut totals = RunTotals::for_pipeline(&pipeline);
    std::thread::scope(|scope| {
        let (tx, rx) = mpsc::sync_channel(2);
        scope.spawn(move || {
            for entry in &recording.frames {
                let loaded = recording.load(entry).map(|images| (*entry, images));
                let failed = loaded.is_err();
                if tx.send(loaded).is_err() || failed {
                    break;
                }
            }
        });
        for loaded in rx {
            let (entry, (left, right)) = loaded?;
            let pipeline_s_before = totals.pipeline_s;
            let output = push_pixels(&mut pipeline, &mut totals, &entry, &left, &right)?;
            for v in &output.vectors {
                tables::write_track_row(tracks, v).map_err(io_error(tracks_path))?;
            }
            if let Some(logger) = rerun {
                let mut log = FrameLog::from_output(&output, entry.world_from_rig);
                log.processing_ms = (totals.pipeline_s - pipeline_s_before) * 1e3;
                if logger.wants_images(totals.frames as u64 - 1) {
                    log.images = Some((left.into(), right.into()));
                }
                logger.log_all(log);
            }
            if let Some(p) = points.as_mut() {
                for m in &output.points {
                    tables::write_point_row(p.writer, output.frame_index, output.t_s, m)
                        .map_err(io_error(p.path))?;
                }
            }
            progress(totals.frames);
        }
        Ok::<(), OfflineError>(())
    })?;
    tracks.flush().map_err(tracks_error)?;
    if let Some(p) = points.as_mut() {
        p.writer.flush().map_err(io_error(p.path))?;
    }
    Ok(totals)
}

/// Runs `recording` through a pipeline with `config` again and keeps what the loss budget needs
/// of every frame; `progress` is told the frames done.
pub fn observe_recording(
    recording: &Recording,
    config: PipelineConfig,
    mut progress: impl FnMut(usize),
) -> Result<Vec<Observation>, OfflineError> {
    let mut pipeline = Pipeline::new(recording.rig.clone(), config)?;
    let mut totals = RunTotals::for_pipeline(&pipeline);
    let mut observations = Vec::with_capacity(recording.frames.len());
    for entry in &recording.frames {
        let (left, right) = recording.load(entry)?;
        let output = push_pixels(&mut pipeline, &mut totals, entry, &left, &right)?;
        observations.push(Observation::of(&output, entry.world_from_rig));
        progress(observations.len());
    }
    Ok(observations)
}

/// A synthetic scenario run end to end in memory: what to render, how to process and score it,
/// and the wire its images cross.
#[derive(Debug, Clone)]
pub struct SyntheticRun {
    pub spec: ScenarioSpec,
    pub config: PipelineConfig,
    pub frames: usize,
    pub particles: usize,
    pub seed: u64,
    pub eval: EvalOptions,
    pub wire: Wire,
}

impl SyntheticRun {
    /// The scenario's default frames and particles, seed 1, scored over the config's velocity
    /// window, images in memory as rendered.
    pub fn new(spec: ScenarioSpec, config: PipelineConfig) -> Self {
        let eval = EvalOptions {
            window_frames: config.velocity.half_window_frames as u64,
            ..Default::default()
        };
        Self {
            frames: spec.default_frames,
            particles: spec.default_particles,
            spec,
            config,
            seed: 1,
            eval,
            wire: Wire::Frames(Encoding::Raw8),
        }
    }

    /// Synthesises, sends the images over the wire (encoded as a headset or hl2ss would,
    /// decoded as the server or the bridge does), processes and scores; `progress` is told each
    /// frame done.
    pub fn run(&self, mut progress: impl FnMut(usize)) -> Result<InMemoryRun, OfflineError> {
        let spec = &self.spec;
        let mut pipeline = Pipeline::new(spec.rig.clone(), self.config.clone())?;
        let pixels = spec.rig.width as usize * spec.rig.height as usize;
        let mut wire = WireLink::new(self.wire, spec)?;
        let mut synth = Synthesizer::new(spec.clone(), self.particles, self.seed);
        let mut scene = SynthSummary::default();
        let (mut truth, mut tracks, mut causal_tracks) = (Vec::new(), Vec::new(), Vec::new());
        let mut totals = RunTotals::for_pipeline(&pipeline);
        for n in 0..self.frames {
            let mut f = synth.next_frame();
            f.left = wire.carry(0, std::mem::take(&mut f.left))?;
            f.right = wire.carry(1, std::mem::take(&mut f.right))?;
            let entry = FrameEntry {
                index: f.index,
                t_s: f.t_s,
                world_from_rig: f.world_from_rig,
            };
            let output = push_pixels(&mut pipeline, &mut totals, &entry, &f.left, &f.right)?;
            tracks.extend(output.vectors.iter().map(TrackRow::from));
            causal_tracks.extend(output.causal_vectors.iter().map(TrackRow::from));
            scene.add(&f, pixels);
            truth.extend(f.truth);
            progress(n + 1);
        }
        let report = evaluate(&truth, &tracks, &self.eval)?;
        Ok(InMemoryRun {
            truth,
            tracks,
            causal_tracks,
            totals,
            report,
            scene,
            wire: wire.summary,
        })
    }
}

/// A scenario run end to end in memory: what it rendered, measured and scored.
#[derive(Debug, Clone)]
pub struct InMemoryRun {
    pub truth: Vec<TruthRow>,
    /// Centred (refined) vectors: the measurement.
    pub tracks: Vec<TrackRow>,
    /// Causal vectors, as the live server sends them first.
    pub causal_tracks: Vec<TrackRow>,
    pub totals: RunTotals,
    pub report: Report,
    pub scene: SynthSummary,
    pub wire: WireSummary,
}

/// How a run's images travel from the cameras to the engine.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Wire {
    /// A frame encoding of the protocol, as a headset sends it.
    Frames(Encoding),
    /// hl2ss's H.264 streams at this bitrate a camera (one IDR a second), as
    /// `mrptv hl2ss --codec h264` receives them.
    H264 { bitrate_bps: u32 },
}

impl std::fmt::Display for Wire {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Wire::Frames(encoding) => write!(f, "{encoding:?} frames"),
            Wire::H264 { bitrate_bps } => {
                write!(
                    f,
                    "H.264 at {:.1} Mbit/s a camera",
                    f64::from(*bitrate_bps) / 1e6
                )
            }
        }
    }
}

/// What a run's images cost on a headset's link.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WireSummary {
    pub wire: Wire,
    pub images: usize,
    pub bytes: u64,
    /// Encoding (the headset's work) and decoding (the server's), all images, seconds.
    pub encode_s: f64,
    pub decode_s: f64,
}

impl WireSummary {
    pub fn bytes_per_pair(&self) -> f64 {
        2.0 * self.bytes as f64 / self.images.max(1) as f64
    }

    /// Megabits a second at `pairs_per_s` stereo pairs a second.
    pub fn mbit_per_s(&self, pairs_per_s: f64) -> f64 {
        self.bytes_per_pair() * 8.0 * pairs_per_s / 1e6
    }

    pub fn encode_ms_per_image(&self) -> f64 {
        1e3 * self.encode_s / self.images.max(1) as f64
    }

    pub fn decode_ms_per_image(&self) -> f64 {
        1e3 * self.decode_s / self.images.max(1) as f64
    }
}

/// One encoder and decoder per camera: a video codec carries state from frame to frame.
type H264Streams = [(crate::video::H264Encoder, crate::video::H264Decoder); 2];

/// A wire the images of a synthetic run cross, with what it has cost so far.
struct WireLink {
    summary: WireSummary,
    width: u32,
    height: u32,
    streams: Option<H264Streams>,
}

impl WireLink {
    fn new(wire: Wire, spec: &ScenarioSpec) -> Result<Self, OfflineError> {
        let (width, height) = (spec.rig.width, spec.rig.height);
        let failed = |message: String| OfflineError::Wire { wire, message };
        let streams = match wire {
            Wire::H264 { bitrate_bps } => {
                let fps = (1.0 / spec.frame_interval_s) as f32;
                let stream = || -> Result<_, OfflineError> {
                    Ok((
                        crate::video::H264Encoder::new(
                            width,
                            height,
                            bitrate_bps,
                            fps,
                            fps.round() as u32,
                        )
                        .map_err(|e| failed(e.to_string()))?,
                        crate::video::H264Decoder::new(width, height)
                            .map_err(|e| failed(e.to_string()))?,
                    ))
                };
                Some([stream()?, stream()?])
            }
            Wire::Frames(_) => None,
        };
        let summary = WireSummary {
            wire,
            images: 0,
            bytes: 0,
            encode_s: 0.0,
            decode_s: 0.0,
        };
        Ok(Self {
            summary,
            width,
            height,
            streams,
        })
    }

    /// Camera `camera`'s image after the wire, timing the coding.
    fn carry(&mut self, camera: usize, image: Vec<u8>) -> Result<Vec<u8>, OfflineError> {
        let wire = self.summary.wire;
        let failed = |message: String| OfflineError::Wire { wire, message };
        let (width, height) = (self.width, self.height);
        self.summary.images += 1;
        let started = Instant::now();
        let (sent, encoded, received) = match (wire, &mut self.streams) {
            (Wire::Frames(Encoding::Raw8), _) => {
                self.summary.bytes += image.len() as u64;
                return Ok(image);
            }
            (Wire::Frames(encoding), _) => {
                let sent = encoding
                    .encode_image(&image, width, height)
                    .map_err(failed)?;
                let encoded = Instant::now();
                let received = encoding
                    .decode_image(&sent, width, height)
                    .map_err(failed)?;
                (sent, encoded, received)
            }
            (Wire::H264 { .. }, streams) => {
                let Some((encoder, decoder)) = streams.as_mut().map(|s| &mut s[camera]) else {
                    return Err(failed("no H.264 stream".into()));
                };
                let sent = encoder.encode(&image).map_err(|e| failed(e.to_string()))?;
                let encoded = Instant::now();
                let received = decoder
                    .decode(&sent)
                    .map_err(|e| failed(e.to_string()))?
                    .ok_or_else(|| failed("the decoder gave no picture for a frame".into()))?;
                (sent, encoded, received)
            }
        };
        self.summary.encode_s += (encoded - started).as_secs_f64();
        self.summary.decode_s += encoded.elapsed().as_secs_f64();
        self.summary.bytes += sent.len() as u64;
        Ok(received)
    }
}
