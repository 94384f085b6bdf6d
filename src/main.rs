//! `mrptv`: the command-line edge. Parses arguments, shows progress, reports errors; the work
//! itself lives in the library (`mrptv::offline`).

use std::fs;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::{Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};

use mrptv::eval::{evaluate, EvalOptions};
use mrptv::offline::{self, ProcessSinks, Sink};
use mrptv::ptv::PipelineConfig;
use mrptv::recording::Recording;
use mrptv::synth::{Scenario, ScenarioSpec};
use mrptv::tables;

#[derive(Parser)]
#[command(
    name = "mrptv",
    version,
    about = "Mixed-reality particle tracking velocimetry: stereo frames in, 3D velocity vectors out"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

fn scenario_help() -> String {
    Scenario::ALL
        .iter()
        .map(|s| format!("  {:<13} {}", s.name(), s.description()))
        .collect::<Vec<_>>()
        .join("\n")
}

#[derive(Subcommand)]
enum Command {
    /// Write a synthetic recording with ground truth (OUT/truth.csv) and a suggested OUT/mrptv.toml.
    #[command(after_help = format!("Scenarios:\n{}", scenario_help()))]
    Synth {
        /// Scenario name (see below).
        scenario: Scenario,
        /// Output recording directory (created; must be empty or absent).
        out: PathBuf,
        /// Number of frames [default: the scenario's].
        #[arg(long)]
        frames: Option<usize>,
        /// Number of particles in the domain [default: the scenario's].
        #[arg(long)]
        particles: Option<usize>,
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
    /// Process a recording: write velocity vectors (tracks.csv) and optionally every matched particle.
    Process {
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
    },
    /// Score a tracks.csv against a truth.csv.
    Eval {
        truth: PathBuf,
        tracks: PathBuf,
        /// Association radius, metres.
        #[arg(long, default_value_t = 0.02)]
        radius: f64,
        /// Outlier threshold as a fraction of the mean speed.
        #[arg(long, default_value_t = 0.2)]
        outlier_fraction: f64,
        /// M of the velocity window, for the measurable yield (particles living +-M frames).
        #[arg(long, default_value_t = 0)]
        window: u64,
        /// Machine-readable output.
        #[arg(long)]
        json: bool,
    },
    /// Run a synthetic scenario through the engine in memory and print its accuracy (no files, no headset).
    #[command(after_help = format!("Scenarios:\n{}", scenario_help()))]
    Demo {
        #[arg(default_value = "flume")]
        scenario: Scenario,
        #[arg(long)]
        frames: Option<usize>,
        #[arg(long)]
        particles: Option<usize>,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Use the published method's choices instead of mrptv's defaults.
        #[arg(long)]
        method: bool,
    },
    /// Print the default processing config as TOML (every key, with mrptv's defaults).
    Config {
        /// Print the published method's choices instead.
        #[arg(long)]
        method: bool,
    },
}

fn progress_bar(len: usize, what: &str) -> ProgressBar {
    let bar = ProgressBar::new(len as u64);
    let style = ProgressStyle::with_template(
        "{msg:>10} [{bar:40}] {pos}/{len} frames, {per_sec}, eta {eta}",
    )
    .unwrap_or_else(|_| ProgressStyle::default_bar())
    .progress_chars("=> ");
    bar.set_style(style);
    bar.set_message(what.to_string());
    bar
}

fn create_output(path: &Path) -> Result<BufWriter<fs::File>> {
    Ok(BufWriter::new(fs::File::create(path).with_context(
        || format!("cannot create {}", path.display()),
    )?))
}

fn main() -> std::process::ExitCode {
    match run(Cli::parse()) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Synth {
            scenario,
            out,
            frames,
            particles,
            seed,
        } => {
            if out.exists()
                && fs::read_dir(&out)
                    .map(|mut d| d.next().is_some())
                    .unwrap_or(true)
            {
                bail!(
                    "{} exists and is not empty; choose a new directory",
                    out.display()
                );
            }
            let spec = ScenarioSpec::new(scenario);
            let frames = frames.unwrap_or(spec.default_frames);
            let particles = particles.unwrap_or(spec.default_particles);
            if frames == 0 {
                bail!("--frames must be at least 1");
            }
            let bar = progress_bar(frames, "synth");
            let summary = offline::write_synthetic(spec, &out, frames, particles, seed, |n| {
                bar.set_position(n as u64)
            })?;
            bar.finish_and_clear();
            println!(
                "wrote {} frames of '{scenario}' ({particles} particles, seed {seed}) to {}; {:.1} % of particle-frames visible in both cameras",
                summary.frames,
                out.display(),
                100.0 * summary.visible_fraction
            );
            println!(
                "next: mrptv process {0} --out tracks.csv && mrptv eval {0}/truth.csv tracks.csv",
                out.display()
            );
        }
        Command::Process {
            rec,
            out,
            points,
            config,
            method,
        } => {
            let recording = Recording::open(&rec)?;
            let config = load_config(&rec, config.as_deref(), method)?;
            let mut tracks = create_output(&out)?;
            let mut points_file = points.as_deref().map(create_output).transpose()?;
            let bar = progress_bar(recording.frames.len(), "process");
            let totals = offline::process_recording(
                &recording,
                config,
                ProcessSinks {
                    tracks: Sink {
                        path: &out,
                        writer: &mut tracks,
                    },
                    points: match (points.as_deref(), points_file.as_mut()) {
                        (Some(path), Some(file)) => Some(Sink { path, writer: file }),
                        _ => None,
                    },
                },
                |n| bar.set_position(n as u64),
            )
            .with_context(|| format!("processing {}", rec.display()))?;
            bar.finish_and_clear();
            eprintln!(
                "{} frames: {:.1} detections/image, {:.1} matches/frame, {} vectors ({} rejected as rough) -> {}; pipeline {:.0} frames/s",
                totals.frames,
                (totals.detections_left + totals.detections_right) as f64 / (2 * totals.frames.max(1)) as f64,
                totals.matches as f64 / totals.frames.max(1) as f64,
                totals.vectors,
                totals.rejected,
                out.display(),
                totals.frames as f64 / totals.pipeline_s.max(1e-9)
            );
        }
        Command::Eval {
            truth,
            tracks,
            radius,
            outlier_fraction,
            window,
            json,
        } => {
            if !(radius > 0.0 && radius.is_finite()) {
                bail!("--radius must be a positive number of metres");
            }
            let truth = tables::read_truth(&truth)?;
            let tracks = tables::read_tracks(&tracks)?;
            let report = evaluate(
                &truth,
                &tracks,
                &EvalOptions {
                    radius_m: radius,
                    outlier_fraction,
                    window_frames: window,
                    ..Default::default()
                },
            )?;
            if json {
                println!("{}", serde_json::to_string_pretty(&report)?);
            } else {
                print!("{report}");
            }
        }
        Command::Demo {
            scenario,
            frames,
            particles,
            seed,
            method,
        } => {
            let spec = ScenarioSpec::new(scenario);
            let frames = frames.unwrap_or(spec.default_frames);
            let particles = particles.unwrap_or(spec.default_particles);
            let config = if method {
                method_config(&spec.config)
            } else {
                spec.config.clone()
            };
            if frames == 0 {
                bail!("--frames must be at least 1");
            }
            println!("scenario '{scenario}': {}", scenario.description());
            println!(
                "{frames} frames, {particles} particles, seed {seed}, {} config",
                if method { "published-method" } else { "mrptv" }
            );
            let bar = progress_bar(frames, "demo");
            let eval = EvalOptions {
                window_frames: config.velocity.half_window_frames as u64,
                ..Default::default()
            };
            let run = offline::run_in_memory(spec, config, frames, particles, seed, &eval, |n| {
                bar.set_position(n as u64)
            })?;
            bar.finish_and_clear();
            println!(
                "engine: {:.0} stereo frames/s on one thread, {:.1} matches/frame, {} vectors\n",
                run.totals.frames as f64 / run.totals.pipeline_s.max(1e-9),
                run.totals.matches as f64 / run.totals.frames.max(1) as f64,
                run.totals.vectors
            );
            print!("{}", run.report);
        }
        Command::Config { method } => {
            let config = if method {
                PipelineConfig::method()
            } else {
                PipelineConfig::default()
            };
            print!("{}", mrptv::config::to_toml(&config));
        }
    }
    Ok(())
}

/// The published method's choices, keeping a scenario's scale parameters (M, H, contrast).
fn method_config(base: &PipelineConfig) -> PipelineConfig {
    let mut c = PipelineConfig::method();
    c.velocity.half_window_frames = base.velocity.half_window_frames;
    c.link.box_half_side_px = base.link.box_half_side_px;
    c.detect.contrast_c = base.detect.contrast_c;
    c
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
