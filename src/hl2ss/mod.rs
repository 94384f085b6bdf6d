//! The wire formats and geometry of the public hl2ss HoloLens 2 streaming app
//! (github.com/jdibenes/hl2ss), for `mrptv hl2ss`: pure encode/decode and conversions, no I/O.
//!
//! Facts used (hl2ss server `stream_rm_vlc.cpp`, client `viewer/hl2ss.py`, `hl2ss_3dcv.py`):
//! - Visible-light cameras on TCP ports 3800 (LeftFront) and 3802 (RightFront). The client sends
//!   a configuration: `<B mode>` then, for modes 0 and 1, `<B divisor>`, `<B profile, B level,
//!   u32 bitrate>`, `<B n>` and n `<u64 key, u64 value>` options, all little-endian. Mode 0:
//!   images; mode 1: images and poses; mode 2: the calibration (nothing else is sent).
//!   Profile 0xFF is raw (uncompressed L8).
//! - Each frame: `u64 timestamp` (QPC, 100 ns units), `u32 payload size`, the payload (raw: 640x480
//!   L8 pixels, then a 24-byte trailer: `u64 sensor_ticks, u64 exposure, u32 gain, u32 reserved`),
//!   then in mode 1 the rig node's pose: 16 f32, row-major, *row-vector* convention
//!   (`p_world = p_rig * M`, translation in the last row); all zeros when tracking was lost.
//! - Calibration (mode 2): 1,228,820 f32 = `uv2x` (640x480), `uv2y`, `extrinsics` (4x4,
//!   row-vector, rig node -> camera), `mapx`, `mapy` (undistortion maps), `K` (fx, fy, cx, cy of a
//!   virtual undistorted pinhole). `uv2xy[v][u]` is the point on the camera's z = 1 plane seen at
//!   the *centre* of pixel (u, v) (Research Mode maps `(u + 0.5, v + 0.5)` with the pixel's corner
//!   at 0; in OpenCV's convention, which `rig.json` uses, that centre is `(u, v)`).
//!
//! Submodules with I/O: [`bridge`] turns the streams into a headset
//! session (`mrptv hl2ss`); [`holograms`] draws the vectors back through the Unity plugin's
//! message queue (`mrptv hl2ss --holograms`).

pub mod bridge;
pub mod clock;
pub mod holograms;

use nalgebra::{Isometry3, Matrix4, SMatrix, SVector};

use mrptv_engine::geometry::{isometry_from_row_major, CameraModel, Distortion, StereoRig};

pub const LEFT_FRONT_PORT: u16 = 3800;
pub const RIGHT_FRONT_PORT: u16 = 3802;
pub(crate) const VLC_WIDTH: u32 = 640;
pub(crate) const VLC_HEIGHT: u32 = 480;
pub const VLC_PIXELS: usize = (VLC_WIDTH * VLC_HEIGHT) as usize;
/// `sensor_ticks`, `exposure`, `gain`, reserved.
pub(crate) const VLC_METADATA_BYTES: usize = 24;
pub(crate) const POSE_BYTES: usize = 64;
/// Frame header: timestamp and payload size.
pub(crate) const HEADER_BYTES: usize = 12;
/// uv2x, uv2y, extrinsics, mapx, mapy, K.
pub(crate) const CALIBRATION_FLOATS: usize = 4 * VLC_PIXELS + 16 + 4;
pub(crate) const PROFILE_RAW: u8 = 0xFF;
/// hl2ss's `VideoProfile.H264_BASE`: constrained baseline, what OpenH264 decodes.
pub const PROFILE_H264_BASE: u8 = 0;
/// hl2ss's client default GOP for encoded streams: one IDR (with its SPS and PPS) a second.
pub const H264_GOP_FRAMES: u64 = 30;
pub(crate) const LEVEL_DEFAULT: u8 = 0xFF;
/// hl2ss's own default for raw VLC streams (the server refuses 0 even when raw).
pub(crate) const RAW_BITRATE: u32 = 640 * 480 * 30 * 12;
/// `CODECAPI_AVEncMPVGOPSize`, set to 1 by hl2ss's client for raw streams.
pub(crate) const OPTION_GOP_SIZE: u64 = 10;
/// `HL2SSAPI_VLCHostTicksOffsetExposure`: the server stamps a frame `host_ticks + factor *
/// exposure / 100 + constant` (the factor a double's bits) and locates its pose at that time.
pub const OPTION_TICKS_OFFSET_EXPOSURE: u64 = 0xFFFF_FFFF_FFFF_FFFF;
/// `HL2SSAPI_VLCHostTicksOffsetConstant`, 100 ns ticks as an i64's bits.
pub const OPTION_TICKS_OFFSET_CONSTANT: u64 = 0xFFFF_FFFF_FFFF_FFFE;
/// What hl2ss's client sends since v1.0.33: host ticks run 12.5 ms after mid-exposure, so
/// these stamp each frame (and locate its pose) at mid-exposure. Without them a current server
/// stamps raw host ticks: poses 12.5 ms late.
pub(crate) const TICKS_OFFSET_EXPOSURE_FACTOR: f64 = 0.0;
pub(crate) const TICKS_OFFSET_CONSTANT: i64 = -125_000;
/// The oldest hl2ss whose wire format the bridge speaks: the frame trailer and the timestamp
/// options the bridge sets both date from it.
pub(crate) const OLDEST_SUPPORTED_VERSION: &str = "1.0.33";
/// QPC ticks (100 ns) per second.
pub(crate) const TICKS_PER_SECOND: f64 = 1e7;

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Hl2ssError {
    #[error("configuration: {0}")]
    Configuration(String),
    #[error("frame: {0}")]
    Frame(String),
    #[error("calibration: {0}")]
    Calibration(String),
    #[error("pose: {0}")]
    Pose(String),
}

/// How a camera's images come: raw, or compressed by the HoloLens's encoder.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum VlcCodec {
    Raw,
    H264,
    /// hl2ss's client default; this build has no HEVC decoder and refuses it.
    Hevc,
}

impl std::str::FromStr for VlcCodec {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "raw" => Ok(VlcCodec::Raw),
            "h264" => Ok(VlcCodec::H264),
            "hevc" => Ok(VlcCodec::Hevc),
            _ => Err(format!("{s:?}: expected raw, h264 or hevc")),
        }
    }
}

/// What the client asks a stream for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StreamMode {
    Images = 0,
    ImagesAndPoses = 1,
    Calibration = 2,
}

/// The configuration a client sends on connecting.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StreamConfig {
    pub(crate) mode: StreamMode,
    /// Send every n-th frame.
    pub(crate) divisor: u8,
    pub profile: u8,
    pub(crate) level: u8,
    pub bitrate: u32,
    pub options: Vec<(u64, u64)>,
}

impl StreamConfig {
    /// Raw frames with poses, every frame: what the bridge asks for.
    pub fn raw_with_poses() -> Self {
        Self {
            mode: StreamMode::ImagesAndPoses,
            divisor: 1,
            profile: PROFILE_RAW,
            level: LEVEL_DEFAULT,
            bitrate: RAW_BITRATE,
            options: vec![
                (OPTION_GOP_SIZE, 1),
                (
                    OPTION_TICKS_OFFSET_EXPOSURE,
                    TICKS_OFFSET_EXPOSURE_FACTOR.to_bits(),
                ),
                (OPTION_TICKS_OFFSET_CONSTANT, TICKS_OFFSET_CONSTANT as u64),
            ],
        }
    }

    /// H.264 (constrained baseline) at `bitrate` bits a second with poses: exactly what hl2ss's
    /// own client (`hl2ss_lnm.rx_rm_vlc(mode=MODE_1, profile=H264_BASE, bitrate=...)`) sends:
    /// its default GOP option, then the two timestamp options.
    pub fn h264_with_poses(bitrate: u32) -> Self {
        let mut config = Self::raw_with_poses();
        config.profile = PROFILE_H264_BASE;
        config.bitrate = bitrate;
        config.options[0] = (OPTION_GOP_SIZE, H264_GOP_FRAMES);
        config
    }

    pub(crate) fn calibration() -> Self {
        Self {
            mode: StreamMode::Calibration,
            ..Self::raw_with_poses()
        }
    }

    pub(crate) fn encode(&self) -> Vec<u8> {
        let mut b = vec![self.mode as u8];
        if self.mode == StreamMode::Calibration {
            return b;
        }
        b.push(self.divisor);
        b.push(self.profile);
        b.push(self.level);
        b.extend_from_slice(&self.bitrate.to_le_bytes());
        b.push(self.options.len() as u8);
        for (k, v) in &self.options {
            b.extend_from_slice(&k.to_le_bytes());
            b.extend_from_slice(&v.to_le_bytes());
        }
        b
    }

    /// Decodes a whole configuration (a fake server's side); errors name what is wrong.
    pub fn decode(b: &[u8]) -> Result<Self, Hl2ssError> {
        let bad = |m: String| Hl2ssError::Configuration(m);
        let mode = match b.first() {
            Some(0) => StreamMode::Images,
            Some(1) => StreamMode::ImagesAndPoses,
            Some(2) => StreamMode::Calibration,
            Some(m) => return Err(bad(format!("unknown mode {m}"))),
            None => return Err(bad("empty".into())),
        };
        if mode == StreamMode::Calibration {
            if b.len() != 1 {
                return Err(bad(format!(
                    "calibration request of {} bytes, not 1",
                    b.len()
                )));
            }
            return Ok(Self::calibration());
        }
        if b.len() < 9 {
            return Err(bad(format!(
                "{} bytes, shorter than the 9 before the options",
                b.len()
            )));
        }
        let n = usize::from(b[8]);
        if b.len() != 9 + 16 * n {
            return Err(bad(format!(
                "{} bytes, but {n} options make {}",
                b.len(),
                9 + 16 * n
            )));
        }
        let u64_at = |at: usize| {
            let mut a = [0; 8];
            a.copy_from_slice(&b[at..at + 8]);
            u64::from_le_bytes(a)
        };
        let config = Self {
            mode,
            divisor: b[1],
            profile: b[2],
            level: b[3],
            bitrate: u32::from_le_bytes([b[4], b[5], b[6], b[7]]),
            options: (0..n)
                .map(|i| (u64_at(9 + 16 * i), u64_at(17 + 16 * i)))
                .collect(),
        };
        if config.divisor == 0 || config.bitrate == 0 {
            return Err(bad("divisor and bitrate must be positive".into()));
        }
        Ok(config)
    }

    /// Bytes the client sends, for a reader that has the first 9.
    pub fn options_bytes(head: &[u8; 9]) -> usize {
        16 * usize::from(head[8])
    }
}

/// One raw frame of a visible-light camera.
#[derive(Debug, Clone, PartialEq)]
pub struct VlcFrame {
    /// QPC time, 100 ns units.
    pub timestamp: u64,
    pub pixels: Vec<u8>,
    pub sensor_ticks: u64,
    pub exposure: u64,
    pub gain: u32,
    /// Row-vector rig-node -> world, as sent; `None` when hl2ss sent zeros (tracking lost).
    pub pose: Option<[f32; 16]>,
}

/// `(timestamp, payload bytes)` of a frame header.
pub(crate) fn decode_header(h: &[u8; HEADER_BYTES]) -> (u64, usize) {
    let mut t = [0; 8];
    t.copy_from_slice(&h[..8]);
    (
        u64::from_le_bytes(t),
        u32::from_le_bytes([h[8], h[9], h[10], h[11]]) as usize,
    )
}

impl VlcFrame {
    /// From a raw payload (pixels and trailer) and, in mode 1, the 64 pose bytes.
    pub(crate) fn decode(
        timestamp: u64,
        payload: &[u8],
        pose: Option<&[u8]>,
    ) -> Result<Self, Hl2ssError> {
        if payload.len() == VLC_PIXELS {
            return Err(Hl2ssError::Frame(format!(
                "payload of {VLC_PIXELS} bytes: a bare image without the 24-byte trailer, as hl2ss \
                 before v{OLDEST_SUPPORTED_VERSION} sends; mrptv hl2ss needs hl2ss \
                 v{OLDEST_SUPPORTED_VERSION} or later on the HoloLens: update its hl2ss app"
            )));
        }
        if payload.len() != VLC_PIXELS + VLC_METADATA_BYTES {
            return Err(Hl2ssError::Frame(format!(
                "payload of {} bytes; a raw 640x480 frame and its trailer are {} (is the stream raw?)",
                payload.len(),
                VLC_PIXELS + VLC_METADATA_BYTES
            )));
        }
        Self::decode_with(timestamp, payload, pose, |pixels| Ok(pixels.to_vec()))
    }

    /// From any payload (the image as the stream's codec sent it, then the 24-byte trailer),
    /// `image` turning the codec's bytes into 640x480 pixels.
    pub(crate) fn decode_with(
        timestamp: u64,
        payload: &[u8],
        pose: Option<&[u8]>,
        image: impl FnOnce(&[u8]) -> Result<Vec<u8>, Hl2ssError>,
    ) -> Result<Self, Hl2ssError> {
        let Some(image_bytes) = payload.len().checked_sub(VLC_METADATA_BYTES) else {
            return Err(Hl2ssError::Frame(format!(
                "payload of {} bytes, shorter than its {VLC_METADATA_BYTES}-byte trailer",
                payload.len()
            )));
        };
        let trailer = &payload[image_bytes..];
        let u64_at = |at: usize| {
            let mut a = [0; 8];
            a.copy_from_slice(&trailer[at..at + 8]);
            u64::from_le_bytes(a)
        };
        let pose = match pose {
            None => None,
            Some(p) if p.len() != POSE_BYTES => {
                return Err(Hl2ssError::Frame(format!(
                    "pose of {} bytes, not {POSE_BYTES}",
                    p.len()
                )))
            }
            Some(p) => {
                let mut m = [0f32; 16];
                for (k, v) in m.iter_mut().enumerate() {
                    *v = f32::from_le_bytes([p[4 * k], p[4 * k + 1], p[4 * k + 2], p[4 * k + 3]]);
                }
                // hl2ss's own test of a valid pose.
                (m[15] != 0.0).then_some(m)
            }
        };
        let pixels = image(&payload[..image_bytes])?;
        if pixels.len() != VLC_PIXELS {
            return Err(Hl2ssError::Frame(format!(
                "an image of {} pixels, not 640x480",
                pixels.len()
            )));
        }
        Ok(Self {
            timestamp,
            pixels,
            sensor_ticks: u64_at(0),
            exposure: u64_at(8),
            gain: u32::from_le_bytes([trailer[16], trailer[17], trailer[18], trailer[19]]),
            pose,
        })
    }

    /// The frame as hl2ss sends it raw (a fake server's side).
    pub fn encode(&self) -> Vec<u8> {
        self.encode_as(&self.pixels)
    }

    /// The frame as hl2ss sends it with its image as `image` (a codec's bytes for it).
    pub fn encode_as(&self, image: &[u8]) -> Vec<u8> {
        let payload = image.len() + VLC_METADATA_BYTES;
        let mut b = Vec::with_capacity(HEADER_BYTES + payload + POSE_BYTES);
        b.extend_from_slice(&self.timestamp.to_le_bytes());
        b.extend_from_slice(&(payload as u32).to_le_bytes());
        b.extend_from_slice(image);
        b.extend_from_slice(&self.sensor_ticks.to_le_bytes());
        b.extend_from_slice(&self.exposure.to_le_bytes());
        b.extend_from_slice(&self.gain.to_le_bytes());
        b.extend_from_slice(&0u32.to_le_bytes());
        if let Some(m) = &self.pose {
            for v in m {
                b.extend_from_slice(&v.to_le_bytes());
            }
        }
        b
    }
}

/// A column-vector isometry from a row-vector 4x4 (`p' = p * M`): the transpose, checked rigid.
pub(crate) fn isometry_from_row_vector(
    field: &str,
    m: &[f32; 16],
) -> Result<Isometry3<f64>, Hl2ssError> {
    let row_vector = Matrix4::from_row_slice(&m.map(f64::from));
    let column = row_vector.transpose();
    let mut row_major = [0.0; 16];
    for (i, v) in row_major.iter_mut().enumerate() {
        *v = column[(i / 4, i % 4)];
    }
    isometry_from_row_major(field, &row_major).map_err(|e| Hl2ssError::Pose(e.to_string()))
}

/// The inverse of `isometry_from_row_vector` (a fake server's side).
pub fn row_vector_from_isometry(pose: &Isometry3<f64>) -> [f32; 16] {
    let m = pose.to_homogeneous().transpose();
    let mut out = [0f32; 16];
    for (i, v) in out.iter_mut().enumerate() {
        *v = m[(i / 4, i % 4)] as f32;
    }
    out
}

/// A camera's calibration as hl2ss sends it (mode 2).
#[derive(Debug, Clone, PartialEq)]
pub struct VlcCalibration {
    /// Per pixel, row-major (v * 640 + u): the point on the z = 1 plane seen at its centre.
    pub(crate) uv2x: Vec<f32>,
    pub(crate) uv2y: Vec<f32>,
    /// Row-vector rig node -> camera.
    pub(crate) extrinsics: [f32; 16],
    pub(crate) mapx: Vec<f32>,
    pub(crate) mapy: Vec<f32>,
    /// fx, fy, cx, cy of hl2ss's virtual undistorted pinhole.
    pub(crate) k: [f32; 4],
}

impl VlcCalibration {
    pub(crate) fn decode(b: &[u8]) -> Result<Self, Hl2ssError> {
        if b.len() != 4 * CALIBRATION_FLOATS {
            return Err(Hl2ssError::Calibration(format!(
                "{} bytes, not {}",
                b.len(),
                4 * CALIBRATION_FLOATS
            )));
        }
        let floats: Vec<f32> = b
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        let (uv2x, rest) = floats.split_at(VLC_PIXELS);
        let (uv2y, rest) = rest.split_at(VLC_PIXELS);
        let (extrinsics, rest) = rest.split_at(16);
        let (mapx, rest) = rest.split_at(VLC_PIXELS);
        let (mapy, k) = rest.split_at(VLC_PIXELS);
        let mut e = [0f32; 16];
        e.copy_from_slice(extrinsics);
        Ok(Self {
            uv2x: uv2x.to_vec(),
            uv2y: uv2y.to_vec(),
            extrinsics: e,
            mapx: mapx.to_vec(),
            mapy: mapy.to_vec(),
            k: [k[0], k[1], k[2], k[3]],
        })
    }

    pub fn encode(&self) -> Vec<u8> {
        let mut b = Vec::with_capacity(4 * CALIBRATION_FLOATS);
        for part in [
            &self.uv2x[..],
            &self.uv2y[..],
            &self.extrinsics[..],
            &self.mapx[..],
            &self.mapy[..],
            &self.k[..],
        ] {
            for v in part {
                b.extend_from_slice(&v.to_le_bytes());
            }
        }
        b
    }

    /// What hl2ss would send for a known camera (fake servers and tests): every pixel centre
    /// unprojected (NaN where the model cannot invert), the extrinsics, and placeholder maps.
    pub fn from_camera(camera: &CameraModel, camera_from_node: &Isometry3<f64>) -> Self {
        let mut uv2x = Vec::with_capacity(VLC_PIXELS);
        let mut uv2y = Vec::with_capacity(VLC_PIXELS);
        for v in 0..VLC_HEIGHT {
            for u in 0..VLC_WIDTH {
                let (x, y) = camera
                    .unproject(mrptv_engine::geometry::PixelPoint {
                        x: f64::from(u),
                        y: f64::from(v),
                    })
                    .unwrap_or((f64::NAN, f64::NAN));
                uv2x.push(x as f32);
                uv2y.push(y as f32);
            }
        }
        Self {
            uv2x,
            uv2y,
            extrinsics: row_vector_from_isometry(camera_from_node),
            mapx: vec![0.0; VLC_PIXELS],
            mapy: vec![0.0; VLC_PIXELS],
            k: [
                camera.fx as f32,
                camera.fy as f32,
                camera.cx as f32,
                camera.cy as f32,
            ],
        }
    }

    /// The camera's pose on the rig node, column-vector: `point_in_camera = camera_from_rig *
    /// point_in_rig`.
    pub(crate) fn camera_from_rig_node(&self) -> Result<Isometry3<f64>, Hl2ssError> {
        isometry_from_row_vector("extrinsics", &self.extrinsics)
    }
}

/// A lens model fitted to an unprojection table, and how well it fits.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LensFit {
    pub(crate) camera: CameraModel,
    /// Root mean square of the reprojection error over the pixels used, pixels.
    pub rms_px: f64,
    pub max_px: f64,
    pub pixels_used: usize,
}

const FIT_PARAMETERS: usize = 12;
type Params = SVector<f64, FIT_PARAMETERS>;

fn camera_of(p: &Params) -> CameraModel {
    CameraModel {
        fx: p[0],
        fy: p[1],
        cx: p[2],
        cy: p[3],
        skew: 0.0,
        distortion: Distortion {
            k1: p[4],
            k2: p[5],
            p1: p[6],
            p2: p[7],
            k3: p[8],
            k4: p[9],
            k5: p[10],
            k6: p[11],
        },
    }
}

fn project(p: &Params, x: f64, y: f64) -> (f64, f64) {
    let c = camera_of(p);
    let (xd, yd) = c.distortion.distort(x, y);
    (c.fx * xd + c.cx, c.fy * yd + c.cy)
}

/// Fits OpenCV's rational model (fx, fy, cx, cy, k1..k6, p1, p2: `rig.json`'s 8 coefficients)
/// to an unprojection table by Levenberg-Marquardt on the pixel reprojection error, over every
/// `step`-th pixel in each direction with a finite table entry.
pub(crate) fn fit_lens(
    uv2x: &[f32],
    uv2y: &[f32],
    width: u32,
    height: u32,
    step: usize,
) -> Result<LensFit, Hl2ssError> {
    let n = (width * height) as usize;
    if uv2x.len() != n || uv2y.len() != n {
        return Err(Hl2ssError::Calibration(format!(
            "unprojection tables are not {width}x{height}"
        )));
    }
    let samples = table_samples(uv2x, uv2y, width, height, step.max(1));
    if samples.len() < 100 {
        return Err(Hl2ssError::Calibration(format!(
            "only {} pixels with a finite unprojection",
            samples.len()
        )));
    }
    let (params, cost) = refine(&samples, central_pinhole(&samples)?);
    let max_px = samples
        .iter()
        .map(|&(x, y, u, v)| {
            let (pu, pv) = project(&params, x, y);
            ((pu - u).powi(2) + (pv - v).powi(2)).sqrt()
        })
        .fold(0.0, f64::max);
    Ok(LensFit {
        camera: camera_of(&params),
        rms_px: (cost / samples.len() as f64).sqrt(),
        max_px,
        pixels_used: samples.len(),
    })
}

/// A table entry the fit uses: the ray's normalised (x, y) and its pixel's (u, v).
type TableSample = (f64, f64, f64, f64);

/// Every `step`-th pixel of the tables, each way, that has a ray of its own.
fn table_samples(
    uv2x: &[f32],
    uv2y: &[f32],
    width: u32,
    height: u32,
    step: usize,
) -> Vec<TableSample> {
    let mut samples = Vec::new();
    for v in (0..height as usize).step_by(step) {
        for u in (0..width as usize).step_by(step) {
            let (x, y) = (
                f64::from(uv2x[v * width as usize + u]),
                f64::from(uv2y[v * width as usize + u]),
            );
            // hl2ss leaves a pixel that failed to map with its neighbour's value: no real
            // pixel sees exactly the ray of the one beside it.
            let repeated = u > 0
                && uv2x[v * width as usize + u - 1] == uv2x[v * width as usize + u]
                && uv2y[v * width as usize + u - 1] == uv2y[v * width as usize + u];
            // hl2ss leaves a pixel whose unprojection failed at (0, 0); only the principal
            // point's own ray is there, so dropping that one pixel costs nothing.
            let failed = x == 0.0 && y == 0.0;
            if x.is_finite() && y.is_finite() && !repeated && !failed {
                samples.push((x, y, u as f64, v as f64));
            }
        }
    }
    samples
}

/// The fit's start: a pinhole from the central pixels by linear least squares,
/// u = fx x + cx, v = fy y + cy, without distortion.
fn central_pinhole(samples: &[TableSample]) -> Result<Params, Hl2ssError> {
    let central: Vec<_> = samples
        .iter()
        .filter(|(x, y, ..)| x * x + y * y < 0.1)
        .copied()
        .collect();
    let line = |pairs: &mut dyn Iterator<Item = (f64, f64)>| {
        let (mut n, mut sx, mut sy, mut sxx, mut sxy) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for (a, b) in pairs {
            n += 1.0;
            sx += a;
            sy += b;
            sxx += a * a;
            sxy += a * b;
        }
        let slope = (n * sxy - sx * sy) / (n * sxx - sx * sx);
        (slope, (sy - slope * sx) / n)
    };
    let (fx, cx) = line(&mut central.iter().map(|s| (s.0, s.2)));
    let (fy, cy) = line(&mut central.iter().map(|s| (s.1, s.3)));
    if !(fx > 0.0 && fy > 0.0) {
        return Err(Hl2ssError::Calibration(format!(
            "the table's axes do not run with the image's (fx {fx:.1}, fy {fy:.1}): not an x-right, y-down camera"
        )));
    }
    let mut params = Params::zeros();
    params[0] = fx;
    params[1] = fy;
    params[2] = cx;
    params[3] = cy;
    Ok(params)
}

/// The sum of squared reprojection errors of `samples` under `p`, pixels squared.
fn reprojection_cost(samples: &[TableSample], p: &Params) -> f64 {
    samples
        .iter()
        .map(|&(x, y, u, v)| {
            let (pu, pv) = project(p, x, y);
            (pu - u).powi(2) + (pv - v).powi(2)
        })
        .sum()
}

/// Levenberg-Marquardt from `params` until a step no longer lowers the cost (at most 200
/// steps); the parameters and their cost.
fn refine(samples: &[TableSample], mut params: Params) -> (Params, f64) {
    let mut current = reprojection_cost(samples, &params);
    let mut lambda = 1e-3;
    for _ in 0..200 {
        let (jtj, jtr) = normal_equations(samples, &params);
        let mut improved = false;
        for _ in 0..10 {
            let mut damped = jtj;
            for k in 0..FIT_PARAMETERS {
                damped[(k, k)] += lambda * jtj[(k, k)].max(1e-12);
            }
            let Some(delta) = damped.cholesky().map(|c| c.solve(&(-jtr))) else {
                lambda *= 10.0;
                continue;
            };
            let candidate = params + delta;
            let c = reprojection_cost(samples, &candidate);
            if c.is_finite() && c < current {
                let relative = (current - c) / current.max(1e-300);
                params = candidate;
                current = c;
                lambda = (lambda / 3.0).max(1e-12);
                improved = relative > 1e-12;
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    (params, current)
}

/// J^T J and J^T r of the reprojection residuals at `params`, the Jacobian by forward
/// differences.
fn normal_equations(
    samples: &[TableSample],
    params: &Params,
) -> (SMatrix<f64, FIT_PARAMETERS, FIT_PARAMETERS>, Params) {
    let mut jtj = SMatrix::<f64, FIT_PARAMETERS, FIT_PARAMETERS>::zeros();
    let mut jtr = Params::zeros();
    for &(x, y, u, v) in samples {
        let (pu, pv) = project(params, x, y);
        let (ru, rv) = (pu - u, pv - v);
        let mut ju = Params::zeros();
        let mut jv = Params::zeros();
        for k in 0..FIT_PARAMETERS {
            let h = 1e-7 * params[k].abs().max(1e-3);
            let mut q = *params;
            q[k] += h;
            let (qu, qv) = project(&q, x, y);
            ju[k] = (qu - pu) / h;
            jv[k] = (qv - pv) / h;
        }
        jtj += ju * ju.transpose() + jv * jv.transpose();
        jtr += ju * ru + jv * rv;
    }
    (jtj, jtr)
}

/// The stereo rig of two fitted cameras and their extrinsics; mrptv's rig frame is the left
/// camera's. Also returns `left_from_rig_node`, which turns hl2ss's rig-node poses into
/// `world_from_rig = world_from_rig_node * rig_node_from_left`.
pub(crate) fn stereo_rig(
    left: &LensFit,
    left_calibration: &VlcCalibration,
    right: &LensFit,
    right_calibration: &VlcCalibration,
) -> Result<(StereoRig, Isometry3<f64>), Hl2ssError> {
    let left_from_node = left_calibration.camera_from_rig_node()?;
    let right_from_node = right_calibration.camera_from_rig_node()?;
    let right_from_left = right_from_node * left_from_node.inverse();
    let rig = StereoRig {
        width: VLC_WIDTH,
        height: VLC_HEIGHT,
        left: left.camera,
        right: right.camera,
        right_from_left,
    };
    // Through the file form: the same checks as any rig.json.
    let rig =
        StereoRig::from_file(&rig.to_file()).map_err(|e| Hl2ssError::Calibration(e.to_string()))?;
    Ok((rig, left_from_node))
}

/// Pairs left and right frames whose times (on the chosen [`clock::FrameClock`]) agree within a
/// tolerance. Frames that find no
/// partner (the other camera's frame was lost, or came too late) are counted and dropped.
#[derive(Debug)]
pub(crate) struct Pairer {
    tolerance_ticks: u64,
    clock: clock::FrameClock,
    left: std::collections::VecDeque<VlcFrame>,
    right: std::collections::VecDeque<VlcFrame>,
    pub(crate) unpaired_left: u64,
    pub(crate) unpaired_right: u64,
}

/// How long a frame waits for its partner when the other camera has sent nothing newer (its
/// stream stalled or lags), ticks: a second.
const PAIRING_PATIENCE_TICKS: u64 = 10_000_000;

impl Pairer {
    pub(crate) fn new(tolerance_ticks: u64, clock: clock::FrameClock) -> Self {
        Self {
            tolerance_ticks,
            clock,
            left: Default::default(),
            right: Default::default(),
            unpaired_left: 0,
            unpaired_right: 0,
        }
    }

    pub(crate) fn tolerance_ticks(&self) -> u64 {
        self.tolerance_ticks
    }

    /// A frame's time on the pairing clock, ticks.
    pub(crate) fn ticks(&self, frame: &VlcFrame) -> u64 {
        clock::frame_ticks(self.clock, frame.timestamp, frame.sensor_ticks)
    }

    pub(crate) fn push_left(&mut self, frame: VlcFrame) -> Option<(VlcFrame, VlcFrame)> {
        self.left.push_back(frame);
        self.pair()
    }

    pub(crate) fn push_right(&mut self, frame: VlcFrame) -> Option<(VlcFrame, VlcFrame)> {
        self.right.push_back(frame);
        self.pair()
    }

    fn pair(&mut self) -> Option<(VlcFrame, VlcFrame)> {
        loop {
            let (l, r) = (self.left.front()?, self.right.front()?);
            let (l, r) = (self.ticks(l), self.ticks(r));
            if l.abs_diff(r) <= self.tolerance_ticks {
                let (l, r) = (self.left.pop_front()?, self.right.pop_front()?);
                return Some((l, r));
            }
            // The older of the two fronts can no longer be paired: frames arrive in time order.
            if l < r {
                self.left.pop_front();
                self.unpaired_left += 1;
            } else {
                self.right.pop_front();
                self.unpaired_right += 1;
            }
        }
    }

    /// At the end of the streams: whatever waits for a partner never gets one.
    pub(crate) fn flush(&mut self) {
        self.unpaired_left += self.left.len() as u64;
        self.unpaired_right += self.right.len() as u64;
        self.left.clear();
        self.right.clear();
    }

    /// Frames a second older than the newest frame of either camera are given up on: one
    /// camera's stream has stalled. (A lagging stream's frames still pair when they come.)
    pub(crate) fn trim(&mut self) {
        let newest = [self.left.back(), self.right.back()]
            .into_iter()
            .flatten()
            .map(|f| self.ticks(f))
            .max()
            .unwrap_or(0);
        let oldest_kept = newest.saturating_sub(PAIRING_PATIENCE_TICKS);
        while self
            .left
            .front()
            .is_some_and(|f| self.ticks(f) < oldest_kept)
        {
            self.left.pop_front();
            self.unpaired_left += 1;
        }
        while self
            .right
            .front()
            .is_some_and(|f| self.ticks(f) < oldest_kept)
        {
            self.right.pop_front();
            self.unpaired_right += 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mrptv_engine::geometry::PixelPoint;
    use nalgebra::{Translation3, UnitQuaternion};

    fn at(timestamp: u64) -> VlcFrame {
        VlcFrame {
            timestamp,
            pixels: Vec::new(),
            sensor_ticks: 0,
            exposure: 0,
            gain: 0,
            pose: None,
        }
    }

    #[test]
    fn frames_pair_by_the_sensor_clock_whatever_their_host_stamps() {
        let frame = |host: u64, sensor_ns: u64| VlcFrame {
            sensor_ticks: sensor_ns,
            ..at(host)
        };
        // Host stamps 4 ms apart (beyond a 2 ms tolerance), one exposure on the sensor clock.
        let mut p = Pairer::new(20_000, clock::FrameClock::Sensor);
        assert!(p.push_left(frame(1_000_000, 5_000_000_000)).is_none());
        let (l, r) = p
            .push_right(frame(1_040_000, 5_000_000_000))
            .expect("a pair");
        assert_eq!((l.timestamp, r.timestamp), (1_000_000, 1_040_000));
        let mut p = Pairer::new(20_000, clock::FrameClock::Host);
        assert!(p.push_left(frame(1_000_000, 5_000_000_000)).is_none());
        assert!(p.push_right(frame(1_040_000, 5_000_000_000)).is_none());
    }

    #[test]
    fn frames_pair_by_timestamp_and_orphans_are_counted() {
        let mut p = Pairer::new(50_000, clock::FrameClock::Sensor);
        assert!(p.push_left(at(1_000_000)).is_none());
        let (l, r) = p.push_right(at(1_000_100)).expect("a pair");
        assert_eq!((l.timestamp, r.timestamp), (1_000_000, 1_000_100));
        // The right frame of 1.33 s was lost: the left one is dropped once a later right comes.
        assert!(p.push_left(at(1_333_333)).is_none());
        assert!(p.push_left(at(1_666_666)).is_none());
        let (l, r) = p.push_right(at(1_666_700)).expect("a pair");
        assert_eq!((l.timestamp, r.timestamp), (1_666_666, 1_666_700));
        assert_eq!((p.unpaired_left, p.unpaired_right), (1, 0));
        // Right runs ahead: a right frame without its left is dropped the same way.
        assert!(p.push_right(at(2_000_000)).is_none());
        assert!(p.push_right(at(2_333_333)).is_none());
        assert!(p.push_left(at(2_333_300)).is_some());
        assert_eq!((p.unpaired_left, p.unpaired_right), (1, 1));
        // The right stream stalls: left frames wait a second for it, then are given up on.
        for t in 0..40 {
            p.push_left(at(3_000_000 + t * 333_333));
        }
        p.trim();
        assert_eq!(
            p.unpaired_left,
            1 + 9,
            "frames older than a second before the newest"
        );
        // A lagging right stream still pairs with the frames kept.
        let (l, _) = p
            .push_right(at(3_000_000 + 9 * 333_333))
            .expect("late but paired");
        assert_eq!(l.timestamp, 3_000_000 + 9 * 333_333);
    }

    #[test]
    fn configurations_round_trip_and_match_hl2ss_bytes() {
        let raw = StreamConfig::raw_with_poses();
        let b = raw.encode();
        // hl2ss_lnm.rx_rm_vlc(mode=MODE_1, profile=RAW), v1.0.33 to v1.0.37: mode 1, divisor 1,
        // raw, default level, bitrate 640*480*30*12, three options: GOP size 1, then the
        // exposure factor 0.0 (a double's bits) and the constant -125000 (an int64's bits),
        // in that order (Python's dict keeps insertion order).
        let mut hl2ss = vec![1u8, 1, 0xFF, 0xFF];
        hl2ss.extend_from_slice(&110_592_000u32.to_le_bytes());
        hl2ss.push(3);
        for (key, value) in [
            (10u64, 1u64),
            (0xFFFF_FFFF_FFFF_FFFF, 0),
            (0xFFFF_FFFF_FFFF_FFFE, 0xFFFF_FFFF_FFFE_17B8),
        ] {
            hl2ss.extend_from_slice(&key.to_le_bytes());
            hl2ss.extend_from_slice(&value.to_le_bytes());
        }
        assert_eq!(b.len(), 57);
        assert_eq!(b, hl2ss);
        // The same client asked for H.264 (profile H264_BASE) at 2.5 Mbit/s: its default GOP of
        // 30 frames instead of 1, the rest alike.
        let h264 = StreamConfig::h264_with_poses(2_500_000).encode();
        let mut expected = hl2ss.clone();
        expected[2] = 0;
        expected[4..8].copy_from_slice(&2_500_000u32.to_le_bytes());
        expected[17..25].copy_from_slice(&30u64.to_le_bytes());
        assert_eq!(h264, expected);
        assert_eq!(StreamConfig::decode(&b), Ok(raw));
        assert_eq!(StreamConfig::calibration().encode(), vec![2]);
        assert!(StreamConfig::decode(&b[..20]).is_err());
        assert!(StreamConfig::decode(&[7]).is_err());
    }

    #[test]
    fn frames_round_trip_and_a_zero_pose_means_none() {
        let pose = Isometry3::from_parts(
            Translation3::new(0.1, 1.6, -0.3),
            UnitQuaternion::from_euler_angles(0.1, -0.4, 0.2),
        );
        let frame = VlcFrame {
            timestamp: 133_000_000_000,
            pixels: (0..VLC_PIXELS).map(|i| (i % 251) as u8).collect(),
            sensor_ticks: 42,
            exposure: 9000,
            gain: 3,
            pose: Some(row_vector_from_isometry(&pose)),
        };
        let wire = frame.encode();
        let mut head = [0u8; HEADER_BYTES];
        head.copy_from_slice(&wire[..HEADER_BYTES]);
        let (t, size) = decode_header(&head);
        assert_eq!(
            (t, size),
            (frame.timestamp, VLC_PIXELS + VLC_METADATA_BYTES)
        );
        let payload = &wire[HEADER_BYTES..HEADER_BYTES + size];
        let back = VlcFrame::decode(t, payload, Some(&wire[HEADER_BYTES + size..])).expect("frame");
        assert_eq!(back, frame);
        let world_from_node =
            isometry_from_row_vector("pose", &back.pose.expect("a pose")).expect("rigid");
        let d = (world_from_node.to_homogeneous() - pose.to_homogeneous())
            .abs()
            .max();
        assert!(d < 1e-6, "{d}");
        // Row-vector: the translation is in the last row of what is sent.
        let m = back.pose.expect("a pose");
        assert!((m[12] - 0.1).abs() < 1e-6 && (m[13] - 1.6).abs() < 1e-6);
        let lost = VlcFrame::decode(t, payload, Some(&[0u8; 64])).expect("frame");
        assert_eq!(lost.pose, None);
        assert!(VlcFrame::decode(t, &payload[1..], None).is_err());
        // hl2ss before v1.0.33 sends the bare image: told which version is needed.
        let e = VlcFrame::decode(t, &payload[..VLC_PIXELS], None).expect_err("refused");
        assert!(e.to_string().contains("v1.0.33 or later"), "{e}");
    }

    fn table(camera: &CameraModel) -> (Vec<f32>, Vec<f32>) {
        let c = VlcCalibration::from_camera(camera, &Isometry3::identity());
        (c.uv2x, c.uv2y)
    }

    #[test]
    fn a_lens_is_recovered_from_its_unprojection_table() {
        let rig = mrptv_engine::synth::hololens_raw_rig();
        for truth in [rig.left, rig.right] {
            let (x, y) = table(&truth);
            let fit = fit_lens(&x, &y, VLC_WIDTH, VLC_HEIGHT, 8).expect("fits");
            // float32 tables: a few thousandths of a pixel.
            assert!(fit.rms_px < 0.01 && fit.max_px < 0.05, "{fit:?}");
            assert!((fit.camera.fx - truth.fx).abs() < 0.05, "{fit:?}");
            assert!((fit.camera.cx - truth.cx).abs() < 0.05, "{fit:?}");
            // What matters: the fitted model maps pixels to the same rays.
            for (u, v) in [(5.0, 5.0), (320.0, 240.0), (630.0, 470.0), (10.0, 400.0)] {
                let p = PixelPoint { x: u, y: v };
                let (a, b) = truth.unproject(p).expect("truth");
                let (c, d) = fit.camera.unproject(p).expect("fit");
                assert!((a - c).abs() < 1e-4 && (b - d).abs() < 1e-4, "({u},{v})");
            }
        }
        // Pixels whose unprojection failed, left at (0, 0) by hl2ss (as at a real lens's
        // corners), are not fitted.
        let truth = rig.left;
        let (mut x, mut y) = table(&truth);
        for v in 0..VLC_HEIGHT as usize {
            for u in 0..VLC_WIDTH as usize {
                let corner = u.min(VLC_WIDTH as usize - 1 - u) + v.min(VLC_HEIGHT as usize - 1 - v);
                if corner < 40 || (u * 7 + v * 13) % 97 == 0 {
                    x[v * VLC_WIDTH as usize + u] = 0.0;
                    y[v * VLC_WIDTH as usize + u] = 0.0;
                }
            }
        }
        let fit = fit_lens(&x, &y, VLC_WIDTH, VLC_HEIGHT, 8).expect("fits");
        assert!(fit.rms_px < 0.01 && fit.max_px < 0.05, "{fit:?}");
        assert!((fit.camera.cx - truth.cx).abs() < 0.05, "{fit:?}");
        // An upside-down table is refused with a reason.
        let (x, y) = table(&rig.left);
        let flipped: Vec<f32> = y.iter().map(|v| -v).collect();
        let e = fit_lens(&x, &flipped, VLC_WIDTH, VLC_HEIGHT, 8).expect_err("refused");
        assert!(e.to_string().contains("y-down"), "{e}");
    }

    #[test]
    fn the_rig_comes_from_the_two_extrinsics_and_calibrations_round_trip() {
        let truth = mrptv_engine::synth::hololens_raw_rig();
        // The left camera somewhere on the rig node; the right one where the rig puts it.
        let left_from_node = Isometry3::from_parts(
            Translation3::new(-0.05, 0.02, 0.01),
            UnitQuaternion::from_euler_angles(0.0, 0.2, 1.5),
        );
        let right_from_node = truth.right_from_left * left_from_node;
        let calibration = VlcCalibration::from_camera;
        let left = calibration(&truth.left, &left_from_node);
        let right = calibration(&truth.right, &right_from_node);
        let left = VlcCalibration::decode(&left.encode()).expect("round trip");
        let right = VlcCalibration::decode(&right.encode()).expect("round trip");
        let fit = |c: &VlcCalibration| {
            fit_lens(&c.uv2x, &c.uv2y, VLC_WIDTH, VLC_HEIGHT, 16).expect("fit")
        };
        let (rig, node_to_left) =
            stereo_rig(&fit(&left), &left, &fit(&right), &right).expect("a rig");
        let d = (rig.right_from_left.to_homogeneous() - truth.right_from_left.to_homogeneous())
            .abs()
            .max();
        assert!(d < 1e-5, "{d}");
        let d = (node_to_left.to_homogeneous() - left_from_node.to_homogeneous())
            .abs()
            .max();
        assert!(d < 1e-6, "{d}");
        assert!(VlcCalibration::decode(&[0u8; 100]).is_err());
    }
}
