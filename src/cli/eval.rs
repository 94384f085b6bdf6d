//! `mrptv eval`: scores a tracks.csv against a truth.csv and, where the recording is at hand,
//! says where the measurable truth was lost.

use std::path::{Path, PathBuf};

use anyhow::{bail, Result};

use mrptv::offline;
use mrptv::recording::Recording;
use mrptv::tables;
use mrptv_engine::eval::{evaluate, loss_budget, EvalOptions, LossBudget, Report, TrackRow};
use mrptv_engine::synth::TruthRow;

use super::args::{ConfigChoices, ConfigFile, JsonOutput};
use super::{load_config, progress_bar};

#[derive(clap::Args)]
#[command(mut_arg("json", |a| a.help("Machine-readable output")))]
pub struct Args {
    /// truth.csv: frame,t_s,pid,x,y,z,u,v,w, then any further columns (in_left and in_right, 0
    /// or 1, say which images show the particle).
    truth: PathBuf,
    tracks: PathBuf,
    /// Association radius, metres.
    #[arg(long, default_value_t = 0.02)]
    radius: f64,
    /// Outlier threshold as a fraction of the mean speed.
    #[arg(long, default_value_t = 0.2)]
    outlier_fraction: f64,
    /// M of the velocity window, for the measurable yield (particles living +-M frames) [the
    /// loss budget's default: the config's velocity window].
    #[arg(long, default_value_t = 0)]
    window: u64,
    /// The recording the tracks came from, for the loss budget: it is processed again (with
    /// --config, --method and --depth-range as `process` took them) to follow every measurable
    /// truth particle through the stages [default: the truth's folder, when it holds rig.json].
    #[arg(long, value_name = "DIR")]
    rec: Option<PathBuf>,
    /// No loss budget: score the tracks only.
    #[arg(long, conflicts_with = "rec")]
    no_budget: bool,
    #[command(flatten)]
    config: ConfigFile,
    #[command(flatten)]
    choices: ConfigChoices,
    #[command(flatten)]
    output: JsonOutput,
}

/// The report with the loss budget, as `--json` prints it.
#[derive(serde::Serialize)]
struct Scored<'a> {
    #[serde(flatten)]
    report: &'a Report,
    #[serde(skip_serializing_if = "Option::is_none")]
    loss_budget: Option<&'a LossBudget>,
}

pub fn run(args: Args) -> Result<()> {
    if !(args.radius > 0.0 && args.radius.is_finite()) {
        bail!("--radius must be a positive number of metres");
    }
    let truth = tables::read_truth(&args.truth)?;
    let tracks = tables::read_tracks(&args.tracks)?;
    let options = EvalOptions {
        radius_m: args.radius,
        outlier_fraction: args.outlier_fraction,
        window_frames: args.window,
        ..Default::default()
    };
    let report = evaluate(&truth, &tracks, &options)?;
    let budget = match budget_recording(&args) {
        Some(rec) => Some(budget(&args, &rec, &truth, &tracks, options)?),
        None => None,
    };
    if args.output.json {
        let scored = Scored {
            report: &report,
            loss_budget: budget.as_ref(),
        };
        println!("{}", serde_json::to_string_pretty(&scored)?);
    } else {
        print!("{report}");
        if let Some(budget) = &budget {
            print!("{budget}");
        }
    }
    Ok(())
}

/// `--rec`, else the truth's folder where it is a recording; `None` with `--no-budget`.
fn budget_recording(args: &Args) -> Option<PathBuf> {
    if args.no_budget {
        return None;
    }
    if let Some(rec) = &args.rec {
        return Some(rec.clone());
    }
    let folder = args.truth.parent().unwrap_or(Path::new("."));
    let folder = if folder.as_os_str().is_empty() {
        Path::new(".")
    } else {
        folder
    };
    folder
        .join("rig.json")
        .is_file()
        .then(|| folder.to_path_buf())
}

/// Processes the recording again, following every measurable truth particle-frame.
fn budget(
    args: &Args,
    rec: &Path,
    truth: &[TruthRow],
    tracks: &[TrackRow],
    mut options: EvalOptions,
) -> Result<LossBudget> {
    let recording = Recording::open(rec)?;
    let config = args.choices.clone().apply(load_config(rec, &args.config)?);
    if options.window_frames == 0 {
        options.window_frames = config.velocity.half_window_frames as u64;
    }
    let bar = progress_bar(recording.frames.len(), "budget");
    let observations =
        offline::observe_recording(&recording, config, |n| bar.set_position(n as u64))?;
    bar.finish_and_clear();
    Ok(loss_budget(
        truth,
        tracks,
        &observations,
        &recording.rig,
        &options,
    ))
}
