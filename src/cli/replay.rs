//! `mrptv replay`: a recording streamed to a server as a headset would, with the vectors saved
//! and the latency and drops reported.

use std::path::PathBuf;

use anyhow::{Context, Result};

use mrptv::client::{self, Rate, RecordingSource, ReplayOptions, ReplayReport};
use mrptv::protocol::Convention;
use mrptv::recording::Recording;

use super::args::{
    CaCert, ConfigFile, Headsets, IngestSecret, IngestUrl, JsonOutput, WireEncoding,
};
use super::{create_output, init_logging, progress_bar, runtime, termination};

#[derive(clap::Args)]
#[command(
    mut_arg("config", |a| a.help(
        "TOML config to ask for [default: REC/mrptv.toml if present, else the server's]"
    )),
    mut_arg("headsets", |a| a.help(
        "Run this many headsets at once, each streaming the recording on its own connection"
    )),
)]
pub struct Args {
    /// Recording directory (rig.json, frames.csv, left/, right/).
    rec: PathBuf,
    #[command(flatten)]
    url: IngestUrl,
    /// "recorded" (the recording's timestamps), "max", or frames per second.
    #[arg(long, default_value = "recorded")]
    rate: Rate,
    /// With --rate max: frames sent but not yet answered, at most.
    #[arg(long, default_value_t = 2)]
    in_flight: usize,
    /// With a paced rate (recorded or Hz, as a live headset): frames unanswered at most; a
    /// frame that cannot go before a newer one is due is skipped, so a slow link costs frames,
    /// never a growing delay.
    #[arg(long, default_value_t = 8)]
    live_window: usize,
    #[command(flatten)]
    encoding: WireEncoding,
    /// Coordinate convention of the vectors received: opencv, unity or webxr.
    #[arg(long, default_value = "opencv")]
    convention: Convention,
    /// Write the refined (centred) vectors received: frame,t_s,track_id,x,y,z,u,v,w.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Write the causal vectors received, same columns.
    #[arg(long)]
    causal_out: Option<PathBuf>,
    #[command(flatten)]
    config: ConfigFile,
    #[command(flatten)]
    headsets: Headsets,
    #[command(flatten)]
    ca_cert: CaCert,
    #[command(flatten)]
    output: JsonOutput,
    #[command(flatten)]
    secret: IngestSecret,
}

pub fn run(args: Args) -> Result<()> {
    init_logging("warn");
    let recording = Recording::open(&args.rec)?;
    let config = match args.config.or_in_recording(&args.rec) {
        Some(path) => Some(mrptv::config::load(&path)?),
        None => None,
    };
    let headsets = args.headsets.count()?;
    let options = ReplayOptions {
        rate: args.rate,
        max_in_flight: args.in_flight,
        live_window: args.live_window,
        encoding: args.encoding.encoding,
        convention: args.convention,
        config,
        keep_batches: args.out.is_some() || args.causal_out.is_some(),
        tls: args.ca_cert.client_tls()?,
        secret: args.secret.secret,
        ..ReplayOptions::new(args.url.url)
    };
    let reports = runtime()?.block_on(replay(&recording, &options, headsets))?;
    for (path, batches) in [
        (&args.out, &reports[0].refined),
        (&args.causal_out, &reports[0].causal),
    ] {
        if let Some(path) = path {
            write_batches(path, batches)?;
        }
    }
    print_replay(&reports, args.output.json)
}

/// The vectors of `batches` as CSV: frame,t_s,track_id,x,y,z,u,v,w.
pub(super) fn write_batches(
    path: &std::path::Path,
    batches: &[mrptv::protocol::DecodedBatch],
) -> Result<()> {
    let mut file = create_output(path)?;
    client::write_batches_csv(&mut file, batches)
        .and_then(|()| std::io::Write::flush(&mut file))
        .with_context(|| format!("writing {}", path.display()))
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

/// The summary of one or more headsets' runs, as text or JSON.
pub(super) fn print_replay(reports: &[ReplayReport], json: bool) -> Result<()> {
    let all = ReplayReport {
        latencies_s: reports.iter().flat_map(|r| r.latencies_s.clone()).collect(),
        ..Default::default()
    };
    let ages = ReplayReport {
        latencies_s: reports.iter().flat_map(|r| r.ages_s.clone()).collect(),
        ..Default::default()
    };
    let ms = |p: f64| all.latency_percentile_s(p).map(|s| s * 1e3);
    let age_ms = |p: f64| ages.latency_percentile_s(p).map(|s| s * 1e3);
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
        "frames_skipped": sum(&|r| r.frames_skipped),
        "last_causal_frame": reports.iter().filter_map(|r| r.last_causal_frame).max(),
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
        "age_ms": {"p50": age_ms(50.0), "p90": age_ms(90.0), "p99": age_ms(99.0), "max": age_ms(100.0)},
        "mean_processing_ms": reports.iter().filter_map(|r| r.counters.map(|c| c.processing_ms_mean)).sum::<f64>() / reports.len() as f64,
    });
    if json {
        println!("{}", serde_json::to_string_pretty(&summary)?);
        return Ok(());
    }
    let f = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.1} ms"));
    println!(
        "{} headset(s), sessions {}: {} frames sent in {:.1} s ({:.1} frames/s), {} skipped unsent (a newer frame was due)",
        reports.len(),
        summary["sessions"],
        summary["frames_sent"],
        elapsed_s,
        summary["frames_per_s"].as_f64().unwrap_or(0.0),
        summary["frames_skipped"]
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
    println!(
        "age, frame due -> causal vectors received: p50 {}, p90 {}, p99 {}, max {}",
        f(age_ms(50.0)),
        f(age_ms(90.0)),
        f(age_ms(99.0)),
        f(age_ms(100.0))
    );
    for r in reports {
        for (code, message) in r.errors.iter().take(5) {
            println!("  {}: server error {code:?}: {message}", r.session);
        }
    }
    Ok(())
}
