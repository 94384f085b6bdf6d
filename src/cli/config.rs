//! `mrptv config`: the processing config as TOML.

use anyhow::Result;

use mrptv_engine::PipelineConfig;

#[derive(clap::Args)]
pub struct Args {
    /// Print the published method's choices instead.
    #[arg(long)]
    method: bool,
}

pub fn run(args: Args) -> Result<()> {
    let config = if args.method {
        PipelineConfig::method()
    } else {
        PipelineConfig::default()
    };
    print!("{}", mrptv::config::to_toml(&config));
    Ok(())
}
