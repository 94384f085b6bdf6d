//! `mrptv`: the command-line edge. This file is the command list: it parses the arguments and
//! hands each subcommand to its module under `cli/` (arguments struct and `run`), whose work
//! lives in the library. Errors are reported here, once.

mod cli;

use clap::{Parser, Subcommand};

use cli::scenario_help;

#[derive(Parser)]
#[command(
    name = "mrptv",
    version,
    about = "Mixed-reality particle tracking velocimetry: stereo frames in, 3D velocity vectors out"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Write a synthetic recording with ground truth (OUT/truth.csv).
    #[command(after_help = format!("Scenarios:\n{}", scenario_help()))]
    Synth(cli::synth::Args),
    /// Process a recording: write velocity vectors (tracks.csv) and optionally every matched particle.
    Process(cli::process::Args),
    /// Score a tracks.csv against a truth.csv.
    Eval(cli::eval::Args),
    /// Run a synthetic scenario through the engine in memory and print its accuracy (no files, no headset).
    #[command(after_help = format!("Scenarios:\n{}", scenario_help()))]
    Demo(cli::demo::Args),
    /// Run the live host service: headsets stream stereo frames over WebSocket, 3D vectors stream back.
    #[command(
        after_help = "Protocol: protocol/README.md. Logs: RUST_LOG=debug (per-frame: trace)."
    )]
    Serve(cli::serve::Args),
    /// Stream a recording to a server as a headset would; save the vectors; report latency and drops.
    Replay(cli::replay::Args),
    /// Stream a HoloLens 2 running the hl2ss app to a server: its front cameras, calibration and
    /// poses, as a headset session.
    #[command(
        after_help = "hl2ss: github.com/jdibenes/hl2ss (the app must be running on the HoloLens)."
    )]
    Hl2ss(cli::hl2ss::Args),
    /// Load-test `serve` on this machine: a server on 127.0.0.1, N synthetic headsets and M
    /// viewers for a while; reports frames processed and dropped, latency and server memory.
    Load(cli::load::Args),
    /// Print the default processing config as TOML (every key, with mrptv's defaults).
    Config(cli::config::Args),
}

fn main() -> std::process::ExitCode {
    let result = match Cli::parse().command {
        Command::Synth(args) => cli::synth::run(args),
        Command::Process(args) => cli::process::run(args),
        Command::Eval(args) => cli::eval::run(args),
        Command::Demo(args) => cli::demo::run(args),
        Command::Serve(args) => cli::serve::run(args),
        Command::Replay(args) => cli::replay::run(args),
        Command::Hl2ss(args) => cli::hl2ss::run(args),
        Command::Load(args) => cli::load::run(args),
        Command::Config(args) => cli::config::run(args),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
