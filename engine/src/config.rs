//! Why a stage's config is refused. Each stage's config type owns its defaults, its published-
//! method values (`method()`) and its validation (`validate()`); these are the checks they share.

use crate::stereo::SearchError;

/// A config no run can use, naming the key as the config file spells it (`table.key`).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ConfigError {
    /// A key whose value is out of its range.
    #[error("{table}.{key}: {reason}")]
    Invalid {
        /// The config file's table (`detect`, `link`, `stereo`, `velocity`).
        table: &'static str,
        /// The key within it.
        key: &'static str,
        /// What the value must be.
        reason: &'static str,
    },
    /// The stereo search the config asks for cannot be set up for the rig.
    #[error(transparent)]
    Search(#[from] SearchError),
}

impl ConfigError {
    /// `table.key` refused for `reason`.
    pub(crate) fn invalid(table: &'static str, key: &'static str, reason: &'static str) -> Self {
        Self::Invalid { table, key, reason }
    }
}

/// Refuses the first of `values` (key, value) that is not a finite number >= 0.
pub(crate) fn check_non_negative(
    table: &'static str,
    values: &[(&'static str, f64)],
) -> Result<(), ConfigError> {
    match values.iter().find(|(_, v)| !v.is_finite() || *v < 0.0) {
        Some((key, _)) => Err(ConfigError::invalid(
            table,
            key,
            "must be a finite number >= 0",
        )),
        None => Ok(()),
    }
}
