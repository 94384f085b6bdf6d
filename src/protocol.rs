//! The live wire protocol, version 1 (specified in `protocol/README.md`): JSON control messages
//! and two binary messages, a stereo frame (headset -> server) and a vector batch (server ->
//! headset and viewers). Pure encoding and decoding, no I/O; the server and the clients share it.
//!
//! Binary layouts are little-endian, fixed headers, no padding surprises: every offset below is
//! the one in the spec, and `protocol/golden/` holds example messages the tests decode.

use nalgebra::{Isometry3, Matrix3, Point3, Vector3};
use serde::{Deserialize, Serialize};

use mrptv_engine::geometry::{isometry_from_row_major, isometry_to_row_major, RigFile};
use mrptv_engine::{PipelineConfig, VelocityVector};

/// The protocol major version this build speaks.
pub const PROTOCOL_VERSION: u32 = 1;
pub(crate) const FRAME_MAGIC: [u8; 4] = *b"MRPF";
pub(crate) const BATCH_MAGIC: [u8; 4] = *b"MRPV";
/// Bytes before the optional pose in a frame message.
pub(crate) const FRAME_HEADER_BYTES: usize = 32;
pub(crate) const POSE_BYTES: usize = 16 * 8;
pub(crate) const BATCH_HEADER_BYTES: usize = 40;
pub(crate) const BATCH_RECORD_BYTES: usize = 40;
const FRAME_FLAG_POSE: u16 = 1;
const BATCH_FLAG_WORLD: u8 = 1;
/// Header flag: `count` blocks of [`BATCH_SIGMA_BYTES`] follow the records (asked for with
/// `"uncertainty": true` in `hello` or `subscribe`).
const BATCH_FLAG_SIGMAS: u8 = 2;
/// Per vector: the 1-sigma errors of u, v and w, 3 x f32, m/s.
pub(crate) const BATCH_SIGMA_BYTES: usize = 12;
const VECTOR_FLAG_REFINED: u16 = 1;
const VECTOR_FLAG_WORLD: u16 = 2;

/// Coordinate convention of poses sent and vectors received. Calibration (`rig.json`) is always
/// OpenCV. Each convention is the OpenCV frame with some axes flipped: the headset's poses are
/// read and its vectors written with the same flips, so a client works entirely in its own
/// convention.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Convention {
    /// Right-handed: x right, y down, z forward (the rig's and `rig.json`'s frame).
    #[default]
    OpenCv,
    /// Left-handed: x right, y up, z forward (Unity).
    Unity,
    /// Right-handed: x right, y up, z backward (-z forward; WebXR, three.js, OpenGL).
    WebXr,
}

impl Convention {
    pub(crate) fn code(self) -> u8 {
        match self {
            Convention::OpenCv => 0,
            Convention::Unity => 1,
            Convention::WebXr => 2,
        }
    }

    pub(crate) fn from_code(code: u8) -> Option<Self> {
        match code {
            0 => Some(Convention::OpenCv),
            1 => Some(Convention::Unity),
            2 => Some(Convention::WebXr),
            _ => None,
        }
    }

    /// Per-axis signs taking OpenCV coordinates to this convention (and back: each is its own
    /// inverse).
    pub(crate) fn axis_signs(self) -> Vector3<f64> {
        match self {
            Convention::OpenCv => Vector3::new(1.0, 1.0, 1.0),
            Convention::Unity => Vector3::new(1.0, -1.0, 1.0),
            Convention::WebXr => Vector3::new(1.0, -1.0, -1.0),
        }
    }

    /// A point or a vector given in OpenCV coordinates, in this convention (or the reverse).
    pub fn flip(self, v: &Vector3<f64>) -> Vector3<f64> {
        v.component_mul(&self.axis_signs())
    }

    /// A `world_from_rig` pose given in this convention, in OpenCV coordinates, or the reverse:
    /// `F T F` with `F` the axis flip (its own inverse), a proper rigid motion whichever
    /// handedness `F` has.
    pub(crate) fn flip_pose(self, pose: &Isometry3<f64>) -> Option<Isometry3<f64>> {
        if self == Convention::OpenCv {
            return Some(*pose);
        }
        let flip = Matrix3::from_diagonal(&self.axis_signs());
        let rotation = flip * pose.rotation.to_rotation_matrix().matrix() * flip;
        let translation = self.flip(&pose.translation.vector);
        let mut m = [0.0; 16];
        for r in 0..3 {
            for c in 0..3 {
                m[4 * r + c] = rotation[(r, c)];
            }
            m[4 * r + 3] = translation[r];
        }
        m[15] = 1.0;
        isometry_from_row_major("world_from_rig", &m).ok()
    }
}

/// Reads a unit enum from its wire name (`"webxr"`, `"png"`...), for command lines.
fn from_wire_name<T: serde::de::DeserializeOwned>(s: &str, names: &str) -> Result<T, String> {
    serde_json::from_value(serde_json::Value::String(s.to_string()))
        .map_err(|_| format!("{s:?}: expected one of {names}"))
}

impl std::str::FromStr for Convention {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        from_wire_name(s, "opencv, unity, webxr")
    }
}

impl std::str::FromStr for Encoding {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        from_wire_name(s, "raw8, png, sparse")
    }
}

/// Pixel encoding of the images in frame messages.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Encoding {
    /// width * height bytes, row-major, top row first, 8-bit grayscale.
    #[default]
    Raw8,
    /// A PNG file holding an 8-bit grayscale image of the declared size.
    Png,
    /// The pixels that can belong to a particle, exact, and the background per block
    /// (`sparse` module): a tenth of PNG's size or less, for a headset's Wi-Fi.
    Sparse,
}

impl Encoding {
    pub(crate) fn code(self) -> u8 {
        match self {
            Encoding::Raw8 => 0,
            Encoding::Png => 1,
            Encoding::Sparse => 2,
        }
    }

    pub(crate) fn from_code(code: u8) -> Option<Self> {
        match code {
            0 => Some(Encoding::Raw8),
            1 => Some(Encoding::Png),
            2 => Some(Encoding::Sparse),
            _ => None,
        }
    }

    /// An 8-bit grayscale image (`width * height` bytes) as this encoding sends it (`sparse`
    /// with its default settings).
    pub fn encode_image(self, pixels: &[u8], width: u32, height: u32) -> Result<Vec<u8>, String> {
        match self {
            Encoding::Raw8 => Ok(pixels.to_vec()),
            Encoding::Png => crate::recording::encode_gray_png(pixels, width, height),
            Encoding::Sparse => Ok(crate::sparse::encode(
                pixels,
                width,
                height,
                &crate::sparse::SparseParams::default(),
            )),
        }
    }

    /// The pixels of an image sent in this encoding, checked against the session's size.
    pub fn decode_image(self, bytes: &[u8], width: u32, height: u32) -> Result<Vec<u8>, String> {
        match self {
            Encoding::Raw8 => {
                let expected = width as usize * height as usize;
                if bytes.len() == expected {
                    Ok(bytes.to_vec())
                } else {
                    Err(format!(
                        "{} bytes, a {width}x{height} raw8 image has {expected}",
                        bytes.len()
                    ))
                }
            }
            Encoding::Png => crate::recording::decode_gray_png(bytes, width, height),
            Encoding::Sparse => crate::sparse::decode(bytes, width, height),
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImageFormat {
    pub width: u32,
    pub height: u32,
    pub encoding: Encoding,
}

/// The headset's first message.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Hello {
    pub protocol: u32,
    /// Free text naming the client, for logs and the session list.
    pub client: String,
    pub rig: RigFile,
    pub image: ImageFormat,
    #[serde(default)]
    pub convention: Convention,
    /// Pipeline parameters for this session; the server's own when absent. Missing keys take
    /// their defaults, unknown keys are refused.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub config: Option<PipelineConfig>,
    /// Vector batches carry each vector's 1-sigma velocity errors after the records.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub uncertainty: bool,
}

/// Messages a headset sends as text.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
// Unit variants of an internally tagged enum take any extra field; empty struct variants
// refuse them, as the schemas and the Versioning section say.
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum HeadsetMessage {
    Hello(Box<Hello>),
    Bye {},
}

/// Messages a viewer sends as text.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum ViewerMessage {
    /// Receive a session's batches (`"*"`: every session, present and future).
    Subscribe {
        session: String,
        #[serde(default = "default_viewer_convention")]
        convention: Convention,
        /// Batches carry each vector's 1-sigma velocity errors after the records.
        #[serde(default, skip_serializing_if = "std::ops::Not::not")]
        uncertainty: bool,
    },
    Unsubscribe {},
    List {},
    /// Empties a live session's mean-flow field (`"*"`: every live session's).
    ResetField {
        session: String,
    },
    /// Answered at once by a `pong` with the same `id`: a browser cannot see WebSocket pings,
    /// and needs the round trip to estimate latency.
    Ping {
        id: u64,
    },
}

fn default_viewer_convention() -> Convention {
    Convention::WebXr
}

/// What is fixed about a session from its hello on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SessionDescription {
    pub id: String,
    pub client: String,
    pub width: u32,
    pub height: u32,
    pub encoding: Encoding,
    pub convention: Convention,
    pub started_unix_ms: u64,
}

/// What the server knows of a live session.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SessionInfo {
    #[serde(flatten)]
    pub session: SessionDescription,
    pub viewers: usize,
    pub counters: Counters,
}

/// A session's running totals.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Counters {
    /// Frame messages that decoded and were queued.
    pub frames_received: u64,
    /// Frames the pipeline processed.
    pub frames_processed: u64,
    /// Frames dropped unprocessed because the queue was full (oldest first).
    pub frames_dropped: u64,
    /// Frames refused with an error (bad header, wrong image size, time going back...).
    pub frames_rejected: u64,
    /// Vectors sent to the headset, causal and refined.
    pub vectors_sent: u64,
    /// Batches the headset was too slow to take (its send buffer was full).
    pub batches_dropped: u64,
    /// Frames waiting in the queue when this was written.
    pub queue_depth: usize,
    /// Pipeline time for the last frame and the mean over the session, milliseconds.
    pub processing_ms_last: f64,
    pub processing_ms_mean: f64,
    /// With `serve --record`: frames written and synced to disk (see `recorded`).
    #[serde(default)]
    pub frames_recorded: u64,
    /// The session's health so far, as `mrptv process` reports it for a recording: detections
    /// per image, and the fractions of detections linked to an earlier frame, of left
    /// detections matched in the right image, of matched particles given a (refined) velocity;
    /// and the stereo candidates per left particle that had any (far above 1: ambiguous).
    #[serde(default)]
    pub detections_per_image: f64,
    #[serde(default)]
    pub linked_fraction: f64,
    #[serde(default)]
    pub matched_fraction: f64,
    #[serde(default)]
    pub velocity_fraction: f64,
    #[serde(default)]
    pub stereo_candidates_per_particle: f64,
}

/// Error codes; the `message` next to them is for people.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ErrorCode {
    MalformedJson,
    UnknownType,
    UnsupportedVersion,
    BadHello,
    BadCalibration,
    BadConfig,
    NotReady,
    AlreadyStarted,
    BadFrame,
    BadImage,
    BadTimestamp,
    UnknownSession,
    ShuttingDown,
    Internal,
    /// Missing or wrong secret (HTTP 401 before the WebSocket upgrade).
    Unauthorized,
    /// A configured limit (sessions, viewers per session, image size) is reached.
    LimitReached,
    /// Frames arrive faster than the session's frame-rate limit.
    RateLimited,
}

/// Messages the server sends as text, to headsets and viewers.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum ServerMessage {
    Welcome {
        protocol: u32,
        server: String,
        session: String,
        session_number: u32,
        convention: Convention,
        config: Box<PipelineConfig>,
        /// Frames the server holds for a session before dropping the oldest.
        queue_frames: usize,
        /// Frames between a frame and its refined (centred) vectors: M.
        refined_delay_frames: usize,
    },
    Status {
        session: String,
        counters: Counters,
    },
    Dropped {
        session: String,
        frame_indices: Vec<u64>,
        frames_dropped: u64,
    },
    Error {
        code: ErrorCode,
        message: String,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        frame_index: Option<u64>,
    },
    Bye {
        reason: String,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        counters: Option<Counters>,
    },
    Sessions {
        sessions: Vec<SessionInfo>,
    },
    Subscribed {
        session: String,
        convention: Convention,
        /// Present (true) when the viewer asked for uncertainties.
        #[serde(default, skip_serializing_if = "std::ops::Not::not")]
        uncertainty: bool,
    },
    /// A session's mean-flow field (`protocol/README.md`, "field").
    Field(Box<FieldMessage>),
    /// The answer to `reset_field`: these sessions' fields were emptied.
    FieldReset {
        sessions: Vec<String>,
    },
    Unsubscribed,
    Pong {
        id: u64,
    },
    SessionEnded {
        session: String,
        counters: Counters,
    },
    /// With `serve --record`: every processed frame up to `through_frame_index` is on disk,
    /// synced; a crash of the server from now on cannot lose it.
    Recorded {
        session: String,
        through_frame_index: u64,
        frames_recorded: u64,
    },
}

impl ServerMessage {
    pub fn error(code: ErrorCode, message: impl Into<String>) -> Self {
        ServerMessage::Error {
            code,
            message: message.into(),
            frame_index: None,
        }
    }

    pub fn to_json(&self) -> String {
        // Plain data with string keys: serialisation cannot fail.
        serde_json::to_string(self)
            .unwrap_or_else(|e| format!(r#"{{"type":"error","code":"internal","message":"{e}"}}"#))
    }
}

/// Columns of each row of a `field` message's `cells`, as in `field.csv`.
pub use mrptv_engine::field::FIELD_COLUMNS;

/// A session's mean-flow field as viewers receive it, in their convention.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FieldMessage {
    pub session: String,
    pub convention: Convention,
    /// The newest frame whose vectors are in the field.
    pub frame_index: u64,
    pub t_s: f64,
    /// The cells' side, metres.
    pub cell_m: f64,
    /// Samples older than this are forgotten; absent: the field keeps the whole session.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub window_s: Option<f64>,
    /// Vectors added since the session began or the field was last reset.
    pub samples: u64,
    /// The field's cells number more than `cells` holds (the most sampled are sent).
    pub truncated: bool,
    pub columns: Vec<String>,
    /// One row per cell, in `columns` order.
    pub cells: Vec<[f64; 14]>,
}

impl FieldMessage {
    /// The message of `cells` (of `grid`, the engine's OpenCV world frame; `truncated` if only
    /// some of the grid's) as of frame `(frame_index, t_s)`, in `convention`.
    pub fn new(
        session: String,
        frame: (u64, f64),
        grid: &mrptv_engine::field::FieldGrid,
        cells: &[mrptv_engine::field::CellSummary],
        truncated: bool,
        convention: Convention,
    ) -> Self {
        Self {
            session,
            convention,
            frame_index: frame.0,
            t_s: frame.1,
            cell_m: grid.cell_m(),
            window_s: grid.window_s(),
            samples: grid.samples_added(),
            truncated,
            columns: FIELD_COLUMNS.iter().map(|c| c.to_string()).collect(),
            cells: Self::rows(cells, convention),
        }
    }

    /// `cells` (in the engine's OpenCV world frame) as rows in `convention`: positions and
    /// mean velocities flipped, spreads unsigned.
    pub(crate) fn rows(
        cells: &[mrptv_engine::field::CellSummary],
        convention: Convention,
    ) -> Vec<[f64; 14]> {
        cells
            .iter()
            .map(|c| {
                mrptv_engine::field::CellSummary {
                    centre: Point3::from(convention.flip(&c.centre.coords)),
                    mean: convention.flip(&c.mean),
                    ..*c
                }
                .values()
            })
            .collect()
    }
}

/// Why a message was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{message}")]
pub struct ProtocolError {
    pub(crate) code: ErrorCode,
    pub(crate) message: String,
    pub(crate) frame_index: Option<u64>,
}

impl ProtocolError {
    pub(crate) fn new(code: ErrorCode, message: impl Into<String>) -> Self {
        Self {
            code,
            message: message.into(),
            frame_index: None,
        }
    }

    pub(crate) fn to_message(&self) -> ServerMessage {
        ServerMessage::Error {
            code: self.code,
            message: self.message.clone(),
            frame_index: self.frame_index,
        }
    }
}

/// Reads a text message: malformed JSON, a missing or unknown `type`, a wrong protocol version and
/// bad fields each get their own code, so a client author sees at once what is wrong.
pub fn parse_text<T: serde::de::DeserializeOwned>(
    text: &str,
    known_types: &[&str],
) -> Result<T, ProtocolError> {
    let value: serde_json::Value = serde_json::from_str(text).map_err(|e| {
        ProtocolError::new(ErrorCode::MalformedJson, format!("malformed JSON: {e}"))
    })?;
    let Some(kind) = value
        .get("type")
        .and_then(|t| t.as_str())
        .map(str::to_owned)
    else {
        return Err(ProtocolError::new(
            ErrorCode::UnknownType,
            "a text message must be a JSON object with a string field \"type\"",
        ));
    };
    if !known_types.contains(&kind.as_str()) {
        return Err(ProtocolError::new(
            ErrorCode::UnknownType,
            format!(
                "unknown message type {kind:?} (expected one of: {})",
                known_types.join(", ")
            ),
        ));
    }
    if let Some(version) = value.get("protocol") {
        if version.as_u64() != Some(u64::from(PROTOCOL_VERSION)) {
            return Err(ProtocolError::new(
                ErrorCode::UnsupportedVersion,
                format!("protocol version {version} is not supported; this server speaks {PROTOCOL_VERSION}"),
            ));
        }
    }
    // What is wrong inside `rig` or `config` gets their own codes, whatever it is (an unknown
    // key, a wrong type, a refused value): the client learns which object to fix.
    if let Some(rig) = value.get("rig").filter(|_| kind == "hello") {
        if let Err(e) = serde_json::from_value::<RigFile>(rig.clone()) {
            return Err(ProtocolError::new(
                ErrorCode::BadCalibration,
                format!("bad \"rig\" in hello: {e}"),
            ));
        }
    }
    if let Some(config) = value.get("config").filter(|_| kind == "hello") {
        if let Err(e) = serde_json::from_value::<PipelineConfig>(config.clone()) {
            return Err(ProtocolError::new(
                ErrorCode::BadConfig,
                format!("bad \"config\" in hello: {e}"),
            ));
        }
    }
    let code = if kind == "hello" {
        ErrorCode::BadHello
    } else {
        ErrorCode::MalformedJson
    };
    serde_json::from_value(value)
        .map_err(|e| ProtocolError::new(code, format!("bad {kind:?} message: {e}")))
}

pub const HEADSET_TYPES: &[&str] = &["hello", "bye"];
pub const VIEWER_TYPES: &[&str] = &["subscribe", "unsubscribe", "list", "ping", "reset_field"];

/// A decoded frame message; images borrow the message buffer.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameMessage<'a> {
    pub encoding: Encoding,
    pub frame_index: u64,
    pub t_s: f64,
    /// In the session's convention, as sent.
    pub world_from_rig: Option<Isometry3<f64>>,
    pub left: &'a [u8],
    pub right: &'a [u8],
}

fn bad_frame(message: impl Into<String>) -> ProtocolError {
    ProtocolError::new(ErrorCode::BadFrame, message)
}

fn read_u16(b: &[u8], at: usize) -> u16 {
    u16::from_le_bytes([b[at], b[at + 1]])
}

fn read_u32(b: &[u8], at: usize) -> u32 {
    let mut a = [0; 4];
    a.copy_from_slice(&b[at..at + 4]);
    u32::from_le_bytes(a)
}

fn read_u64(b: &[u8], at: usize) -> u64 {
    let mut a = [0; 8];
    a.copy_from_slice(&b[at..at + 8]);
    u64::from_le_bytes(a)
}

fn read_f64(b: &[u8], at: usize) -> f64 {
    f64::from_bits(read_u64(b, at))
}

fn read_f32(b: &[u8], at: usize) -> f32 {
    f32::from_bits(read_u32(b, at))
}

/// Decodes a frame message, checking magic, version, lengths and pose; the images are returned
/// undecoded.
pub fn decode_frame(b: &[u8]) -> Result<FrameMessage<'_>, ProtocolError> {
    if b.len() < FRAME_HEADER_BYTES {
        let mut e = bad_frame(format!(
            "frame message of {} bytes is shorter than its {FRAME_HEADER_BYTES}-byte header",
            b.len()
        ));
        // Name the frame when enough of the header arrived, so the client can count it answered.
        if b.len() >= 16 && b[0..4] == FRAME_MAGIC {
            e.frame_index = Some(read_u64(b, 8));
        }
        return Err(e);
    }
    if b[0..4] != FRAME_MAGIC {
        return Err(bad_frame(
            "binary message does not start with the frame magic \"MRPF\"",
        ));
    }
    let frame_index = read_u64(b, 8);
    let with_index = |mut e: ProtocolError| {
        e.frame_index = Some(frame_index);
        e
    };
    if u32::from(b[4]) != PROTOCOL_VERSION {
        return Err(with_index(ProtocolError::new(
            ErrorCode::UnsupportedVersion,
            format!(
                "frame {frame_index}: message version {} is not supported; this server speaks {PROTOCOL_VERSION}",
                b[4]
            ),
        )));
    }
    let encoding = Encoding::from_code(b[5])
        .ok_or_else(|| with_index(bad_frame(format!("unknown image encoding code {}", b[5]))))?;
    let flags = read_u16(b, 6);
    if flags & !FRAME_FLAG_POSE != 0 {
        return Err(with_index(bad_frame(format!(
            "unknown frame flags {flags:#06x}"
        ))));
    }
    let t_s = read_f64(b, 16);
    let left_len = read_u32(b, 24) as usize;
    let right_len = read_u32(b, 28) as usize;
    let pose_len = if flags & FRAME_FLAG_POSE != 0 {
        POSE_BYTES
    } else {
        0
    };
    let expected = FRAME_HEADER_BYTES + pose_len + left_len + right_len;
    if b.len() != expected {
        return Err(with_index(bad_frame(format!(
            "frame {frame_index}: message is {} bytes but its header announces {expected} \
             ({FRAME_HEADER_BYTES} header + {pose_len} pose + {left_len} left + {right_len} right)",
            b.len()
        ))));
    }
    if !t_s.is_finite() {
        return Err(with_index(ProtocolError::new(
            ErrorCode::BadTimestamp,
            format!("frame {frame_index}: timestamp {t_s} is not finite"),
        )));
    }
    let world_from_rig = if pose_len > 0 {
        let mut m = [0.0; 16];
        for (k, v) in m.iter_mut().enumerate() {
            *v = read_f64(b, FRAME_HEADER_BYTES + 8 * k);
        }
        Some(isometry_from_row_major("world_from_rig", &m).map_err(|e| {
            with_index(bad_frame(format!(
                "frame {frame_index}: world_from_rig is not a rigid transform: {e}"
            )))
        })?)
    } else {
        None
    };
    let images = FRAME_HEADER_BYTES + pose_len;
    Ok(FrameMessage {
        encoding,
        frame_index,
        t_s,
        world_from_rig,
        left: &b[images..images + left_len],
        right: &b[images + left_len..],
    })
}

/// Encodes a frame message (the reference client's side).
pub fn encode_frame(frame: &FrameMessage<'_>) -> Result<Vec<u8>, ProtocolError> {
    let too_big = |side: &str| bad_frame(format!("{side} image exceeds 4 GiB"));
    let left_len = u32::try_from(frame.left.len()).map_err(|_| too_big("left"))?;
    let right_len = u32::try_from(frame.right.len()).map_err(|_| too_big("right"))?;
    let mut b =
        Vec::with_capacity(FRAME_HEADER_BYTES + POSE_BYTES + frame.left.len() + frame.right.len());
    b.extend_from_slice(&FRAME_MAGIC);
    b.push(PROTOCOL_VERSION as u8);
    b.push(frame.encoding.code());
    let flags = if frame.world_from_rig.is_some() {
        FRAME_FLAG_POSE
    } else {
        0
    };
    b.extend_from_slice(&flags.to_le_bytes());
    b.extend_from_slice(&frame.frame_index.to_le_bytes());
    b.extend_from_slice(&frame.t_s.to_le_bytes());
    b.extend_from_slice(&left_len.to_le_bytes());
    b.extend_from_slice(&right_len.to_le_bytes());
    if let Some(pose) = &frame.world_from_rig {
        for v in isometry_to_row_major(pose) {
            b.extend_from_slice(&v.to_le_bytes());
        }
    }
    b.extend_from_slice(frame.left);
    b.extend_from_slice(frame.right);
    Ok(b)
}

/// Which estimate a batch carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum BatchKind {
    /// For the newest frame, sent as soon as it is processed.
    Causal,
    /// Centred moving-least-squares estimates, `M` frames after the frame they describe.
    Refined,
}

impl BatchKind {
    fn code(self) -> u8 {
        match self {
            BatchKind::Causal => 1,
            BatchKind::Refined => 2,
        }
    }
}

/// One session's vectors for one frame, in the engine's frame (OpenCV axes, world of the poses);
/// encoded per receiver in the receiver's convention.
#[derive(Debug, Clone, PartialEq)]
pub struct Batch {
    pub kind: BatchKind,
    pub session_number: u32,
    pub frame_index: u64,
    pub t_s: f64,
    /// The frame the vectors describe came with a pose: coordinates are in the world frame.
    pub world: bool,
    /// Pipeline time of the frame whose processing produced this batch, microseconds.
    pub processing_us: u32,
    /// Server time from that frame's arrival (its last byte read) to this batch being ready to
    /// send, microseconds: queue wait, decode and pipeline. A viewer adds half its round trip
    /// (`ping`) to estimate how old what it draws is.
    pub age_us: u32,
    pub vectors: Vec<VelocityVector>,
}

impl Batch {
    /// The batch as protocol 1's first layout gives it: header and records.
    pub fn encode(&self, convention: Convention) -> Vec<u8> {
        self.encode_with(convention, false)
    }

    /// With `sigmas`, each vector's velocity errors follow the records (header flag bit 1).
    pub fn encode_with(&self, convention: Convention, sigmas: bool) -> Vec<u8> {
        let per_vector = BATCH_RECORD_BYTES + if sigmas { BATCH_SIGMA_BYTES } else { 0 };
        let mut b = Vec::with_capacity(BATCH_HEADER_BYTES + per_vector * self.vectors.len());
        b.extend_from_slice(&BATCH_MAGIC);
        b.push(PROTOCOL_VERSION as u8);
        b.push(self.kind.code());
        b.push(convention.code());
        let mut header_flags = if self.world { BATCH_FLAG_WORLD } else { 0 };
        if sigmas {
            header_flags |= BATCH_FLAG_SIGMAS;
        }
        b.push(header_flags);
        b.extend_from_slice(&self.session_number.to_le_bytes());
        // A batch never holds more than u32::MAX vectors: the pipeline makes one per track.
        let count = u32::try_from(self.vectors.len()).unwrap_or(u32::MAX);
        b.extend_from_slice(&count.to_le_bytes());
        b.extend_from_slice(&self.frame_index.to_le_bytes());
        b.extend_from_slice(&self.t_s.to_le_bytes());
        b.extend_from_slice(&self.processing_us.to_le_bytes());
        b.extend_from_slice(&self.age_us.to_le_bytes());
        let mut flags = 0;
        if self.kind == BatchKind::Refined {
            flags |= VECTOR_FLAG_REFINED;
        }
        if self.world {
            flags |= VECTOR_FLAG_WORLD;
        }
        for v in self.vectors.iter().take(count as usize) {
            b.extend_from_slice(&v.track_id.to_le_bytes());
            let p = convention.flip(&v.position_in_world.coords);
            let u = convention.flip(&v.velocity_in_world);
            for x in p.iter().chain(u.iter()) {
                b.extend_from_slice(&(*x as f32).to_le_bytes());
            }
            b.extend_from_slice(&(v.rms_residual_m as f32).to_le_bytes());
            b.extend_from_slice(&flags.to_le_bytes());
            b.extend_from_slice(&0u16.to_le_bytes());
        }
        if sigmas {
            // A convention only flips axes: a spread keeps its value.
            for v in self.vectors.iter().take(count as usize) {
                for s in v.velocity_sigma.iter() {
                    b.extend_from_slice(&(*s as f32).to_le_bytes());
                }
            }
        }
        b
    }
}

/// One vector as it travels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WireVector {
    pub track_id: u64,
    pub position_m: [f32; 3],
    pub velocity_m_per_s: [f32; 3],
    pub(crate) rms_residual_m: f32,
    pub flags: u16,
    /// 1-sigma velocity errors, m/s, where the batch carries them.
    pub velocity_sigma: Option<[f32; 3]>,
}

impl WireVector {
    pub fn refined(&self) -> bool {
        self.flags & VECTOR_FLAG_REFINED != 0
    }
}

/// A decoded vector batch (the clients' side).
#[derive(Debug, Clone, PartialEq)]
pub struct DecodedBatch {
    pub kind: BatchKind,
    pub convention: Convention,
    pub world: bool,
    pub session_number: u32,
    pub frame_index: u64,
    pub(crate) t_s: f64,
    pub processing_us: u32,
    pub age_us: u32,
    pub vectors: Vec<WireVector>,
}

pub fn decode_batch(b: &[u8]) -> Result<DecodedBatch, ProtocolError> {
    if b.len() < BATCH_HEADER_BYTES || b[0..4] != BATCH_MAGIC {
        return Err(bad_frame(
            "not a vector batch (magic \"MRPV\", 40-byte header)",
        ));
    }
    if u32::from(b[4]) != PROTOCOL_VERSION {
        return Err(ProtocolError::new(
            ErrorCode::UnsupportedVersion,
            format!("vector batch version {}", b[4]),
        ));
    }
    let kind = match b[5] {
        1 => BatchKind::Causal,
        2 => BatchKind::Refined,
        k => return Err(bad_frame(format!("unknown batch kind {k}"))),
    };
    let convention = Convention::from_code(b[6])
        .ok_or_else(|| bad_frame(format!("unknown convention code {}", b[6])))?;
    let count = read_u32(b, 12) as usize;
    let sigmas = b[7] & BATCH_FLAG_SIGMAS != 0;
    let per_vector = BATCH_RECORD_BYTES + if sigmas { BATCH_SIGMA_BYTES } else { 0 };
    let expected = count
        .checked_mul(per_vector)
        .and_then(|n| n.checked_add(BATCH_HEADER_BYTES));
    if expected != Some(b.len()) {
        return Err(bad_frame(format!(
            "batch of {} bytes announces {count} vectors",
            b.len()
        )));
    }
    let vectors = (0..count)
        .map(|i| {
            let at = BATCH_HEADER_BYTES + i * BATCH_RECORD_BYTES;
            WireVector {
                track_id: read_u64(b, at),
                position_m: [0, 1, 2].map(|k| read_f32(b, at + 8 + 4 * k)),
                velocity_m_per_s: [0, 1, 2].map(|k| read_f32(b, at + 20 + 4 * k)),
                rms_residual_m: read_f32(b, at + 32),
                flags: read_u16(b, at + 36),
                velocity_sigma: sigmas.then(|| {
                    let at =
                        BATCH_HEADER_BYTES + count * BATCH_RECORD_BYTES + i * BATCH_SIGMA_BYTES;
                    [0, 1, 2].map(|k| read_f32(b, at + 4 * k))
                }),
            }
        })
        .collect();
    Ok(DecodedBatch {
        kind,
        convention,
        world: b[7] & BATCH_FLAG_WORLD != 0,
        session_number: read_u32(b, 8),
        frame_index: read_u64(b, 16),
        t_s: read_f64(b, 24),
        processing_us: read_u32(b, 32),
        age_us: read_u32(b, 36),
        vectors,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Point3, Translation3, UnitQuaternion};

    fn pose() -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(0.1, -0.2, 0.3),
            UnitQuaternion::from_euler_angles(0.1, 0.2, -0.3),
        )
    }

    #[test]
    fn a_frame_round_trips_byte_for_byte() {
        let left = [1u8, 2, 3, 4, 5, 6];
        let right = [9u8, 8, 7, 6, 5, 4];
        let frame = FrameMessage {
            encoding: Encoding::Raw8,
            frame_index: 7,
            t_s: 0.25,
            world_from_rig: Some(pose()),
            left: &left,
            right: &right,
        };
        let bytes = encode_frame(&frame).expect("encodes");
        assert_eq!(bytes.len(), FRAME_HEADER_BYTES + POSE_BYTES + 12);
        let back = decode_frame(&bytes).expect("decodes");
        assert_eq!((back.frame_index, back.t_s), (7, 0.25));
        assert_eq!((back.left, back.right), (&left[..], &right[..]));
        let p = back.world_from_rig.expect("pose");
        assert!((p.to_homogeneous() - pose().to_homogeneous()).abs().max() < 1e-12);
    }

    #[test]
    fn every_truncation_of_a_frame_is_refused_cleanly() {
        let left = [1u8; 20];
        let frame = FrameMessage {
            encoding: Encoding::Raw8,
            frame_index: 3,
            t_s: 1.0,
            world_from_rig: Some(pose()),
            left: &left,
            right: &left,
        };
        let bytes = encode_frame(&frame).expect("encodes");
        for n in 0..bytes.len() {
            let e = decode_frame(&bytes[..n]).expect_err("truncated");
            assert_eq!(e.code, ErrorCode::BadFrame, "{n}: {e}");
        }
    }

    #[test]
    fn conventions_flip_axes_and_keep_poses_rigid() {
        let p = Vector3::new(1.0, 2.0, 3.0);
        assert_eq!(Convention::Unity.flip(&p), Vector3::new(1.0, -2.0, 3.0));
        assert_eq!(Convention::WebXr.flip(&p), Vector3::new(1.0, -2.0, -3.0));
        // A pose in a convention maps a point given in that convention like the OpenCV pose maps
        // the OpenCV point.
        for c in [Convention::OpenCv, Convention::Unity, Convention::WebXr] {
            let in_convention = pose();
            let cv = c.flip_pose(&in_convention).expect("rigid");
            let x_cv = Point3::new(0.3, -0.1, 1.2);
            let x_conv = Point3::from(c.flip(&x_cv.coords));
            let via_convention = c.flip(&(in_convention * x_conv).coords);
            assert!(
                ((cv * x_cv).coords - via_convention).norm() < 1e-12,
                "{c:?}"
            );
        }
    }

    #[test]
    fn batches_round_trip_in_each_convention() {
        let v = VelocityVector {
            frame_index: 4,
            t_s: 0.5,
            track_id: 11,
            position_in_world: Point3::new(0.1, 0.2, 1.5),
            velocity_in_world: Vector3::new(0.01, -0.02, 0.03),
            rms_residual_m: 1e-4,
            velocity_sigma: Vector3::new(1e-3, 2e-3, 5e-3),
            position_sigma: Vector3::new(1e-4, 1e-4, 5e-4),
        };
        let batch = Batch {
            kind: BatchKind::Refined,
            session_number: 2,
            frame_index: 4,
            t_s: 0.5,
            world: true,
            processing_us: 1234,
            age_us: 5678,
            vectors: vec![v, v],
        };
        let bytes = batch.encode(Convention::WebXr);
        assert_eq!(bytes.len(), BATCH_HEADER_BYTES + 2 * BATCH_RECORD_BYTES);
        let back = decode_batch(&bytes).expect("decodes");
        assert_eq!(back.kind, BatchKind::Refined);
        assert_eq!(back.vectors.len(), 2);
        assert_eq!(back.vectors[0].position_m, [0.1, -0.2, -1.5]);
        assert!(back.vectors[0].refined());
        assert_eq!(back.processing_us, 1234);
        assert_eq!(back.age_us, 5678);
        assert!(decode_batch(&bytes[..bytes.len() - 1]).is_err());
    }

    #[test]
    fn text_errors_are_told_apart() {
        let code = |t: &str| {
            parse_text::<HeadsetMessage>(t, HEADSET_TYPES)
                .expect_err("refused")
                .code
        };
        assert_eq!(code("{not json"), ErrorCode::MalformedJson);
        assert_eq!(code(r#"{"kind":"hello"}"#), ErrorCode::UnknownType);
        assert_eq!(code(r#"{"type":"launch"}"#), ErrorCode::UnknownType);
        assert_eq!(
            code(r#"{"type":"hello","protocol":2}"#),
            ErrorCode::UnsupportedVersion
        );
        assert_eq!(
            code(r#"{"type":"hello","protocol":1}"#),
            ErrorCode::BadHello
        );
        assert!(matches!(
            parse_text::<HeadsetMessage>(r#"{"type":"bye"}"#, HEADSET_TYPES),
            Ok(HeadsetMessage::Bye {})
        ));
        assert_eq!(
            code(r#"{"type":"bye","reason":"done"}"#),
            ErrorCode::MalformedJson,
            "a field bye does not have"
        );
        let hello = |rig: &str| {
            format!(
                r#"{{"type":"hello","protocol":1,"client":"c","rig":{rig},"image":{{"width":4,"height":2,"encoding":"raw8"}}}}"#
            )
        };
        assert_eq!(
            code(&hello(
                r#"{"image_size":[4,2],"K1":[[1,0,0],[0,1,0],[0,0,1]],"typo":1}"#
            )),
            ErrorCode::BadCalibration,
            "anything wrong inside rig is the calibration's"
        );
        assert_eq!(code(&hello(r#"[]"#)), ErrorCode::BadCalibration);
        assert_eq!(
            code(&hello(r#"{}"#).replace("\"client\":\"c\",", "")),
            ErrorCode::BadCalibration,
            "the rig is read before the rest of hello"
        );
        let viewer = |t: &str| {
            parse_text::<ViewerMessage>(t, VIEWER_TYPES)
                .map_err(|e| e.code)
                .err()
        };
        assert_eq!(viewer(r#"{"type":"list"}"#), None);
        assert_eq!(viewer(r#"{"type":"unsubscribe"}"#), None);
        for extra in [
            r#"{"type":"list","all":true}"#,
            r#"{"type":"unsubscribe","session":"s1"}"#,
            r#"{"type":"ping","id":1,"at":2}"#,
            r#"{"type":"subscribe","session":"*","format":"x"}"#,
        ] {
            assert_eq!(viewer(extra), Some(ErrorCode::MalformedJson), "{extra}");
        }
    }
}
