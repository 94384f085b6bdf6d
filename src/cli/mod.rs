//! One module per subcommand, each with its `Args` (the flags, as clap declares them) and its
//! `run(Args)`, which turns them into the library's options and calls the library. Flags that
//! several commands share are declared once in [`args`]; what several commands do at the edge
//! (progress bars, output files, the async runtime, logging, signals) is here.

pub mod args;
pub mod config;
pub mod demo;
pub mod eval;
pub mod hl2ss;
pub mod load;
pub mod process;
pub mod replay;
pub mod serve;
pub mod synth;

use std::fs;
use std::io::BufWriter;
use std::path::Path;

use anyhow::{Context, Result};
use indicatif::{ProgressBar, ProgressStyle};

use mrptv_engine::synth::Scenario;

/// The scenario list shown below `synth --help` and `demo --help`.
pub fn scenario_help() -> String {
    let width = Scenario::ALL
        .iter()
        .map(|s| s.name().len())
        .max()
        .unwrap_or(0);
    Scenario::ALL
        .iter()
        .map(|s| format!("  {:<width$} {}", s.name(), s.description()))
        .collect::<Vec<_>>()
        .join("\n")
}

/// The config a run of recording `rec` uses: `--config`, else the recording's own, else the
/// defaults.
pub(crate) fn load_config(
    rec: &std::path::Path,
    file: &args::ConfigFile,
) -> Result<mrptv_engine::PipelineConfig> {
    match file.or_in_recording(rec) {
        Some(path) => {
            if file.config.is_none() {
                eprintln!("using {}", path.display());
            }
            Ok(mrptv::config::load(&path)?)
        }
        None => Ok(mrptv_engine::PipelineConfig::default()),
    }
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

/// What a run settled on and its health figures, then its warnings, on stderr.
fn print_health(health: &mrptv::offline::RunHealth) {
    eprintln!("settled: {}", health.settled);
    eprintln!("health: {}", health.summary);
    for warning in &health.warnings {
        eprintln!("warning: {warning}");
    }
}
