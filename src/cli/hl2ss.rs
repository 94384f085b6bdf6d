//! `mrptv hl2ss`: a HoloLens 2 running the hl2ss app streamed to a server as a headset session,
//! optionally with the vectors drawn back into the wearer's view.

use std::path::PathBuf;

use anyhow::{bail, Context, Result};

use mrptv::client::{self, Rate, ReplayOptions, ReplayReport};
use mrptv::hl2ss::bridge::{calibrate, BridgeCounters, Hl2ssEndpoints, Hl2ssSource};
use mrptv::hl2ss::clock::FrameClock;
use mrptv::hl2ss::holograms::{self, HologramContent, Painter};
use mrptv::hl2ss::VlcCodec;
use mrptv::protocol::Convention;

use super::args::{CaCert, IngestSecret, IngestUrl, JsonOutput, WatchSecret};
use super::replay::{print_replay, write_batches};
use super::{init_logging, runtime, termination};

#[derive(clap::Args)]
#[command(
    mut_arg("url", |a| a.help("The mrptv server's headset endpoint")),
    mut_arg("ca_cert", |a| a.help("For wss:// URLs: also trust the certificates in this PEM file")),
    mut_arg("watch_secret", |a| a.help(
        "With --holograms, the server's watch secret (vectors are followed as a viewer)"
    )),
)]
pub struct Args {
    /// The HoloLens's address.
    #[arg(long)]
    host: String,
    /// hl2ss's LeftFront visible-light camera port.
    #[arg(long, default_value_t = mrptv::hl2ss::LEFT_FRONT_PORT)]
    left_port: u16,
    /// hl2ss's RightFront visible-light camera port.
    #[arg(long, default_value_t = mrptv::hl2ss::RIGHT_FRONT_PORT)]
    right_port: u16,
    #[command(flatten)]
    url: IngestUrl,
    /// Left and right frames further apart than this are not a pair, milliseconds.
    #[arg(long, default_value_t = 5.0)]
    pair_tolerance_ms: f64,
    /// Which clock times the frames: sensor (the cameras' own `sensor_ticks`, exact exposure
    /// times; poses at each exposure's fitted host time) or host (the host ticks as sent, which
    /// jitter by a millisecond or more per camera).
    #[arg(long, value_enum, default_value_t = FrameClock::Sensor)]
    frame_clock: FrameClock,
    /// Fit the lens model to every N-th pixel of the calibration tables, each way.
    #[arg(long, default_value_t = 8)]
    fit_step: usize,
    /// Write the refined vectors received: frame,t_s,track_id,x,y,z,u,v,w (hl2ss's world).
    #[arg(long)]
    out: Option<PathBuf>,
    #[command(flatten)]
    secret: IngestSecret,
    #[command(flatten)]
    ca_cert: CaCert,
    /// Draw in the wearer's view through hl2ss's Unity plugin (its message queue must be
    /// running: the hl2ss Unity app, not the plain one): the live vectors, or with
    /// `--holograms field` the session's mean-flow field (an arrow per grid cell).
    #[arg(long, value_name = "WHAT", num_args = 0..=1, default_missing_value = "vectors")]
    holograms: Option<HologramContent>,
    /// The Unity plugin's message-queue port.
    #[arg(long, default_value_t = holograms::MESSAGE_QUEUE_PORT)]
    mq_port: u16,
    /// Hologram updates per second, at most (each is one display list).
    #[arg(long, default_value_t = 10.0)]
    hologram_rate: f64,
    /// Arrows in the wearer's view, at most (created once, then reused).
    #[arg(long, default_value_t = 150)]
    hologram_arrows: usize,
    #[command(flatten)]
    watch_secret: WatchSecret,
    #[command(flatten)]
    output: JsonOutput,
    /// How hl2ss sends the images: raw (uncompressed, 74 Mbit/s a camera: a wired or very good
    /// link) or h264 (compressed on the HoloLens: Wi-Fi). hevc, hl2ss's own default, is refused:
    /// this build has no HEVC decoder.
    #[arg(long, default_value = "raw")]
    codec: VlcCodec,
    /// With --codec h264: the bitrate hl2ss encodes each camera at, Mbit/s (README: what each
    /// costs in accuracy).
    #[arg(long, default_value_t = 2.5, value_name = "MBIT_PER_S")]
    bitrate_mbps: f64,
}

pub fn run(args: Args) -> Result<()> {
    if !(args.hologram_rate.is_finite() && args.hologram_rate > 0.0 && args.hologram_rate <= 60.0) {
        bail!("--hologram-rate must be between 0 and 60 updates a second");
    }
    let pair_tolerance_ms = args.pair_tolerance_ms;
    if !(pair_tolerance_ms.is_finite() && pair_tolerance_ms > 0.0 && pair_tolerance_ms <= 1000.0) {
        bail!("--pair-tolerance-ms must be between 0 and 1000, not {pair_tolerance_ms}");
    }
    let (codec, bitrate_mbps) = (args.codec, args.bitrate_mbps);
    if codec == VlcCodec::Hevc {
        bail!("--codec hevc: this build decodes H.264 only (OpenH264); use --codec h264 (or raw)");
    }
    if !(bitrate_mbps.is_finite() && (0.1..=100.0).contains(&bitrate_mbps)) {
        bail!("--bitrate-mbps must be between 0.1 and 100, not {bitrate_mbps}");
    }
    init_logging("warn");
    let endpoints = Hl2ssEndpoints {
        host: args.host.clone(),
        left_port: args.left_port,
        right_port: args.right_port,
        connect_timeout: std::time::Duration::from_secs(10),
    };
    let rig = calibrate(&endpoints, args.fit_step)?;
    // Before any frame: a missing Unity plugin is said at once.
    let painter = if args.holograms.is_some() {
        Some(Painter::connect(
            &endpoints.host,
            args.mq_port,
            args.hologram_arrows,
            args.hologram_rate,
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
    let source = match Hl2ssSource::open(
        &endpoints,
        rig,
        std::time::Duration::from_secs_f64(pair_tolerance_ms / 1e3),
        args.frame_clock,
        codec,
        (bitrate_mbps * 1e6) as u32,
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
        keep_batches: args.out.is_some(),
        tls: args.ca_cert.client_tls()?,
        secret: args.secret.secret,
        ..ReplayOptions::new(args.url.url.clone())
    };
    let painter = painter.map(|p| (p, args.holograms.unwrap_or_default()));
    let (report, painted) = stream(source, &options, painter, args.watch_secret.watch_secret)?;
    let report = report.with_context(|| format!("streaming to {}", args.url.url))?;
    let painted = match painted {
        Some(Ok(p)) => Some((p.updates, p.refused)),
        Some(Err(e)) => {
            eprintln!("holograms: {e}");
            None
        }
        None => None,
    };
    if let Some(path) = &args.out {
        write_batches(path, &report.refined)?;
    }
    let bridge = *counters.lock().unwrap_or_else(|p| p.into_inner());
    print_summary(&bridge, report, painted, args.output.json)
}

type Streamed = (
    Result<ReplayReport, client::ClientError>,
    Option<Result<Painter, String>>,
);

/// Streams the pairs to the server until the cameras end or Ctrl-C; with a painter, follows the
/// session's vectors as a viewer and draws them until the stream ends.
fn stream(
    source: Hl2ssSource,
    options: &ReplayOptions,
    painter: Option<(Painter, HologramContent)>,
    watch_secret: Option<String>,
) -> Result<Streamed> {
    let watch_url = options.url.replace("/v1/ingest", "/v1/watch");
    Ok(runtime()?.block_on(async {
        let (done_tx, done_rx) = tokio::sync::watch::channel(false);
        let painting = painter.map(|(painter, content)| {
            let mut done = done_rx.clone();
            tokio::spawn(holograms::follow_and_paint(
                watch_url,
                watch_secret,
                options.tls.clone(),
                options.client_name.clone(),
                content,
                painter,
                async move {
                    let _ = done.wait_for(|d| *d).await;
                },
            ))
        });
        let report = client::replay(source, options, termination(), |_| {}).await;
        let _ = done_tx.send(true);
        let painted = match painting {
            Some(task) => Some(task.await.map_err(|e| e.to_string()).and_then(|r| r)),
            None => None,
        };
        (report, painted)
    }))
}

fn print_summary(
    bridge: &BridgeCounters,
    report: ReplayReport,
    painted: Option<(u64, u64)>,
    json: bool,
) -> Result<()> {
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
    Ok(())
}
