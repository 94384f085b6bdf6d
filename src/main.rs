//! `mrptv`: the command-line edge. Parses arguments, shows progress, reports errors; the work
//! itself lives in the library (`mrptv::offline`).

use std::fs;
use std::io::BufWriter;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::{Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};

use mrptv::client::{self, Rate, RecordingSource, ReplayOptions, ReplayReport, SyntheticSource};
use mrptv::eval::{evaluate, EvalOptions};
use mrptv::offline::{self, ProcessSinks, Sink};
use mrptv::protocol::{Convention, Encoding};
use mrptv::ptv::PipelineConfig;
use mrptv::recording::Recording;
use mrptv::rerun_log::{start_proxy, RerunLogger, RerunOptions, RerunSink};
use mrptv::server::{self, ServerOptions};
use mrptv::synth::{Scenario, ScenarioSpec};
use mrptv::tables;
use mrptv::tls::{CertificateOrigin, CertificateSource, ServerTls};

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

/// Access control and limits of `serve` (defaults: `ServerOptions::default()`).
#[derive(clap::Args)]
#[command(next_help_heading = "Access and limits")]
struct GuardArgs {
    /// Secret headsets must present (Authorization: Bearer, or ?token=). Prefer the environment
    /// variable: command lines are visible to other users of this machine.
    #[arg(
        long,
        env = "MRPTV_INGEST_SECRET",
        hide_env_values = true,
        value_name = "SECRET"
    )]
    ingest_secret: Option<String>,
    /// Secret viewers (the observer page: ?token=SECRET) and /v1/sessions must present.
    #[arg(
        long,
        env = "MRPTV_WATCH_SECRET",
        hide_env_values = true,
        value_name = "SECRET"
    )]
    watch_secret: Option<String>,
    /// Connections open at once; more are closed on accept.
    #[arg(long, default_value_t = ServerOptions::default().max_connections, value_name = "N")]
    max_connections: usize,
    /// Live sessions at once.
    #[arg(long, default_value_t = ServerOptions::default().max_sessions, value_name = "N")]
    max_sessions: usize,
    /// Viewers per session.
    #[arg(long, default_value_t = ServerOptions::default().max_viewers_per_session, value_name = "N")]
    max_viewers: usize,
    /// Largest image width or height, pixels.
    #[arg(long, default_value_t = ServerOptions::default().max_image_side, value_name = "PIXELS")]
    max_image_size: u32,
    /// Frames per second a session takes (bursts of one second's worth pass); 0: no limit.
    #[arg(long, default_value_t = ServerOptions::default().max_frame_rate_hz, value_name = "HZ")]
    max_frame_rate: f64,
    /// Largest WebSocket message, MiB (a raw8 stereo frame of 640x480 is 0.6 MiB).
    #[arg(long, default_value_t = ServerOptions::default().max_message_bytes >> 20, value_name = "MIB")]
    max_message_mib: usize,
    /// Seconds a client has for its TLS handshake, its HTTP request, and a headset its hello.
    #[arg(long, default_value_t = ServerOptions::default().handshake_timeout.as_secs_f64(), value_name = "S")]
    handshake_timeout: f64,
    /// Seconds of silence (not even a pong to the server's pings) before a connection is closed.
    #[arg(long, default_value_t = ServerOptions::default().idle_timeout.as_secs_f64(), value_name = "S")]
    idle_timeout: f64,
}

impl GuardArgs {
    fn apply(self, options: &mut ServerOptions) -> Result<()> {
        let seconds = |what: &str, s: f64| {
            if s.is_finite() && s > 0.0 && s < 1e6 {
                Ok(std::time::Duration::from_secs_f64(s))
            } else {
                bail!("--{what} must be a positive number of seconds, not {s}")
            }
        };
        if !(self.max_frame_rate.is_finite() && self.max_frame_rate >= 0.0) {
            bail!(
                "--max-frame-rate must be 0 (no limit) or a positive rate, not {}",
                self.max_frame_rate
            );
        }
        if self.max_message_mib == 0 || self.max_message_mib > 1024 {
            bail!(
                "--max-message-mib must be 1 to 1024, not {}",
                self.max_message_mib
            );
        }
        options.access = server::access::AccessControl::new(
            self.ingest_secret.as_deref(),
            self.watch_secret.as_deref(),
        )?;
        options.max_connections = self.max_connections;
        options.max_sessions = self.max_sessions;
        options.max_viewers_per_session = self.max_viewers;
        options.max_image_side = self.max_image_size;
        options.max_frame_rate_hz = self.max_frame_rate;
        options.max_message_bytes = self.max_message_mib << 20;
        options.handshake_timeout = seconds("handshake-timeout", self.handshake_timeout)?;
        options.idle_timeout = seconds("idle-timeout", self.idle_timeout)?;
        Ok(())
    }
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
        /// Log the run to Rerun: file:RUN.rrd, connect (a viewer on this machine) or
        /// connect:URL. Repeat for several.
        #[arg(long, value_name = "SINK")]
        rerun: Vec<RerunSink>,
        /// With --rerun: log the camera images every N frames (0: never).
        #[arg(long, default_value_t = 10, value_name = "N")]
        rerun_images_every: u64,
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
    /// Run the live host service: headsets stream stereo frames over WebSocket, 3D vectors stream back.
    #[command(
        after_help = "Protocol: protocol/README.md. Logs: RUST_LOG=debug (per-frame: trace)."
    )]
    Serve {
        /// Address to listen on.
        #[arg(long, default_value = "127.0.0.1:8770")]
        bind: SocketAddr,
        /// Also run a built-in synthetic headset, looping, so vectors flow without hardware.
        #[arg(long)]
        demo: bool,
        /// Scenario the demo headset streams.
        #[arg(long, default_value = "flume")]
        demo_scenario: Scenario,
        /// Record every session's incoming frames as a recording directory under DIR.
        #[arg(long, value_name = "DIR")]
        record: Option<PathBuf>,
        /// TOML config for sessions whose hello brings none [default: built-in defaults].
        #[arg(long)]
        config: Option<PathBuf>,
        /// Use the published method's choices as the sessions' default config.
        #[arg(long)]
        method: bool,
        /// Frames a session may queue before the oldest is dropped.
        #[arg(long, default_value_t = ServerOptions::default().queue_frames)]
        queue_frames: usize,
        /// Log every session to Rerun: file:DIR (one .rrd per session), connect (a viewer on
        /// this machine) or connect:URL. Repeat for several.
        #[arg(long, value_name = "SINK")]
        rerun: Vec<RerunSink>,
        /// With --rerun: log the camera images every N frames (0: never).
        #[arg(long, default_value_t = 0, value_name = "N")]
        rerun_images_every: u64,
        /// Serve HTTPS and WSS only (browsers give WebXR to secure pages only). Without
        /// --tls-cert: a self-signed certificate, generated once and kept in --tls-dir.
        #[arg(long)]
        tls: bool,
        /// PEM certificate chain to serve (implies --tls; needs --tls-key).
        #[arg(long, value_name = "PEM", requires = "tls_key")]
        tls_cert: Option<PathBuf>,
        /// PEM private key of --tls-cert.
        #[arg(long, value_name = "PEM", requires = "tls_cert")]
        tls_key: Option<PathBuf>,
        /// Where the self-signed certificate is kept [default: ~/.local/share/mrptv/tls].
        #[arg(long, value_name = "DIR")]
        tls_dir: Option<PathBuf>,
        /// Extra host name or IP address the self-signed certificate must cover (repeatable);
        /// localhost, this host's name and addresses are always in it.
        #[arg(long, value_name = "NAME")]
        tls_name: Vec<String>,
        #[command(flatten)]
        guard: GuardArgs,
    },
    /// Stream a recording to a server as a headset would; save the vectors; report latency and drops.
    Replay {
        /// Recording directory (rig.json, frames.csv, left/, right/).
        rec: PathBuf,
        #[arg(long, default_value = "ws://127.0.0.1:8770/v1/ingest")]
        url: String,
        /// "recorded" (the recording's timestamps), "max", or frames per second.
        #[arg(long, default_value = "recorded")]
        rate: Rate,
        /// With --rate max: frames sent but not yet answered, at most.
        #[arg(long, default_value_t = 2)]
        in_flight: usize,
        /// Image encoding on the wire: raw8 or png (the recording's files, sent as they are).
        #[arg(long, default_value = "raw8")]
        encoding: Encoding,
        /// Coordinate convention of the vectors received: opencv, unity or webxr.
        #[arg(long, default_value = "opencv")]
        convention: Convention,
        /// Write the refined (centred) vectors received: frame,t_s,track_id,x,y,z,u,v,w.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Write the causal vectors received, same columns.
        #[arg(long)]
        causal_out: Option<PathBuf>,
        /// TOML config to ask for [default: REC/mrptv.toml if present, else the server's].
        #[arg(long)]
        config: Option<PathBuf>,
        /// Run this many headsets at once, each streaming the recording on its own connection.
        #[arg(long, default_value_t = 1)]
        headsets: usize,
        /// For wss:// URLs: also trust the certificates in this PEM file (e.g. a server's
        /// self-signed cert.pem); the public web roots are always trusted.
        #[arg(long, value_name = "PEM")]
        ca_cert: Option<PathBuf>,
        /// Print the summary as JSON.
        #[arg(long)]
        json: bool,
        /// The server's ingest secret (see `serve --ingest-secret`).
        #[arg(
            long,
            env = "MRPTV_INGEST_SECRET",
            hide_env_values = true,
            value_name = "SECRET"
        )]
        secret: Option<String>,
    },
    /// Stream a HoloLens 2 running the hl2ss app to a server: its front cameras, calibration and
    /// poses, as a headset session.
    #[command(
        after_help = "hl2ss: github.com/jdibenes/hl2ss (the app must be running on the HoloLens)."
    )]
    Hl2ss {
        /// The HoloLens's address.
        #[arg(long)]
        host: String,
        /// hl2ss's LeftFront visible-light camera port.
        #[arg(long, default_value_t = mrptv::hl2ss::LEFT_FRONT_PORT)]
        left_port: u16,
        /// hl2ss's RightFront visible-light camera port.
        #[arg(long, default_value_t = mrptv::hl2ss::RIGHT_FRONT_PORT)]
        right_port: u16,
        /// The mrptv server's headset endpoint.
        #[arg(long, default_value = "ws://127.0.0.1:8770/v1/ingest")]
        url: String,
        /// Left and right frames further apart than this are not a pair, milliseconds.
        #[arg(long, default_value_t = 5.0)]
        pair_tolerance_ms: f64,
        /// Fit the lens model to every N-th pixel of the calibration tables, each way.
        #[arg(long, default_value_t = 8)]
        fit_step: usize,
        /// Write the refined vectors received: frame,t_s,track_id,x,y,z,u,v,w (hl2ss's world).
        #[arg(long)]
        out: Option<PathBuf>,
        /// The server's ingest secret (see `serve --ingest-secret`).
        #[arg(
            long,
            env = "MRPTV_INGEST_SECRET",
            hide_env_values = true,
            value_name = "SECRET"
        )]
        secret: Option<String>,
        /// For wss:// URLs: also trust the certificates in this PEM file.
        #[arg(long, value_name = "PEM")]
        ca_cert: Option<PathBuf>,
        /// Draw the live vectors in the wearer's view through hl2ss's Unity plugin (its message
        /// queue must be running: the hl2ss Unity app, not the plain one).
        #[arg(long)]
        holograms: bool,
        /// The Unity plugin's message-queue port.
        #[arg(long, default_value_t = mrptv::hl2ss_holograms::MESSAGE_QUEUE_PORT)]
        mq_port: u16,
        /// Hologram updates per second, at most (each is one display list).
        #[arg(long, default_value_t = 10.0)]
        hologram_rate: f64,
        /// Arrows in the wearer's view, at most (created once, then reused).
        #[arg(long, default_value_t = 150)]
        hologram_arrows: usize,
        /// With --holograms, the server's watch secret (vectors are followed as a viewer).
        #[arg(
            long,
            env = "MRPTV_WATCH_SECRET",
            hide_env_values = true,
            value_name = "SECRET"
        )]
        watch_secret: Option<String>,
        /// Print the summary as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Load-test `serve` on this machine: a server on 127.0.0.1, N synthetic headsets and M
    /// viewers for a while; reports frames processed and dropped, latency and server memory.
    Load {
        /// Headsets streaming at once.
        #[arg(long, default_value_t = 1)]
        headsets: usize,
        /// Viewers subscribed to every session.
        #[arg(long, default_value_t = 0)]
        viewers: usize,
        /// Stop after this many seconds.
        #[arg(long, default_value_t = 10.0)]
        seconds: f64,
        /// Or once each headset has sent this many frames.
        #[arg(long)]
        frames: Option<u64>,
        /// Frames per second per headset, or "max" (as fast as answered, 2 in flight).
        #[arg(long, default_value = "30")]
        rate: Rate,
        /// Scenario the headsets stream.
        #[arg(long, default_value = "flume")]
        scenario: Scenario,
        /// Print the report as JSON.
        #[arg(long)]
        json: bool,
        /// Further `serve` arguments, after `--` (e.g. -- --record DIR).
        #[arg(last = true)]
        serve_args: Vec<String>,
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
            rerun,
            rerun_images_every,
        } => {
            let recording = Recording::open(&rec)?;
            let config = load_config(&rec, config.as_deref(), method)?;
            let mut tracks = create_output(&out)?;
            let mut rerun = rerun;
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
                    rerun: logger.as_ref(),
                },
                |n| bar.set_position(n as u64),
            )
            .with_context(|| format!("processing {}", rec.display()))?;
            bar.finish_and_clear();
            if let Some(logger) = logger {
                let summary = logger.finish();
                eprintln!(
                    "rerun: {} frames logged to {}{}",
                    summary.frames_logged,
                    rerun
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
            if let Some(proxy) = proxy {
                println!(
                    "serving the Rerun log: rerun --connect {}   (Ctrl-C to stop)",
                    proxy.url()
                );
                runtime()?.block_on(termination());
            }
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
        Command::Serve {
            bind,
            demo,
            demo_scenario,
            record,
            config,
            method,
            queue_frames,
            rerun,
            rerun_images_every,
            tls,
            tls_cert,
            tls_key,
            tls_dir,
            tls_name,
            guard,
        } => {
            let tls = match (tls_cert, tls_key) {
                (Some(cert), Some(key)) => Some(CertificateSource::Files { cert, key }),
                _ if tls => Some(CertificateSource::SelfSigned {
                    dir: tls_dir.unwrap_or_else(mrptv::tls::default_self_signed_dir),
                    names: certificate_names(bind, tls_name),
                }),
                _ => None,
            };
            let config = match config {
                Some(path) => mrptv::config::load(&path)?,
                None => PipelineConfig::default(),
            };
            let options = ServerOptions {
                config: if method {
                    method_config(&config)
                } else {
                    config
                },
                queue_frames,
                record_dir: record,
                rerun: (!rerun.is_empty()).then(|| RerunOptions {
                    sinks: rerun,
                    images_every: rerun_images_every,
                    ..Default::default()
                }),
                ..Default::default()
            };
            init_logging("info");
            let mut options = options;
            let secrets = Secrets {
                ingest: guard.ingest_secret.clone(),
                watch: guard.watch_secret.is_some(),
            };
            guard.apply(&mut options)?;
            // Kept alive while the server runs: one Rerun gRPC server for every session.
            let proxy = match options.rerun.as_mut() {
                Some(r) => start_proxy(&mut r.sinks)?,
                None => None,
            };
            if let Some(proxy) = &proxy {
                println!(
                    "  rerun: viewers connect with `rerun --connect {}`",
                    proxy.url()
                );
            }
            let tls = tls.map(|source| setup_tls(&source)).transpose()?;
            runtime()?.block_on(serve(
                bind,
                options,
                tls,
                demo.then_some(demo_scenario),
                secrets,
            ))?;
            drop(proxy);
        }
        Command::Replay {
            rec,
            url,
            rate,
            in_flight,
            encoding,
            convention,
            out,
            causal_out,
            config,
            headsets,
            ca_cert,
            json,
            secret,
        } => {
            init_logging("warn");
            let recording = Recording::open(&rec)?;
            let suggested = rec.join("mrptv.toml");
            let config = match config {
                Some(path) => Some(mrptv::config::load(&path)?),
                None if suggested.is_file() => Some(mrptv::config::load(&suggested)?),
                None => None,
            };
            if headsets == 0 {
                bail!("--headsets must be at least 1");
            }
            let options = ReplayOptions {
                rate,
                max_in_flight: in_flight,
                encoding,
                convention,
                config,
                keep_batches: out.is_some() || causal_out.is_some(),
                tls: match &ca_cert {
                    Some(path) => Some(mrptv::tls::client_config(Some(path))?),
                    None => None,
                },
                secret,
                ..ReplayOptions::new(url)
            };
            let reports = runtime()?.block_on(replay(&recording, &options, headsets))?;
            for (path, kind) in [(&out, "refined"), (&causal_out, "causal")] {
                if let Some(path) = path {
                    let mut file = create_output(path)?;
                    let batches = if kind == "refined" {
                        &reports[0].refined
                    } else {
                        &reports[0].causal
                    };
                    client::write_batches_csv(&mut file, batches)
                        .and_then(|()| std::io::Write::flush(&mut file))
                        .with_context(|| format!("writing {}", path.display()))?;
                }
            }
            print_replay(&reports, json)?;
        }
        Command::Hl2ss {
            host,
            left_port,
            right_port,
            url,
            pair_tolerance_ms,
            fit_step,
            out,
            secret,
            ca_cert,
            holograms,
            mq_port,
            hologram_rate,
            hologram_arrows,
            watch_secret,
            json,
        } => {
            if !(hologram_rate.is_finite() && hologram_rate > 0.0 && hologram_rate <= 60.0) {
                bail!("--hologram-rate must be between 0 and 60 updates a second");
            }
            if !(pair_tolerance_ms.is_finite()
                && pair_tolerance_ms > 0.0
                && pair_tolerance_ms <= 1000.0)
            {
                bail!("--pair-tolerance-ms must be between 0 and 1000, not {pair_tolerance_ms}");
            }
            init_logging("warn");
            let endpoints = mrptv::hl2ss_bridge::Hl2ssEndpoints {
                host,
                left_port,
                right_port,
                connect_timeout: std::time::Duration::from_secs(10),
            };
            let rig = mrptv::hl2ss_bridge::calibrate(&endpoints, fit_step)?;
            // Before any frame: a missing Unity plugin is said at once.
            let painter = if holograms {
                Some(mrptv::hl2ss_holograms::Painter::connect(
                    &endpoints.host,
                    mq_port,
                    hologram_arrows,
                    hologram_rate,
                )?)
            } else {
                None
            };
            for (camera, fit) in [("left", &rig.left_fit), ("right", &rig.right_fit)] {
                eprintln!(
                    "{camera} camera: lens model fitted to hl2ss's calibration over {} pixels: residual {:.4} px rms, {:.4} px max",
                    fit.pixels_used, fit.rms_px, fit.max_px
                );
            }
            let source = match mrptv::hl2ss_bridge::Hl2ssSource::open(
                &endpoints,
                rig,
                std::time::Duration::from_secs_f64(pair_tolerance_ms / 1e3),
            ) {
                Ok(source) => source,
                Err(e) => {
                    if let Some(mut painter) = painter {
                        let _ = painter.remove_all();
                    }
                    return Err(e.into());
                }
            };
            let counters = source.counters();
            let options = ReplayOptions {
                client_name: format!("mrptv hl2ss bridge ({})", endpoints.host),
                // hl2ss's world has WebXR's axes (see `opencv_from_hl2ss_world`).
                convention: Convention::WebXr,
                rate: Rate::Max,
                max_in_flight: 2,
                keep_batches: out.is_some(),
                tls: match &ca_cert {
                    Some(path) => Some(mrptv::tls::client_config(Some(path))?),
                    None => None,
                },
                secret,
                ..ReplayOptions::new(url.clone())
            };
            let watch_url = url.replace("/v1/ingest", "/v1/watch");
            let (report, painted) = runtime()?.block_on(async {
                let (done_tx, done_rx) = tokio::sync::watch::channel(false);
                let painting = painter.map(|painter| {
                    let mut done = done_rx.clone();
                    tokio::spawn(mrptv::hl2ss_holograms::follow_and_paint(
                        watch_url,
                        watch_secret,
                        options.tls.clone(),
                        options.client_name.clone(),
                        painter,
                        async move {
                            let _ = done.wait_for(|d| *d).await;
                        },
                    ))
                });
                let report = client::replay(source, &options, termination(), |_| {}).await;
                let _ = done_tx.send(true);
                let painted = match painting {
                    Some(task) => Some(task.await.map_err(|e| e.to_string()).and_then(|r| r)),
                    None => None,
                };
                (report, painted)
            });
            let report = report.with_context(|| format!("streaming to {url}"))?;
            let painted = match painted {
                Some(Ok(p)) => Some((p.updates, p.refused)),
                Some(Err(e)) => {
                    eprintln!("holograms: {e}");
                    None
                }
                None => None,
            };
            if let Some(path) = &out {
                let mut file = create_output(path)?;
                client::write_batches_csv(&mut file, &report.refined)
                    .and_then(|()| std::io::Write::flush(&mut file))
                    .with_context(|| format!("writing {}", path.display()))?;
            }
            let bridge = *counters.lock().unwrap_or_else(|p| p.into_inner());
            if json {
                println!(
                    "{}",
                    serde_json::json!({
                        "bridge": bridge,
                        "session": report.session,
                        "frames_sent": report.frames_sent,
                        "causal_vectors": report.causal_vectors,
                        "refined_vectors": report.refined_vectors,
                        "errors": report.errors.len(),
                        "frames_processed": report.counters.map(|c| c.frames_processed),
                        "hologram_updates": painted.map(|p| p.0),
                        "hologram_commands_refused": painted.map(|p| p.1),
                    })
                );
            } else {
                println!(
                    "hl2ss: {} left and {} right frames, {} pairs ({} left and {} right unpaired, {} without a pose)",
                    bridge.left_frames, bridge.right_frames, bridge.pairs, bridge.unpaired_left,
                    bridge.unpaired_right, bridge.unposed
                );
                print_replay(&[report], false)?;
                if let Some((updates, refused)) = painted {
                    println!("holograms: {updates} updates, {refused} commands refused");
                }
            }
        }
        Command::Load {
            headsets,
            viewers,
            seconds,
            frames,
            rate,
            scenario,
            json,
            serve_args,
        } => {
            if headsets == 0 {
                bail!("--headsets must be at least 1");
            }
            if !(seconds.is_finite() && seconds > 0.0 && seconds <= 86_400.0) {
                bail!("--seconds must be between 0 and 86400, not {seconds}");
            }
            init_logging("warn");
            let options = mrptv::load::LoadOptions {
                headsets,
                viewers,
                duration: std::time::Duration::from_secs_f64(seconds),
                frames_per_headset: frames,
                rate,
                scenario,
                ring_frames: 90,
                server_exe: std::env::current_exe().context("where is this mrptv binary?")?,
                server_args: serve_args,
            };
            let bar = ProgressBar::new(seconds.ceil() as u64);
            bar.set_style(
                ProgressStyle::with_template("{msg:>14} [{bar:40}] {pos}/{len} s")
                    .unwrap_or_else(|_| ProgressStyle::default_bar())
                    .progress_chars("=> "),
            );
            bar.set_message("load");
            let report = runtime()?.block_on(mrptv::load::run(&options, |elapsed, sent| {
                bar.set_position(elapsed as u64);
                bar.set_message(format!("{sent} frames"));
            }))?;
            bar.finish_and_clear();
            if json {
                println!("{}", serde_json::to_string(&report)?);
            } else {
                print_load(&report);
            }
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

fn runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")
}

/// Logs to stderr; RUST_LOG overrides `default` (e.g. RUST_LOG=mrptv=trace for per-frame logs).
fn init_logging(default: &str) {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .try_init();
}

/// Resolves on Ctrl-C or SIGTERM.
async fn termination() {
    let ctrl_c = async {
        if tokio::signal::ctrl_c().await.is_err() {
            std::future::pending::<()>().await;
        }
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {}
        _ = term => {}
    }
}

/// Names a self-signed certificate covers: loopback, this host's name (and its mDNS `.local`
/// name), the bind address or, for a wildcard bind, the address of the default route's
/// interface, and what the user adds.
fn certificate_names(bind: SocketAddr, extra: Vec<String>) -> Vec<String> {
    let mut names = vec!["localhost".to_string(), "127.0.0.1".into(), "::1".into()];
    if let Some(host) = host_name() {
        names.push(format!("{host}.local"));
        names.push(host);
    }
    if bind.ip().is_unspecified() {
        names.extend(lan_address().map(|ip| ip.to_string()));
    } else {
        names.push(bind.ip().to_string());
    }
    names.extend(extra);
    let mut seen = std::collections::BTreeSet::new();
    names.retain(|n| seen.insert(n.clone()));
    names
}

fn host_name() -> Option<String> {
    let name = std::fs::read_to_string("/etc/hostname")
        .ok()
        .or_else(|| std::env::var("COMPUTERNAME").ok())?;
    let name = name.trim();
    (!name.is_empty() && name != "localhost").then(|| name.to_string())
}

/// The address other devices on the network most likely reach this host at: the source address
/// of the default route (a UDP "connect" sends nothing).
fn lan_address() -> Option<std::net::IpAddr> {
    let socket = std::net::UdpSocket::bind("0.0.0.0:0").ok()?;
    socket.connect("192.0.2.1:9").ok()?;
    let ip = socket.local_addr().ok()?.ip();
    (!ip.is_unspecified() && !ip.is_loopback()).then_some(ip)
}

fn setup_tls(source: &CertificateSource) -> Result<ServerTls> {
    let tls = mrptv::tls::server_tls(source)?;
    match tls.origin {
        CertificateOrigin::Given => {
            println!("TLS: certificate {}", tls.cert_path.display())
        }
        CertificateOrigin::Generated => println!(
            "TLS: generated a self-signed certificate {} for {}",
            tls.cert_path.display(),
            tls.names.join(", ")
        ),
        CertificateOrigin::Reused => println!(
            "TLS: self-signed certificate {} (for {})",
            tls.cert_path.display(),
            tls.names.join(", ")
        ),
    }
    println!("  SHA-256 fingerprint {}", tls.fingerprint);
    if tls.origin != CertificateOrigin::Given {
        println!(
            "  browsers warn about a self-signed certificate: check that the fingerprint they show matches, then accept it"
        );
    }
    Ok(tls)
}

/// What the banner and the demo headset need to know of the secrets.
struct Secrets {
    /// The demo headset presents it.
    ingest: Option<String>,
    watch: bool,
}

async fn serve(
    bind: SocketAddr,
    mut options: ServerOptions,
    tls: Option<ServerTls>,
    demo: Option<Scenario>,
    secrets: Secrets,
) -> Result<()> {
    let listener = tokio::net::TcpListener::bind(bind)
        .await
        .with_context(|| format!("cannot listen on {bind}"))?;
    let addr = listener.local_addr()?;
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let stopped = |mut rx: tokio::sync::watch::Receiver<bool>| async move {
        let _ = rx.wait_for(|stop| *stop).await;
    };
    let (http, ws) = if tls.is_some() {
        ("https", "wss")
    } else {
        ("http", "ws")
    };
    // The demo headset trusts the server's own certificate.
    let demo_tls = match &tls {
        Some(t) => Some(mrptv::tls::client_config(Some(&t.cert_path))?),
        None => None,
    };
    options.tls = tls.map(|t| t.config);
    for warning in server::access::exposure_warnings(addr, &options.access, options.tls.is_some()) {
        eprintln!("warning: {warning}");
    }
    println!(
        "mrptv {} listening on {http}://{addr}",
        env!("CARGO_PKG_VERSION")
    );
    let token = if secrets.watch {
        "?token=WATCH_SECRET"
    } else {
        ""
    };
    println!("  observers: open {http}://{addr}/{token} in a browser");
    if addr.ip().is_unspecified() {
        if let Some(ip) = lan_address() {
            println!(
                "             from other devices: {http}://{}/{token}",
                SocketAddr::new(ip, addr.port())
            );
        }
    }
    if options.access.requires(server::access::Role::Ingest) {
        println!("  headsets present the ingest secret (Authorization: Bearer, or ?token=)");
    }
    println!("  headsets: {ws}://{addr}/v1/ingest");
    println!("  viewers:  {ws}://{addr}/v1/watch");
    println!("  sessions: {http}://{addr}/v1/sessions   health: {http}://{addr}/healthz");
    if let Some(dir) = &options.record_dir {
        println!("  recording every session under {}", dir.display());
    }
    let demo_task = demo.map(|scenario| {
        let spec = ScenarioSpec::new(scenario);
        println!(
            "  demo: a synthetic headset streams '{scenario}' at {:.0} Hz, looping ({})",
            1.0 / spec.frame_interval_s,
            scenario.description()
        );
        let options = ReplayOptions {
            client_name: format!("mrptv demo ({scenario})"),
            config: Some(spec.config.clone()),
            keep_batches: false,
            tls: demo_tls,
            secret: secrets.ingest,
            ..ReplayOptions::new(format!("{ws}://{}/v1/ingest", loopback_of(addr)))
        };
        let stop = stop_rx.clone();
        tokio::spawn(async move {
            let source = SyntheticSource::new(spec, 1, None, Encoding::Raw8);
            match client::replay(source, &options, stopped(stop), |_| {}).await {
                Ok(r) => tracing::info!(frames = r.frames_sent, "demo headset stopped"),
                Err(e) => tracing::error!("demo headset: {e}"),
            }
        })
    });
    println!("Ctrl-C to stop.");
    let server = tokio::spawn(server::run(listener, options, stopped(stop_rx)));
    termination().await;
    let _ = stop_tx.send(true);
    let report = server.await.context("server task")??;
    if let Some(task) = demo_task {
        let _ = task.await;
    }
    if report.connections_dropped == 0 {
        println!("stopped: every session closed");
    } else {
        println!(
            "stopped: every session's frames processed and recorded; {} connection(s) not reading were dropped without their bye",
            report.connections_dropped
        );
    }
    Ok(())
}

/// Where a client on this host reaches a server bound to `addr` (a wildcard bind included).
fn loopback_of(addr: SocketAddr) -> SocketAddr {
    if addr.ip().is_unspecified() {
        SocketAddr::new(std::net::Ipv4Addr::LOCALHOST.into(), addr.port())
    } else {
        addr
    }
}

async fn replay(
    recording: &Recording,
    options: &ReplayOptions,
    headsets: usize,
) -> Result<Vec<ReplayReport>> {
    let bar = progress_bar(recording.frames.len() * headsets, "replay");
    let runs = (0..headsets).map(|_| {
        let source = RecordingSource::new(recording.clone(), options.encoding);
        let bar = bar.clone();
        client::replay(source, options, termination(), move |_| bar.inc(1))
    });
    let reports = futures_util::future::join_all(runs).await;
    bar.finish_and_clear();
    reports
        .into_iter()
        .map(|r| r.with_context(|| format!("replaying to {}", options.url)))
        .collect()
}

fn print_load(r: &mrptv::load::LoadReport) {
    let ms = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.1}"));
    println!(
        "{} headset(s), {} viewer(s), {:.1} s: {} frames sent, {} processed ({:.1}/s), {} dropped, {} rejected",
        r.headsets, r.viewers, r.seconds, r.frames_sent, r.frames_processed, r.frames_per_second,
        r.frames_dropped, r.frames_rejected
    );
    println!(
        "latency (frame sent -> causal batch), ms: p50 {} p90 {} p99 {} max {}",
        ms(r.latency_ms_p50),
        ms(r.latency_ms_p90),
        ms(r.latency_ms_p99),
        ms(r.latency_ms_max)
    );
    if r.viewers > 0 {
        println!(
            "viewers: {} batches published, each viewer got {:.0} on average (fewest {})",
            r.batches_published, r.viewer_batches_mean, r.viewer_batches_min
        );
    }
    println!(
        "server memory (RSS): {:.1} MiB at start, {:.1} MiB at end, peak {:.1} MiB; {}",
        r.rss_start_mib,
        r.rss_end_mib,
        r.rss_peak_mib,
        if r.clean_exit {
            "clean exit on SIGTERM"
        } else {
            "did NOT exit cleanly"
        }
    );
}

fn print_replay(reports: &[ReplayReport], json: bool) -> Result<()> {
    let all = ReplayReport {
        latencies_s: reports.iter().flat_map(|r| r.latencies_s.clone()).collect(),
        ..Default::default()
    };
    let ms = |p: f64| all.latency_percentile_s(p).map(|s| s * 1e3);
    let sum = |f: &dyn Fn(&ReplayReport) -> u64| reports.iter().map(f).sum::<u64>();
    let counter = |f: &dyn Fn(&mrptv::protocol::Counters) -> u64| {
        reports
            .iter()
            .map(|r| r.counters.as_ref().map_or(0, f))
            .sum::<u64>()
    };
    let elapsed_s = reports.iter().map(|r| r.elapsed_s).fold(0.0, f64::max);
    let summary = serde_json::json!({
        "headsets": reports.len(),
        "sessions": reports.iter().map(|r| r.session.clone()).collect::<Vec<_>>(),
        "frames_sent": sum(&|r| r.frames_sent),
        "frames_processed": counter(&|c| c.frames_processed),
        "frames_dropped": counter(&|c| c.frames_dropped),
        "frames_rejected": counter(&|c| c.frames_rejected),
        "batches_dropped": counter(&|c| c.batches_dropped),
        "causal_vectors": sum(&|r| r.causal_vectors),
        "refined_vectors": sum(&|r| r.refined_vectors),
        "errors": reports.iter().map(|r| r.errors.len()).sum::<usize>(),
        "elapsed_s": elapsed_s,
        "frames_per_s": sum(&|r| r.frames_sent) as f64 / elapsed_s.max(1e-9),
        "latency_ms": {"p50": ms(50.0), "p90": ms(90.0), "p99": ms(99.0), "max": ms(100.0), "samples": all.latencies_s.len()},
        "mean_processing_ms": reports.iter().filter_map(|r| r.counters.map(|c| c.processing_ms_mean)).sum::<f64>() / reports.len() as f64,
    });
    if json {
        println!("{}", serde_json::to_string_pretty(&summary)?);
        return Ok(());
    }
    let f = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.1} ms"));
    println!(
        "{} headset(s), sessions {}: {} frames sent in {:.1} s ({:.1} frames/s)",
        reports.len(),
        summary["sessions"],
        summary["frames_sent"],
        elapsed_s,
        summary["frames_per_s"].as_f64().unwrap_or(0.0)
    );
    println!(
        "server: {} processed, {} dropped (queue full), {} rejected, {} batches undelivered; pipeline {:.2} ms/frame mean",
        summary["frames_processed"],
        summary["frames_dropped"],
        summary["frames_rejected"],
        summary["batches_dropped"],
        summary["mean_processing_ms"].as_f64().unwrap_or(0.0)
    );
    println!(
        "vectors received: {} causal, {} refined",
        summary["causal_vectors"], summary["refined_vectors"]
    );
    println!(
        "latency, frame sent -> causal vectors received ({} frames): p50 {}, p90 {}, p99 {}, max {}",
        all.latencies_s.len(),
        f(ms(50.0)),
        f(ms(90.0)),
        f(ms(99.0)),
        f(ms(100.0))
    );
    for r in reports {
        for (code, message) in r.errors.iter().take(5) {
            println!("  {}: server error {code:?}: {message}", r.session);
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
