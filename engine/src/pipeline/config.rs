//! Every parameter of the pipeline, one config per stage, and the config file's layout: one
//! table per stage (`[detect]`, `[link]`, `[stereo]`, `[velocity]`), every key optional, unknown
//! keys refused so a typo is not silently ignored. The 3D tracks' keys sit in `[link]`, as files
//! written before the tracks had a stage of their own have them.

use std::collections::BTreeMap;

use serde::de::IgnoredAny;
use serde::{Deserialize, Serialize};

use crate::config::ConfigError;
use crate::detect::DetectConfig;
use crate::link::LinkConfig;
use crate::stereo::StereoConfig;
use crate::tracks::TrackConfig;
use crate::velocity::VelocityConfig;

/// Every parameter of the pipeline, per stage.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(from = "ConfigFile", into = "ConfigFile")]
pub struct PipelineConfig {
    /// Detection.
    pub detect: DetectConfig,
    /// Per-camera linking.
    pub link: LinkConfig,
    /// Stereo matching.
    pub stereo: StereoConfig,
    /// 3D tracks.
    pub tracks: TrackConfig,
    /// Velocity.
    pub velocity: VelocityConfig,
}

impl PipelineConfig {
    /// The published method with none of mrptv's improvements: per-particle choices, stereo
    /// search ranges as image fractions (K = 0.25, S = 0.01), no track memory in stereo, no
    /// neighbour prediction, no touching-particle split, no rejection.
    pub fn method() -> Self {
        Self {
            detect: DetectConfig::method(),
            link: LinkConfig::method(),
            stereo: StereoConfig::method(),
            tracks: TrackConfig::method(),
            velocity: VelocityConfig::method(),
        }
    }

    /// Refuses a config no run can use, naming the first bad key.
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.detect.validate()?;
        self.link.validate()?;
        self.stereo.validate()?;
        self.tracks.validate()?;
        self.velocity.validate()
    }
}

/// The config file's layout.
#[derive(Serialize, Deserialize, Default)]
#[serde(default, deny_unknown_fields)]
struct ConfigFile {
    detect: DetectConfig,
    link: LinkTable,
    stereo: StereoConfig,
    velocity: VelocityConfig,
}

/// `[link]`: the linking keys and the 3D tracks' keys.
#[derive(Serialize, Deserialize, Default)]
#[serde(try_from = "LinkKeys")]
struct LinkTable {
    #[serde(flatten)]
    link: LinkConfig,
    #[serde(flatten)]
    tracks: TrackConfig,
}

/// `[link]` as read, any other key kept to be refused.
#[derive(Deserialize, Default)]
#[serde(default)]
struct LinkKeys {
    #[serde(flatten)]
    link: LinkConfig,
    #[serde(flatten)]
    tracks: TrackConfig,
    #[serde(flatten)]
    unknown: BTreeMap<String, IgnoredAny>,
}

impl TryFrom<LinkKeys> for LinkTable {
    type Error = String;

    fn try_from(keys: LinkKeys) -> Result<Self, String> {
        match keys.unknown.keys().next() {
            Some(key) => Err(format!(
                "unknown field `{key}`, expected one of {}",
                LinkTable::known_keys().join(", ")
            )),
            None => Ok(Self {
                link: keys.link,
                tracks: keys.tracks,
            }),
        }
    }
}

impl From<ConfigFile> for PipelineConfig {
    fn from(file: ConfigFile) -> Self {
        Self {
            detect: file.detect,
            link: file.link.link,
            stereo: file.stereo,
            tracks: file.link.tracks,
            velocity: file.velocity,
        }
    }
}

impl From<PipelineConfig> for ConfigFile {
    fn from(config: PipelineConfig) -> Self {
        Self {
            detect: config.detect,
            link: LinkTable {
                link: config.link,
                tracks: config.tracks,
            },
            stereo: config.stereo,
            velocity: config.velocity,
        }
    }
}

impl LinkTable {
    /// The keys `[link]` takes, in the file's order.
    fn known_keys() -> Vec<String> {
        let (link, tracks) = (field_names::<LinkConfig>(), field_names::<TrackConfig>());
        link.iter()
            .chain(tracks)
            .map(|k| format!("`{k}`"))
            .collect()
    }
}

/// The field names a struct deserializes from, as its `Deserialize` impl declares them.
fn field_names<'de, T: Deserialize<'de>>() -> &'static [&'static str] {
    let mut names = FieldNames(&[]);
    // The deserializer stops at the struct's field list: the error is expected.
    let _ = T::deserialize(&mut names);
    names.0
}

/// A deserializer that records the field list a struct asks for, and gives nothing else.
struct FieldNames(&'static [&'static str]);

impl<'de> serde::Deserializer<'de> for &mut FieldNames {
    type Error = serde::de::value::Error;

    fn deserialize_any<V: serde::de::Visitor<'de>>(self, _: V) -> Result<V::Value, Self::Error> {
        Err(serde::de::Error::custom(
            "only a struct's field names are read",
        ))
    }

    fn deserialize_struct<V: serde::de::Visitor<'de>>(
        self,
        _name: &'static str,
        fields: &'static [&'static str],
        visitor: V,
    ) -> Result<V::Value, Self::Error> {
        self.0 = fields;
        self.deserialize_any(visitor)
    }

    serde::forward_to_deserialize_any! {
        bool i8 i16 i32 i64 i128 u8 u16 u32 u64 u128 f32 f64 char str string bytes byte_buf
        option unit unit_struct newtype_struct seq tuple tuple_struct map enum identifier
        ignored_any
    }
}
