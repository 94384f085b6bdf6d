//! `mrptv synth`: a synthetic recording with ground truth.

use std::fs;
use std::path::PathBuf;

use anyhow::{bail, Result};

use mrptv::offline;
use mrptv_engine::synth::{Scenario, ScenarioSpec};

use super::progress_bar;

#[derive(clap::Args)]
pub struct Args {
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
}

pub fn run(args: Args) -> Result<()> {
    let Args {
        scenario,
        out,
        frames,
        particles,
        seed,
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
