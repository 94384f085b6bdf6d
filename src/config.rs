//! The TOML processing config: one table per stage (`[detect]`, `[link]`, `[stereo]`,
//! `[velocity]`), every key optional, unknown keys rejected so a typo is not silently ignored.

use std::path::{Path, PathBuf};

use mrptv_engine::{PipelineConfig, PipelineError};

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("{path}: {error}")]
    Io {
        path: PathBuf,
        error: std::io::Error,
    },
    #[error("{path}: {error}")]
    Parse {
        path: PathBuf,
        error: toml::de::Error,
    },
    #[error("{path}: {error}")]
    Invalid { path: PathBuf, error: PipelineError },
}

pub(crate) fn parse(path: &Path, text: &str) -> Result<PipelineConfig, ConfigError> {
    let config: PipelineConfig = toml::from_str(text).map_err(|error| ConfigError::Parse {
        path: path.to_path_buf(),
        error,
    })?;
    config.validate().map_err(|error| ConfigError::Invalid {
        path: path.to_path_buf(),
        error: PipelineError::Config(error),
    })?;
    Ok(config)
}

pub fn load(path: &Path) -> Result<PipelineConfig, ConfigError> {
    let text = std::fs::read_to_string(path).map_err(|error| ConfigError::Io {
        path: path.to_path_buf(),
        error,
    })?;
    parse(path, &text)
}

/// The config as TOML, every key spelled out, so a user sees what can be tuned.
pub fn to_toml(config: &PipelineConfig) -> String {
    toml::to_string_pretty(config).unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_and_defaults_fill_gaps() {
        let text = to_toml(&PipelineConfig::method());
        assert!(text.contains("[velocity]") && text.contains("half_window_frames = 5"));
        let back = parse(Path::new("c.toml"), &text).expect("valid");
        assert_eq!(back, PipelineConfig::method());
        let partial =
            parse(Path::new("c.toml"), "[velocity]\nhalf_window_frames = 2\n").expect("valid");
        assert_eq!(partial.velocity.half_window_frames, 2);
        assert_eq!(partial.detect, PipelineConfig::default().detect);
    }

    #[test]
    fn typos_and_bad_values_are_named() {
        let e = parse(Path::new("c.toml"), "[velocity]\nhalf_windw_frames = 2\n")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("c.toml") && e.contains("half_windw_frames"),
            "{e}"
        );
        let e = parse(Path::new("c.toml"), "[link]\nbox_half_side_px = -3.0\n")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("link.box_half_side_px: must be a finite number >= 0"),
            "{e}"
        );
        let e = parse(Path::new("c.toml"), "[velocity]\nhalf_window_frames = 0\n")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("velocity.half_window_frames: must be in 1..=100"),
            "{e}"
        );
        let huge = format!("[velocity]\nhalf_window_frames = {}\n", u64::MAX);
        let e = parse(Path::new("c.toml"), &huge).unwrap_err().to_string();
        assert!(e.contains("half_window_frames"), "{e}");
    }

    #[test]
    fn the_tracks_keys_live_in_the_link_table() {
        let text = "[link]\nbox_half_side_px = 25\nrejoin_frames = 3\nrejoin_tolerance_px = 4.5\n";
        let config = parse(Path::new("c.toml"), text).expect("valid");
        assert_eq!(config.link.box_half_side_px, 25.0);
        assert_eq!(config.tracks.rejoin_frames, 3);
        assert_eq!(config.tracks.rejoin_tolerance_px, 4.5);
        assert!(to_toml(&config).contains("[link]\nbox_half_side_px = 25.0"));
        assert!(!to_toml(&config).contains("[tracks]"));
        let e = parse(Path::new("c.toml"), "[link]\nrejoin_framez = 3\n")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("c.toml") && e.contains("rejoin_framez") && e.contains("`rejoin_frames`"),
            "{e}"
        );
    }
}
