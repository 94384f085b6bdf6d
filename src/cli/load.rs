//! `mrptv load`: a bounded load test of a `serve` child process on this machine.

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};

use mrptv::client::Rate;
use mrptv::load::LoadReport;
use mrptv_engine::synth::Scenario;

use super::args::{Headsets, JsonOutput};
use super::{init_logging, runtime};

#[derive(clap::Args)]
#[command(mut_arg("json", |a| a.help("Print the report as JSON")))]
pub struct Args {
    #[command(flatten)]
    headsets: Headsets,
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
    #[command(flatten)]
    output: JsonOutput,
    /// Further `serve` arguments, after `--` (e.g. -- --record DIR).
    #[arg(last = true)]
    serve_args: Vec<String>,
}

pub fn run(args: Args) -> Result<()> {
    let headsets = args.headsets.count()?;
    let seconds = args.seconds;
    if !(seconds.is_finite() && seconds > 0.0 && seconds <= 86_400.0) {
        bail!("--seconds must be between 0 and 86400, not {seconds}");
    }
    init_logging("warn");
    let options = mrptv::load::LoadOptions {
        headsets,
        viewers: args.viewers,
        duration: std::time::Duration::from_secs_f64(seconds),
        frames_per_headset: args.frames,
        rate: args.rate,
        scenario: args.scenario,
        ring_frames: 90,
        server_exe: std::env::current_exe().context("where is this mrptv binary?")?,
        server_args: args.serve_args,
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
    if args.output.json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        print_load(&report);
    }
    Ok(())
}

fn print_load(r: &LoadReport) {
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
