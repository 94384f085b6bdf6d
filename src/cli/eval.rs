//! `mrptv eval`: scores a tracks.csv against a truth.csv.

use std::path::PathBuf;

use anyhow::{bail, Result};

use mrptv::tables;
use mrptv_engine::eval::{evaluate, EvalOptions};

use super::args::JsonOutput;

#[derive(clap::Args)]
#[command(mut_arg("json", |a| a.help("Machine-readable output")))]
pub struct Args {
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
    #[command(flatten)]
    output: JsonOutput,
}

pub fn run(args: Args) -> Result<()> {
    if !(args.radius > 0.0 && args.radius.is_finite()) {
        bail!("--radius must be a positive number of metres");
    }
    let truth = tables::read_truth(&args.truth)?;
    let tracks = tables::read_tracks(&args.tracks)?;
    let report = evaluate(
        &truth,
        &tracks,
        &EvalOptions {
            radius_m: args.radius,
            outlier_fraction: args.outlier_fraction,
            window_frames: args.window,
            ..Default::default()
        },
    )?;
    if args.output.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print!("{report}");
    }
    Ok(())
}
