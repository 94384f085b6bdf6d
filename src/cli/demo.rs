//! `mrptv demo`: a synthetic scenario through the engine in memory, with its accuracy.

use anyhow::{bail, Result};

use mrptv::offline::{self, Wire};
use mrptv_engine::synth::{Scenario, ScenarioSpec};
use mrptv_engine::PipelineConfig;

use super::args::{ConfigChoices, DepthRange, SceneSize, WireEncoding};
use super::progress_bar;

// `demo --help` lists the scene's size without a description: the scenarios below it say what
// each defaults to.
#[derive(clap::Args)]
#[command(
    mut_arg("frames", |a| a.help(None::<&str>)),
    mut_arg("particles", |a| a.help(None::<&str>)),
    mut_arg("method", |a| a.help("Use the published method's choices instead of mrptv's defaults")),
    mut_arg("encoding", |a| a.help(
        "Send the images through a frame encoding first (raw8, png, sparse), as a headset \
         would, and report its bandwidth and coding time next to the accuracy it gives"
    )),
)]
pub struct Args {
    #[arg(default_value = "flume")]
    scenario: Scenario,
    #[command(flatten)]
    size: SceneSize,
    #[command(flatten)]
    choices: ConfigChoices,
    #[command(flatten)]
    encoding: WireEncoding,
    /// Send the images as hl2ss's H.264 streams at this many Mbit/s a camera (one IDR a
    /// second) instead, as `mrptv hl2ss --codec h264 --bitrate-mbps` receives them.
    #[arg(long, value_name = "MBIT_PER_S", conflicts_with = "encoding")]
    h264_mbps: Option<f64>,
}

pub fn run(args: Args) -> Result<()> {
    let Args {
        scenario,
        size,
        choices: ConfigChoices {
            method,
            depth_range,
        },
        encoding: WireEncoding { encoding },
        h264_mbps,
    } = args;
    let wire = match h264_mbps {
        Some(mbps) if mbps > 0.0 && mbps.is_finite() => Wire::H264 {
            bitrate_bps: (mbps * 1e6) as u32,
        },
        Some(mbps) => bail!("--h264-mbps {mbps}: must be a positive number of Mbit/s"),
        None => Wire::Frames(encoding),
    };
    let spec = ScenarioSpec::new(scenario);
    let (frames, particles) = size.of(&spec)?;
    let seed = size.seed;
    // `--method`: the published method as it stands (`ConfigChoices::apply` would keep the
    // defaults' scale parameters).
    let mut config = if method {
        PipelineConfig::method()
    } else {
        PipelineConfig::default()
    };
    DepthRange::apply(depth_range, &mut config);
    println!("scenario '{scenario}': {}", scenario.description());
    println!(
        "{frames} frames, {particles} particles, seed {seed}, {} config",
        if method { "published-method" } else { "mrptv" }
    );
    let bar = progress_bar(frames, "demo");
    let pairs_per_s = 1.0 / spec.frame_interval_s;
    let mut run = offline::SyntheticRun::new(spec, config.clone());
    (run.frames, run.particles, run.seed, run.wire) = (frames, particles, seed, wire);
    let run = run.run(|n| bar.set_position(n as u64))?;
    bar.finish_and_clear();
    println!("scene: {}", run.scene.crowding());
    super::print_health(&run.totals.health(&config));
    println!(
        "engine: {:.0} stereo frames/s ({}), {:.1} matches/frame, {} vectors\n",
        run.totals.frames as f64 / run.totals.pipeline_s.max(1e-9),
        match rayon::current_num_threads() {
            1 => "one thread".to_string(),
            n => format!("the two cameras in parallel on {n} threads"),
        },
        run.totals.counts.matches as f64 / run.totals.frames.max(1) as f64,
        run.totals.counts.vectors
    );
    let summary = &run.wire;
    println!(
        "wire: {}, {:.0} bytes per stereo pair, {:.1} Mbit/s at {pairs_per_s:.0} Hz; encoder {:.2} ms, decoder {:.2} ms per image\n",
        summary.wire,
        summary.bytes_per_pair(),
        summary.mbit_per_s(pairs_per_s),
        summary.encode_ms_per_image(),
        summary.decode_ms_per_image()
    );
    print!("{}", run.report);
    Ok(())
}
