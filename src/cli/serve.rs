//! `mrptv serve`: the live host service, optionally with a built-in synthetic headset.

use std::net::SocketAddr;
use std::path::PathBuf;

use anyhow::{Context, Result};

use mrptv::client::{self, ReplayOptions, SyntheticSource};
use mrptv::protocol::Encoding;
use mrptv::rerun_log::{start_proxy, RerunOptions};
use mrptv::server::{self, FieldOptions, ServerOptions};
use mrptv::tls::ServerTls;
use mrptv_engine::field::StreamField;
use mrptv_engine::synth::{Scenario, ScenarioSpec};
use mrptv_engine::PipelineConfig;

use super::args::{
    lan_address, setup_tls, ConfigChoices, ConfigFile, GuardArgs, RerunArgs, TlsArgs,
};
use super::{init_logging, runtime, termination};

// A server's config, volume and Rerun logs are its sessions'; it logs every session, so its
// images are off by default.
#[derive(clap::Args)]
#[command(
    mut_arg("config", |a| a.help(
        "TOML config for sessions whose hello brings none [default: built-in defaults]"
    )),
    mut_arg("method", |a| a.help(
        "Use the published method's choices as the sessions' default config"
    )),
    mut_arg("depth_range", |a| a.help(
        "The measurement volume's depths, metres along the cameras' common viewing direction: \
         NEAR..FAR (FAR may be inf) for sessions whose hello brings no config [default: every \
         depth both cameras see]"
    )),
    mut_arg("rerun", |a| a.help(
        "Log every session to Rerun: file:DIR (one .rrd per session), connect (a viewer on \
         this machine) or connect:URL. Repeat for several"
    )),
    mut_arg("rerun_images_every", |a| a.default_value("0")),
)]
pub struct Args {
    /// Address to listen on.
    #[arg(long, default_value = "127.0.0.1:8770")]
    bind: SocketAddr,
    /// Also run a built-in synthetic headset, looping, so vectors flow without hardware.
    #[arg(long)]
    demo: bool,
    /// Scenario the demo headset streams.
    #[arg(long, default_value = "flume")]
    demo_scenario: Scenario,
    /// How the demo headset sends its images: raw8, png, or sparse (what a headset's Wi-Fi
    /// carries: protocol/README.md, Image encodings).
    #[arg(long, default_value = "raw8")]
    demo_encoding: Encoding,
    /// Record every session's incoming frames as a recording directory under DIR.
    #[arg(long, value_name = "DIR")]
    record: Option<PathBuf>,
    #[command(flatten)]
    config: ConfigFile,
    #[command(flatten)]
    choices: ConfigChoices,
    /// Frames a session may queue before the oldest is dropped.
    #[arg(long, default_value_t = ServerOptions::default().queue_frames)]
    queue_frames: usize,
    #[command(flatten)]
    rerun: RerunArgs,
    /// Each session's mean-flow field (`field` messages to viewers): cell size, metres
    /// [default: a tenth of the volume the session's first 500 vectors span, rounded].
    #[arg(long, value_name = "M")]
    field_cell: Option<f64>,
    /// Forget field samples older than this many seconds [default: keep the whole session].
    #[arg(long, value_name = "S")]
    field_window: Option<f64>,
    /// Seconds between a session's `field` messages, at least.
    #[arg(long, value_name = "S", default_value_t = 1.0)]
    field_interval: f64,
    #[command(flatten)]
    tls: TlsArgs,
    #[command(flatten)]
    guard: GuardArgs,
}

/// What the banner and the demo headset need to know of the secrets.
struct Secrets {
    /// The demo headset presents it.
    ingest: Option<String>,
    watch: bool,
}

pub fn run(args: Args) -> Result<()> {
    let tls = args.tls.source(args.bind);
    let config = match &args.config.config {
        Some(path) => mrptv::config::load(path)?,
        None => PipelineConfig::default(),
    };
    let config = args.choices.apply(config);
    StreamField::new(args.field_cell, args.field_window)?;
    anyhow::ensure!(
        args.field_interval.is_finite() && args.field_interval >= 0.0,
        "--field-interval {}: must be a non-negative number of seconds",
        args.field_interval
    );
    let mut options = ServerOptions {
        field: FieldOptions {
            cell_m: args.field_cell,
            window_s: args.field_window,
            interval: std::time::Duration::from_secs_f64(args.field_interval),
            ..Default::default()
        },
        config,
        queue_frames: args.queue_frames,
        record_dir: args.record,
        rerun: (!args.rerun.rerun.is_empty()).then(|| RerunOptions {
            sinks: args.rerun.rerun,
            images_every: args.rerun.rerun_images_every,
            ..Default::default()
        }),
        ..Default::default()
    };
    init_logging("info");
    let secrets = Secrets {
        ingest: args.guard.ingest_secret.clone(),
        watch: args.guard.watch_secret.watch_secret.is_some(),
    };
    args.guard.apply(&mut options)?;
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
    let demo = args
        .demo
        .then_some((args.demo_scenario, args.demo_encoding));
    runtime()?.block_on(serve(args.bind, options, tls, demo, secrets))?;
    drop(proxy);
    Ok(())
}

async fn serve(
    bind: SocketAddr,
    mut options: ServerOptions,
    tls: Option<ServerTls>,
    demo: Option<(Scenario, Encoding)>,
    secrets: Secrets,
) -> Result<()> {
    let listener = tokio::net::TcpListener::bind(bind)
        .await
        .with_context(|| format!("cannot listen on {bind}"))?;
    let addr = listener.local_addr()?;
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let scheme = if tls.is_some() {
        Scheme::SECURE
    } else {
        Scheme::PLAIN
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
    print_banner(addr, scheme, &options, secrets.watch);
    let demo_task = demo.map(|(scenario, encoding)| {
        let spec = ScenarioSpec::new(scenario);
        println!(
            "  demo: a synthetic headset streams '{scenario}' at {:.0} Hz as {encoding:?} images, looping ({})",
            1.0 / spec.frame_interval_s,
            scenario.description()
        );
        let options = ReplayOptions {
            client_name: format!("mrptv demo ({scenario})"),
            // No config in hello: the session runs on the server's, as a headset's does.
            config: None,
            keep_batches: false,
            tls: demo_tls,
            secret: secrets.ingest,
            ..ReplayOptions::new(format!("{}://{}/v1/ingest", scheme.ws, loopback_of(addr)))
        };
        let stop = stop_rx.clone();
        tokio::spawn(async move {
            let source = SyntheticSource::new(spec, 1, None, encoding);
            match client::replay(source, &options, stopped(stop), |_| {}).await {
                // The target is the binary's name: log filters and readers need not know the
                // CLI's module layout.
                Ok(r) => {
                    tracing::info!(target: "mrptv", frames = r.frames_sent, "demo headset stopped")
                }
                Err(e) => tracing::error!(target: "mrptv", "demo headset: {e}"),
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

async fn stopped(mut rx: tokio::sync::watch::Receiver<bool>) {
    let _ = rx.wait_for(|stop| *stop).await;
}

#[derive(Clone, Copy)]
struct Scheme {
    http: &'static str,
    ws: &'static str,
}

impl Scheme {
    const PLAIN: Scheme = Scheme {
        http: "http",
        ws: "ws",
    };
    const SECURE: Scheme = Scheme {
        http: "https",
        ws: "wss",
    };
}

/// Where observers, headsets and viewers connect.
fn print_banner(addr: SocketAddr, scheme: Scheme, options: &ServerOptions, watch_secret: bool) {
    let Scheme { http, ws } = scheme;
    println!(
        "mrptv {} listening on {http}://{addr}",
        env!("CARGO_PKG_VERSION")
    );
    let token = if watch_secret {
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
}

/// Where a client on this host reaches a server bound to `addr` (a wildcard bind included).
fn loopback_of(addr: SocketAddr) -> SocketAddr {
    if addr.ip().is_unspecified() {
        SocketAddr::new(std::net::Ipv4Addr::LOCALHOST.into(), addr.port())
    } else {
        addr
    }
}
