//! `mrptv process`: a recording in, velocity vectors (tracks.csv) out.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

use mrptv::offline::{self, ProcessSinks, Sink};
use mrptv::ptv::PipelineConfig;
use mrptv::recording::Recording;
use mrptv::rerun_log::{start_proxy, RerunLogger, RerunOptions, RerunSink};

use super::args::DepthRange;
use super::{create_output, method_config, progress_bar, runtime, termination};

#[derive(clap::Args)]
pub struct Args {
    /// Recording directory (rig.json, frames.csv, left/, right/).
    rec: PathBuf,
    /// Output CSV: frame,t_s,track_id,x,y,z,u,v,w (metres, m/s, world frame).
    #[arg(long)]
    out: PathBuf,
    /// Also write every stereo-matched particle: frame,t_s,x,y,z,xl,yl,xr,yr.
    #[arg(long)]
    points: Option<PathBuf>,
    /// TOML config [default: REC/mrptv.toml if present, else built-in defaults].
    #[arg(long)]
    config: Option<PathBuf>,
    /// Use the published method's choices (no mrptv improvements) as the base config.
    #[arg(long)]
    method: bool,
    /// The measurement volume's depths, metres along the cameras' common viewing direction:
    /// NEAR..FAR (FAR may be inf) [default: every depth both cameras see].
    #[arg(long, value_name = "NEAR..FAR")]
    depth_range: Option<DepthRange>,
    /// Log the run to Rerun: file:RUN.rrd, connect (a viewer on this machine) or
    /// connect:URL. Repeat for several.
    #[arg(long, value_name = "SINK")]
    rerun: Vec<RerunSink>,
    /// With --rerun: log the camera images every N frames (0: never).
    #[arg(long, default_value_t = 10, value_name = "N")]
    rerun_images_every: u64,
}

pub fn run(args: Args) -> Result<()> {
    let Args {
        rec,
        out,
        points,
        config,
        method,
        depth_range,
        mut rerun,
        rerun_images_every,
    } = args;
    let recording = Recording::open(&rec)?;
    let mut config = load_config(&rec, config.as_deref(), method)?;
    DepthRange::apply(depth_range, &mut config);
    let mut tracks = create_output(&out)?;
    let proxy = start_proxy(&mut rerun)?;
    let logger = if rerun.is_empty() {
        None
    } else {
        let options = RerunOptions {
            images_every: rerun_images_every,
            ..Default::default()
        };
        let name = rec.file_name().map_or_else(
            || rec.display().to_string(),
            |n| n.to_string_lossy().into_owned(),
        );
        Some(RerunLogger::start(&name, &rerun, &recording.rig, &options)?)
    };
    let mut points_file = points.as_deref().map(create_output).transpose()?;
    let bar = progress_bar(recording.frames.len(), "process");
    let totals = offline::process_recording(
        &recording,
        config.clone(),
        ProcessSinks {
            tracks: Sink {
                path: &out,
                writer: &mut tracks,
            },
            points: match (points.as_deref(), points_file.as_mut()) {
                (Some(path), Some(file)) => Some(Sink { path, writer: file }),
                _ => None,
            },
            rerun: logger.as_ref(),
        },
        |n| bar.set_position(n as u64),
    )
    .with_context(|| format!("processing {}", rec.display()))?;
    bar.finish_and_clear();
    if let Some(logger) = logger {
        report_rerun(logger, &rerun);
    }
    eprintln!(
        "{} frames: {:.1} detections/image, {:.1} matches/frame, {} vectors ({} rejected as rough, {} as straying from their neighbours, {} as no measurement: outside the volume or impossibly fast) -> {}; pipeline {:.1} frames/s",
        totals.frames,
        (totals.counts.detections_left + totals.counts.detections_right) as f64 / (2 * totals.frames.max(1)) as f64,
        totals.counts.matches as f64 / totals.frames.max(1) as f64,
        totals.counts.vectors,
        totals.counts.rejected,
        totals.counts.outliers,
        totals.counts.implausible,
        out.display(),
        totals.frames as f64 / totals.pipeline_s.max(1e-9)
    );
    super::print_health(&totals.health(&config));
    if let Some(proxy) = proxy {
        println!(
            "serving the Rerun log: rerun --connect {}   (Ctrl-C to stop)",
            proxy.url()
        );
        runtime()?.block_on(termination());
    }
    Ok(())
}

/// Waits for the Rerun logger to drain and says where the log went.
fn report_rerun(logger: RerunLogger, sinks: &[RerunSink]) {
    let summary = logger.finish();
    eprintln!(
        "rerun: {} frames logged to {}{}",
        summary.frames_logged,
        sinks
            .iter()
            .map(|s| match s {
                RerunSink::File(p) => p.display().to_string(),
                RerunSink::Connect(url) => url.clone(),
                RerunSink::Serve(port) => format!("serve:{port}"),
            })
            .collect::<Vec<_>>()
            .join(", "),
        if summary.flushed && summary.errors == 0 {
            ""
        } else {
            " (a sink failed: see the warning above; tracks.csv is complete)"
        }
    );
}

fn load_config(rec: &Path, explicit: Option<&Path>, method: bool) -> Result<PipelineConfig> {
    let suggested = rec.join("mrptv.toml");
    let config = match explicit {
        Some(path) => mrptv::config::load(path)?,
        None if suggested.is_file() => {
            eprintln!("using {}", suggested.display());
            mrptv::config::load(&suggested)?
        }
        None => PipelineConfig::default(),
    };
    Ok(if method {
        method_config(&config)
    } else {
        config
    })
}
