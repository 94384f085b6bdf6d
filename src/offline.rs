//! The offline commands' work: write a synthetic recording, process a recording, or run a
//! scenario end to end in memory. The binary adds argument parsing and progress bars only.

use std::fs;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::Instant;

use nalgebra::Isometry3;

use mrptv_engine::eval::{evaluate, EvalError, EvalOptions, Report};

use crate::protocol::Encoding;
use crate::recording::{FrameEntry, Recording, RecordingError, RecordingWriter};
use crate::rerun_log::{FrameLog, RerunLogger};
use crate::tables::{self, TrackRow};
use mrptv_engine::synth::{ScenarioSpec, SynthFrame, Synthesizer, TruthRow};
use mrptv_engine::{
    FrameOutput, FrameStats, ImageView, Pipeline, PipelineConfig, PipelineError, StereoFrame,
    StereoSearch,
};

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

/// Totals over a processing run.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct RunTotals {
    pub frames: usize,
    /// The frames' statistics, summed.
    pub counts: FrameStats,
    /// Time spent inside `Pipeline::push`, seconds.
    pub pipeline_s: f64,
    /// The stereo search the pipeline settled on.
    pub stereo_search: Option<StereoSearch>,
    /// The last search it narrowed to where the tracks were (`stereo.learn_depth_range`).
    pub learnt_search: Option<StereoSearch>,
}

/// A run's health figures (see [`RunTotals::health`]).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct HealthFigures {
    pub detections_per_image: f64,
    /// Of all detections, those continuing a track from an earlier frame.
    pub linked_fraction: f64,
    /// Stereo candidates per left particle that had at least one.
    pub stereo_candidates_per_particle: f64,
    /// Of left detections, those matched in the right image.
    pub matched_fraction: f64,
    /// Of matched particles, those given a centred velocity.
    pub velocity_fraction: f64,
}

impl RunTotals {
    pub fn add(&mut self, s: &FrameStats, pipeline_s: f64) {
        self.frames += 1;
        self.counts += s;
        self.pipeline_s += pipeline_s;
    }

    /// Empty totals that remember the stereo search `pipeline` settled on.
    fn for_pipeline(pipeline: &Pipeline) -> Self {
        Self {
            stereo_search: Some(*pipeline.stereo_search()),
            ..Default::default()
        }
    }

    /// The run's health figures so far.
    pub fn figures(&self) -> HealthFigures {
        let detections = self.counts.detections_left + self.counts.detections_right;
        HealthFigures {
            detections_per_image: ratio(detections, 2 * self.frames),
            linked_fraction: ratio(
                self.counts.linked_left + self.counts.linked_right,
                detections,
            ),
            stereo_candidates_per_particle: ratio(
                self.counts.stereo_candidates,
                self.counts.left_with_candidates,
            ),
            matched_fraction: ratio(self.counts.matches, self.counts.detections_left),
            velocity_fraction: ratio(self.counts.vectors, self.counts.matches),
        }
    }

    /// What a run settled on, how healthy it was, and in words what its figures say cannot be
    /// trusted; a run that gave no vectors always gets a warning saying why.
    pub fn health(&self, config: &PipelineConfig) -> RunHealth {
        let detections = self.counts.detections_left + self.counts.detections_right;
        let HealthFigures {
            detections_per_image,
            linked_fraction,
            stereo_candidates_per_particle: candidates_per_particle,
            matched_fraction,
            velocity_fraction: vector_fraction,
        } = self.figures();
        let box_px = config.link.box_half_side_px;
        let velocity = &config.velocity;
        let window = 2 * velocity.half_window_frames + 1;
        // A fast particle may have its velocity from as few as five frames.
        let shortest_window = if velocity.min_window_travel_px > 0.0 {
            window.min(5)
        } else {
            window
        };
        let mut search = self
            .stereo_search
            .map_or_else(|| "not set up".to_string(), |s| s.to_string());
        if let Some(learnt) = self.learnt_search {
            search += &format!(
                ", narrowed to where the tracks are in {:.0} % of frames (last: depths \
                 {:.3}..{:.3} m, disparity {:.1}..{:.1} px)",
                100.0 * ratio(self.counts.learnt_search, self.frames),
                learnt.near_m,
                learnt.far_m,
                learnt.min_disparity_px,
                learnt.max_disparity_px
            );
        }
        let first_steps =
            if config.link.predict_new_from_neighbours && config.link.max_displacement_px > 0.0 {
                format!(
                    " (a new track's first step learnt from the images, up to {} px)",
                    config.link.max_displacement_px
                )
            } else {
                String::new()
            };
        let rejoins = if config.tracks.rejoin_frames > 0 {
            format!(
                "; broken 3D tracks rejoined across up to {} missing frames ({:.1} per frame)",
                config.tracks.rejoin_frames,
                ratio(self.counts.rejoined, self.frames)
            )
        } else {
            String::new()
        };
        let windows = if shortest_window < window {
            format!(
                "{shortest_window} to {window} frames (narrower where a particle crosses {} px \
                 within it)",
                velocity.min_window_travel_px
            )
        } else {
            format!("{window} frames")
        };
        let components = 3 * self.counts.vectors;
        let fits = if velocity.adaptive_fit && components > 0 {
            let c = &self.counts;
            let line = if velocity.line_past_frames > velocity.half_window_frames {
                format!(
                    ", {:.0} % a line from {} frames back",
                    100.0 * ratio(c.fit_components_line, components),
                    velocity.line_past_frames
                )
            } else {
                String::new()
            };
            format!(
                ", fit per component: {:.0} % quadratic on the full window, {:.0} % on a \
                 narrower one, {:.0} % cubic{line}",
                100.0
                    * ratio(
                        components
                            - c.fit_components_narrower
                            - c.fit_components_cubic
                            - c.fit_components_line,
                        components
                    ),
                100.0 * ratio(c.fit_components_narrower, components),
                100.0 * ratio(c.fit_components_cubic, components)
            )
        } else {
            String::new()
        };
        let noisy = if self.counts.noisy_images > 0 {
            format!(
                " (raised for sensor noise in {:.0} % of images)",
                100.0 * ratio(self.counts.noisy_images, 2 * self.frames)
            )
        } else {
            String::new()
        };
        let background = if config.detect.background_rise_per_frame > 0.0 {
            format!(
                " after a background that learns what stands still (rising {} grey levels per \
                 frame)",
                config.detect.background_rise_per_frame
            )
        } else {
            String::new()
        };
        let settled = format!(
            "stereo search {search}; linking box +-{box_px} px{first_steps}{rejoins}; velocity \
             window {windows}{fits}; threshold {} grey levels above the local mean{noisy}{background}",
            -config.detect.contrast_c
        );
        let summary = format!(
            "{detections_per_image:.1} detections/image, {:.0} % linked to an earlier frame, \
             {candidates_per_particle:.2} stereo candidates per matchable particle, {:.0} % of \
             left detections matched, {:.0} % of matched particles given a velocity, {:.1} \
             fixtures/image (static spots left out)",
            100.0 * linked_fraction,
            100.0 * matched_fraction,
            100.0 * vector_fraction,
            ratio(self.counts.fixtures, 2 * self.frames)
        );
        let mut warnings = Vec::new();
        if self.counts.vectors == 0 {
            warnings.push(if self.frames == 0 {
                "no vectors: the recording has no frames".to_string()
            } else if detections == 0 {
                format!(
                    "no vectors: no particle was detected in any image (a particle must be {} grey \
                     levels brighter than its 15 px neighbourhood, detect.contrast_c, and its \
                     area within detect.min_area_px..max_area_px)",
                    -config.detect.contrast_c
                )
            } else if self.counts.matches == 0 {
                format!(
                    "no vectors: particles were detected ({detections_per_image:.1} per image) but \
                     none matched between the cameras, so none lay in the stereo search: {search}; \
                     check rig.json, or give the measurement volume with --depth-range"
                )
            } else if self.frames < shortest_window {
                format!(
                    "no vectors: the recording has {} frames, and a centred velocity needs a \
                     particle seen through {shortest_window} (velocity.half_window_frames = {})",
                    self.frames, config.velocity.half_window_frames
                )
            } else {
                format!(
                    "no vectors: {} particles were matched between the cameras, but none was \
                     followed through the {windows} a centred velocity needs ({:.0} % of \
                     detections linked to an earlier frame): particles may move more than the \
                     linking box (+-{box_px} px) per frame",
                    self.counts.matches,
                    100.0 * linked_fraction
                )
            });
        } else {
            if linked_fraction < 0.5 {
                warnings.push(format!(
                    "only {:.0} % of detections linked to an earlier frame: particles may move \
                     more than the linking box (+-{box_px} px) per frame; vectors will be few",
                    100.0 * linked_fraction
                ));
            }
            // Only frames at least M from either end can carry a centred velocity.
            let centred_frames = self.frames.saturating_sub(window - 1);
            let possible = ratio(centred_frames, self.frames);
            if vector_fraction < 0.2 * possible && linked_fraction >= 0.5 {
                warnings.push(format!(
                    "only {:.1} % of the particles matched in both cameras were given a velocity: \
                     tracks break before the {windows} a centred velocity needs; particles \
                     may move more than the linking box (+-{box_px} px) per frame",
                    100.0 * vector_fraction
                ));
            }
            if candidates_per_particle > 2.5 {
                warnings.push(format!(
                    "a matchable particle had {candidates_per_particle:.1} stereo candidates on \
                     average: matches are ambiguous and ghosts likely; narrow --depth-range or \
                     check the calibration"
                ));
            }
            if matched_fraction < 0.3 {
                warnings.push(format!(
                    "only {:.0} % of left detections found a partner in the right image: check \
                     rig.json and the stereo search ({search})",
                    100.0 * matched_fraction
                ));
            }
        }
        RunHealth {
            settled,
            summary,
            warnings,
        }
    }
}

fn ratio(a: usize, b: usize) -> f64 {
    if b == 0 {
        0.0
    } else {
        a as f64 / b as f64
    }
}

/// A run's settled parameters and health figures in words, and its warnings.
#[derive(Debug, Clone, PartialEq)]
pub struct RunHealth {
    pub settled: String,
    pub summary: String,
    pub warnings: Vec<String>,
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
    index: u64,
    t_s: f64,
    world_from_rig: Option<Isometry3<f64>>,
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
        index,
        t_s,
        world_from_rig,
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
            let output = push_pixels(
                &mut pipeline,
                &mut totals,
                entry.index,
                entry.t_s,
                entry.world_from_rig,
                &left,
                &right,
            )?;
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

/// A scenario run end to end in memory: synthesise, process, score.
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

pub fn run_in_memory(
    spec: ScenarioSpec,
    config: PipelineConfig,
    frames: usize,
    particles: usize,
    seed: u64,
    eval: &EvalOptions,
    progress: impl FnMut(usize),
) -> Result<InMemoryRun, OfflineError> {
    run_in_memory_over(
        Wire::Frames(Encoding::Raw8),
        spec,
        config,
        frames,
        particles,
        seed,
        eval,
        progress,
    )
}

/// A synthetic run whose images travel over `wire` (encoded as a headset or hl2ss would,
/// decoded as the server or the bridge does) before the pipeline: what that costs in accuracy
/// and bandwidth.
#[allow(clippy::too_many_arguments)]
pub fn run_in_memory_over(
    wire: Wire,
    spec: ScenarioSpec,
    config: PipelineConfig,
    frames: usize,
    particles: usize,
    seed: u64,
    eval: &EvalOptions,
    mut progress: impl FnMut(usize),
) -> Result<InMemoryRun, OfflineError> {
    let mut pipeline = Pipeline::new(spec.rig.clone(), config)?;
    let pixels = spec.rig.width as usize * spec.rig.height as usize;
    let (width, height) = (spec.rig.width, spec.rig.height);
    let mut summary = WireSummary {
        wire,
        images: 0,
        bytes: 0,
        encode_s: 0.0,
        decode_s: 0.0,
    };
    let failed = |message: String| OfflineError::Wire { wire, message };
    // One stream per camera: a video codec carries state from frame to frame.
    let mut streams = match wire {
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
    let mut through_wire = |camera: usize, image: Vec<u8>| -> Result<Vec<u8>, OfflineError> {
        summary.images += 1;
        let started = Instant::now();
        let (sent, encoded, received) = match (wire, &mut streams) {
            (Wire::Frames(Encoding::Raw8), _) => {
                summary.bytes += image.len() as u64;
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
        summary.encode_s += (encoded - started).as_secs_f64();
        summary.decode_s += encoded.elapsed().as_secs_f64();
        summary.bytes += sent.len() as u64;
        Ok(received)
    };
    let mut synth = Synthesizer::new(spec, particles, seed);
    let mut scene = SynthSummary::default();
    let mut truth = Vec::new();
    let mut tracks = Vec::new();
    let mut causal_tracks = Vec::new();
    let mut totals = RunTotals::for_pipeline(&pipeline);
    for n in 0..frames {
        let mut f = synth.next_frame();
        f.left = through_wire(0, std::mem::take(&mut f.left))?;
        f.right = through_wire(1, std::mem::take(&mut f.right))?;
        let output = push_pixels(
            &mut pipeline,
            &mut totals,
            f.index,
            f.t_s,
            f.world_from_rig,
            &f.left,
            &f.right,
        )?;
        tracks.extend(output.vectors.iter().map(TrackRow::from));
        causal_tracks.extend(output.causal_vectors.iter().map(TrackRow::from));
        scene.add(&f, pixels);
        truth.extend(f.truth);
        progress(n + 1);
    }
    let report = evaluate(&truth, &tracks, eval)?;
    Ok(InMemoryRun {
        truth,
        tracks,
        causal_tracks,
        totals,
        report,
        scene,
        wire: summary,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn healthy() -> RunTotals {
        RunTotals {
            frames: 100,
            counts: FrameStats {
                detections_left: 3000,
                detections_right: 3000,
                matches: 2900,
                vectors: 2200,
                linked_left: 2900,
                linked_right: 2900,
                stereo_candidates: 3500,
                left_with_candidates: 2950,
                ..Default::default()
            },
            ..Default::default()
        }
    }

    /// `totals` with its counts changed by `change`.
    fn with(totals: RunTotals, change: impl FnOnce(&mut FrameStats)) -> RunTotals {
        let mut t = totals;
        change(&mut t.counts);
        t
    }

    #[test]
    fn a_healthy_run_has_no_warnings() {
        let health = healthy().health(&PipelineConfig::default());
        assert!(health.warnings.is_empty(), "{:?}", health.warnings);
        assert!(
            health.summary.contains("30.0 detections/image")
                && health.summary.contains("97 % linked"),
            "{}",
            health.summary
        );
    }

    #[test]
    fn every_run_without_vectors_says_why() {
        let config = PipelineConfig::default();
        let why = |totals: RunTotals| {
            let warnings = totals.health(&config).warnings;
            assert_eq!(warnings.len(), 1, "{warnings:?}");
            warnings[0].clone()
        };
        let none = |t: RunTotals| with(t, |c| c.vectors = 0);
        assert!(why(none(RunTotals::default())).contains("no frames"));
        let dark = RunTotals {
            frames: 50,
            ..Default::default()
        };
        assert!(why(dark).contains("no particle was detected"));
        let unmatched = with(none(healthy()), |c| c.matches = 0);
        assert!(why(unmatched).contains("none matched between the cameras"));
        let short = RunTotals {
            frames: 4,
            ..none(healthy())
        };
        assert!(why(short).contains("has 4 frames"));
        let broken = with(none(healthy()), |c| {
            c.linked_left = 300;
            c.linked_right = 300;
        });
        assert!(why(broken).contains("linking box"));
    }

    #[test]
    fn tracks_that_break_and_ambiguous_matches_are_warned_of() {
        let config = PipelineConfig::default();
        let fast = with(healthy(), |c| c.vectors = 20);
        let warnings = fast.health(&config).warnings;
        assert!(
            warnings.iter().any(|w| w.contains("tracks break")),
            "{warnings:?}"
        );
        let crowded = with(healthy(), |c| c.stereo_candidates = 9000);
        let warnings = crowded.health(&config).warnings;
        assert!(
            warnings.iter().any(|w| w.contains("ambiguous")),
            "{warnings:?}"
        );
    }
}
