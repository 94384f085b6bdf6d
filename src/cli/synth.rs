//! `mrptv synth`: a synthetic recording with ground truth.

use std::fs;
use std::path::PathBuf;

use anyhow::{bail, Result};

use mrptv::offline;
use mrptv_engine::synth::{Scenario, ScenarioSpec};

use super::args::SceneSize;
use super::progress_bar;

#[derive(clap::Args)]
pub struct Args {
    /// Scenario name (see below).
    scenario: Scenario,
    /// Output recording directory (created; must be empty or absent).
    out: PathBuf,
    #[command(flatten)]
    size: SceneSize,
}

pub fn run(args: Args) -> Result<()> {
    let Args {
        scenario,
        out,
        size,
    } = args;
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
    let (frames, particles) = size.of(&spec)?;
    let seed = size.seed;
    let bar = progress_bar(frames, "synth");
    let summary = offline::write_synthetic(spec, &out, frames, particles, seed, |n| {
        bar.set_position(n as u64)
    })?;
    bar.finish_and_clear();
    println!(
        "wrote {} frames of '{scenario}' ({particles} particles, seed {seed}) to {}; {:.1} % of particle-frames visible in both cameras; {}",
        summary.frames,
        out.display(),
        100.0 * summary.visible_fraction,
        summary.crowding()
    );
    println!(
        "next: mrptv process {0} --out tracks.csv && mrptv eval {0}/truth.csv tracks.csv",
        out.display()
    );
    Ok(())
}
