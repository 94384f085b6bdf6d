//! `mrptv hl2ss`: a HoloLens 2 running the hl2ss app as a headset of `mrptv serve`. Fetches both
//! front cameras' calibrations, fits the `rig.json` lens model to them, then reads both raw
//! streams with poses, pairs frames by the sensor clock ([`crate::hl2ss::clock`]) and hands them to the reference client
//! ([`crate::client::replay`]), which streams them to the server like any WebSocket headset.
//! Formats: [`crate::hl2ss`].

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream, ToSocketAddrs};
use std::sync::mpsc as std_mpsc;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use nalgebra::Isometry3;
use serde::Serialize;

use crate::client::{ClientError, FrameSource, SourceFrame};
use crate::hl2ss::clock::{FrameClock, PoseHistory, SensorToHost};
use crate::hl2ss::{
    decode_header, fit_lens, isometry_from_row_vector, stereo_rig, LensFit, Pairer, StreamConfig,
    VlcCalibration, VlcCodec, VlcFrame, CALIBRATION_FLOATS, HEADER_BYTES, POSE_BYTES,
    TICKS_PER_SECOND, VLC_HEIGHT, VLC_WIDTH,
};
use crate::video::H264Decoder;
use mrptv_engine::geometry::StereoRig;

#[derive(Debug, thiserror::Error)]
pub enum BridgeError {
    #[error("{camera} camera at {addr}: {error}")]
    Io {
        camera: &'static str,
        addr: String,
        error: std::io::Error,
    },
    #[error("{camera} camera: {error}")]
    Format {
        camera: &'static str,
        error: crate::hl2ss::Hl2ssError,
    },
    #[error("{0}")]
    Rig(crate::hl2ss::Hl2ssError),
    /// The camera's stream closed (the app stopped) or went silent.
    #[error("{camera} camera's stream ended: {why}")]
    Ended { camera: &'static str, why: String },
}

/// A camera that sends nothing for this long is taken as gone (hl2ss streams at 30 Hz).
const STREAM_SILENCE: Duration = Duration::from_secs(10);

/// Where the two cameras stream from.
#[derive(Debug, Clone)]
pub struct Hl2ssEndpoints {
    pub host: String,
    pub left_port: u16,
    pub right_port: u16,
    pub connect_timeout: Duration,
}

impl Hl2ssEndpoints {
    fn addr(&self, camera: &'static str, port: u16) -> Result<SocketAddr, BridgeError> {
        let name = format!("{}:{port}", self.host);
        name.to_socket_addrs()
            .map_err(|error| BridgeError::Io {
                camera,
                addr: name.clone(),
                error,
            })?
            .next()
            .ok_or_else(|| BridgeError::Io {
                camera,
                addr: name.clone(),
                error: std::io::Error::new(std::io::ErrorKind::NotFound, "no address"),
            })
    }

    fn connect(&self, camera: &'static str, port: u16) -> Result<TcpStream, BridgeError> {
        let addr = self.addr(camera, port)?;
        let io = |error| BridgeError::Io {
            camera,
            addr: addr.to_string(),
            error,
        };
        let stream = TcpStream::connect_timeout(&addr, self.connect_timeout).map_err(io)?;
        stream.set_nodelay(true).map_err(io)?;
        Ok(stream)
    }
}

/// The rig hl2ss's calibration gives, and how well the lens model fits it.
#[derive(Debug, Clone)]
pub struct BridgeRig {
    pub(crate) rig: StereoRig,
    /// hl2ss poses are of the rig node: `world_from_rig = world_from_node * node_from_left`.
    pub(crate) node_from_left: Isometry3<f64>,
    pub left_fit: LensFit,
    pub right_fit: LensFit,
}

fn fetch_calibration(
    endpoints: &Hl2ssEndpoints,
    camera: &'static str,
    port: u16,
) -> Result<VlcCalibration, BridgeError> {
    let mut stream = endpoints.connect(camera, port)?;
    let io = |error| BridgeError::Io {
        camera,
        addr: format!("{}:{port}", endpoints.host),
        error,
    };
    // The table is 4.9 MB: generous, but not endless.
    stream
        .set_read_timeout(Some(Duration::from_secs(60)))
        .map_err(io)?;
    stream
        .write_all(&StreamConfig::calibration().encode())
        .map_err(io)?;
    let mut bytes = vec![0u8; 4 * CALIBRATION_FLOATS];
    stream.read_exact(&mut bytes).map_err(io)?;
    VlcCalibration::decode(&bytes).map_err(|error| BridgeError::Format { camera, error })
}

/// Fetches both calibrations and fits the lens model (every `fit_step`-th pixel each way).
pub fn calibrate(endpoints: &Hl2ssEndpoints, fit_step: usize) -> Result<BridgeRig, BridgeError> {
    let left = fetch_calibration(endpoints, "left", endpoints.left_port)?;
    let right = fetch_calibration(endpoints, "right", endpoints.right_port)?;
    let fit = |camera: &'static str, c: &VlcCalibration| {
        fit_lens(&c.uv2x, &c.uv2y, VLC_WIDTH, VLC_HEIGHT, fit_step)
            .map_err(|error| BridgeError::Format { camera, error })
    };
    let (left_fit, right_fit) = (fit("left", &left)?, fit("right", &right)?);
    let (rig, left_from_node) =
        stereo_rig(&left_fit, &left, &right_fit, &right).map_err(BridgeError::Rig)?;
    Ok(BridgeRig {
        rig,
        node_from_left: left_from_node.inverse(),
        left_fit,
        right_fit,
    })
}

/// What the bridge saw of the streams.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct BridgeCounters {
    pub left_frames: u64,
    pub right_frames: u64,
    pub pairs: u64,
    pub unpaired_left: u64,
    pub unpaired_right: u64,
    /// Pairs dropped because hl2ss had no pose for them (tracking lost): their vectors would be
    /// in no frame at all.
    pub unposed: u64,
    /// Pairs dropped unsent because more than 4 were waiting (the server was behind: a live
    /// source does not queue up old frames), or because their time did not move forward.
    pub(crate) stale: u64,
}

#[derive(Clone, Copy)]
enum Side {
    Left = 0,
    Right = 1,
}

/// Reads one camera's frames with poses until the stream ends, decoding H.264 ones.
fn read_stream(
    mut stream: TcpStream,
    camera: &'static str,
    codec: VlcCodec,
    side: fn(VlcFrame) -> (Side, VlcFrame),
    frames: std_mpsc::SyncSender<Result<(Side, VlcFrame), BridgeError>>,
) {
    let format = |error| BridgeError::Format { camera, error };
    let ended = |error: std::io::Error| BridgeError::Ended {
        camera,
        why: match error.kind() {
            std::io::ErrorKind::UnexpectedEof => "closed by the HoloLens".to_string(),
            std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut => {
                format!("nothing received for {} s", STREAM_SILENCE.as_secs())
            }
            _ => error.to_string(),
        },
    };
    let video = |error: crate::video::VideoError| {
        format(crate::hl2ss::Hl2ssError::Frame(error.to_string()))
    };
    let mut decoder = match codec {
        VlcCodec::Raw | VlcCodec::Hevc => None,
        VlcCodec::H264 => match H264Decoder::new(VLC_WIDTH, VLC_HEIGHT) {
            Ok(d) => Some(d),
            Err(e) => {
                let _ = frames.send(Err(video(e)));
                return;
            }
        },
    };
    loop {
        let mut head = [0u8; HEADER_BYTES];
        if let Err(e) = stream.read_exact(&mut head) {
            let _ = frames.send(Err(ended(e)));
            return;
        }
        let (timestamp, size) = decode_header(&head);
        let frame = if size > 4 * crate::hl2ss::VLC_PIXELS {
            Err(format(crate::hl2ss::Hl2ssError::Frame(format!(
                "payload of {size} bytes announced: not a raw visible-light frame"
            ))))
        } else {
            let mut payload = vec![0u8; size + POSE_BYTES];
            match stream.read_exact(&mut payload) {
                Err(e) => Err(ended(e)),
                Ok(()) => {
                    let (payload, pose) = payload.split_at(size);
                    match &mut decoder {
                        None => VlcFrame::decode(timestamp, payload, Some(pose)),
                        Some(decoder) => VlcFrame::decode_with(timestamp, payload, Some(pose), |unit| {
                            decoder
                                .decode(unit)
                                .map_err(|e| crate::hl2ss::Hl2ssError::Frame(e.to_string()))?
                                .ok_or_else(|| {
                                    crate::hl2ss::Hl2ssError::Frame(
                                        "an H.264 frame gave no picture: the stream must start with an IDR frame".into(),
                                    )
                                })
                        }),
                    }
                    .map(side)
                    .map_err(format)
                }
            }
        };
        let failed = frame.is_err();
        if frames.send(frame).is_err() || failed {
            return;
        }
    }
}

impl Hl2ssSource {
    fn sync_unpaired(&self) {
        let (l, r) = (self.pairer.unpaired_left, self.pairer.unpaired_right);
        self.count(|c| {
            c.unpaired_left = l;
            c.unpaired_right = r;
        });
    }

    /// Both streams are over, or one is and the other has nothing left that could pair.
    fn end(&mut self) {
        self.finished = true;
        self.pairer.flush();
        self.sync_unpaired();
    }

    /// One message of a reader thread: a frame is paired if it can be.
    fn take(&mut self, received: Result<(Side, VlcFrame), BridgeError>) -> Result<(), ClientError> {
        let (side, frame) = match received {
            Ok(f) => f,
            Err(BridgeError::Ended { camera, why }) => {
                tracing::warn!("{camera} camera's stream ended: {why}");
                self.ended[usize::from(camera == "right")] = true;
                if self.ended == [true, true] {
                    self.end();
                }
                return Ok(());
            }
            Err(e) => return Err(ClientError::Protocol(e.to_string())),
        };
        let other = 1 - side as usize;
        let ticks = self.pairer.ticks(&frame);
        // One camera alone makes no stereo pair.
        if self.ended[other]
            && ticks > self.last_timestamp[other].saturating_add(self.pairer.tolerance_ticks())
        {
            self.end();
            return Ok(());
        }
        self.last_timestamp[side as usize] = ticks;
        let pair = match side {
            Side::Left => {
                self.count(|c| c.left_frames += 1);
                self.pairer.push_left(frame)
            }
            Side::Right => {
                self.count(|c| c.right_frames += 1);
                self.pairer.push_right(frame)
            }
        };
        self.pairer.trim();
        self.sync_unpaired();
        if let Some(pair) = pair {
            self.count(|c| c.pairs += 1);
            self.ready.push_back(pair);
        }
        Ok(())
    }
}

/// Paired frames of a live hl2ss, as a headset source.
pub struct Hl2ssSource {
    rig: BridgeRig,
    frames: std_mpsc::Receiver<Result<(Side, VlcFrame), BridgeError>>,
    pairer: Pairer,
    clock: FrameClock,
    sensor_to_host: SensorToHost,
    poses: PoseHistory,
    first_timestamp: Option<u64>,
    last_t_s: f64,
    next_index: u64,
    counters: Arc<Mutex<BridgeCounters>>,
    /// Per side (left, right): its stream has ended; its newest time on the pairing clock.
    ended: [bool; 2],
    last_timestamp: [u64; 2],
    finished: bool,
    /// Pairs made and not yet sent.
    ready: std::collections::VecDeque<(VlcFrame, VlcFrame)>,
}

/// Pairs waiting to be sent, at most: 4 frame intervals (133 ms at 30 Hz). A live source keeps
/// up with the room rather than queueing seconds of old frames when the server falls behind.
const MAX_BACKLOG_PAIRS: usize = 4;

impl Hl2ssSource {
    /// Opens both streams with poses, raw or H.264 at `bitrate` bits a second a camera; frames
    /// are paired and timed on `clock`.
    pub fn open(
        endpoints: &Hl2ssEndpoints,
        rig: BridgeRig,
        pair_tolerance: Duration,
        clock: FrameClock,
        codec: VlcCodec,
        bitrate: u32,
    ) -> Result<Self, BridgeError> {
        let config = match codec {
            VlcCodec::Raw => StreamConfig::raw_with_poses(),
            VlcCodec::H264 => StreamConfig::h264_with_poses(bitrate),
            VlcCodec::Hevc => {
                return Err(BridgeError::Rig(crate::hl2ss::Hl2ssError::Configuration(
                    "hevc: this build decodes H.264 only (OpenH264); ask for --codec h264 (or raw)"
                        .into(),
                )))
            }
        };
        let (tx, frames) = std_mpsc::sync_channel(8);
        for (camera, port, side) in [
            (
                "left",
                endpoints.left_port,
                (|f| (Side::Left, f)) as fn(VlcFrame) -> (Side, VlcFrame),
            ),
            ("right", endpoints.right_port, |f| (Side::Right, f)),
        ] {
            let io = |error| BridgeError::Io {
                camera,
                addr: format!("{}:{port}", endpoints.host),
                error,
            };
            let mut stream = endpoints.connect(camera, port)?;
            let _ = stream.set_read_timeout(Some(STREAM_SILENCE));
            stream.write_all(&config.encode()).map_err(io)?;
            let tx = tx.clone();
            std::thread::Builder::new()
                .name(format!("hl2ss-{camera}"))
                .spawn(move || read_stream(stream, camera, codec, side, tx))
                .map_err(io)?;
        }
        Ok(Self {
            rig,
            frames,
            pairer: Pairer::new(
                (pair_tolerance.as_secs_f64() * TICKS_PER_SECOND) as u64,
                clock,
            ),
            clock,
            sensor_to_host: SensorToHost::default(),
            poses: PoseHistory::default(),
            first_timestamp: None,
            last_t_s: f64::NEG_INFINITY,
            next_index: 0,
            counters: Default::default(),
            ended: [false; 2],
            last_timestamp: [0; 2],
            finished: false,
            ready: Default::default(),
        })
    }

    /// Live counters, readable while the source runs on the client's reader thread.
    pub fn counters(&self) -> Arc<Mutex<BridgeCounters>> {
        Arc::clone(&self.counters)
    }

    fn count(&self, f: impl FnOnce(&mut BridgeCounters)) {
        f(&mut self.counters.lock().unwrap_or_else(|p| p.into_inner()));
    }

    /// The rig node's pose when the left camera's exposure was: the left frame's own pose on the
    /// host clock; on the sensor clock, the pose at the exposure's fitted host time, between the
    /// poses the frames brought. `None` when the left frame has no pose (tracking lost).
    fn node_pose(&mut self, left: &VlcFrame, right: &VlcFrame) -> Option<Isometry3<f64>> {
        let pose = |f: &VlcFrame| {
            f.pose
                .and_then(|m| isometry_from_row_vector("pose", &m).ok())
        };
        let own = pose(left)?;
        if self.clock == FrameClock::Host || left.sensor_ticks == 0 {
            return Some(own);
        }
        self.poses.push(left.timestamp, own);
        if let Some(p) = pose(right) {
            self.poses.push(right.timestamp, p);
        }
        let exposure = self.pairer.ticks(left);
        self.sensor_to_host.observe(exposure, left.timestamp);
        let at = self.sensor_to_host.host_at(exposure)?;
        self.poses.at(at).or(Some(own))
    }

    /// A pair as a stereo frame; `None` (counted) when it has no usable pose or time.
    fn convert(&mut self, left: VlcFrame, right: VlcFrame) -> Option<SourceFrame> {
        let Some(world_from_node) = self.node_pose(&left, &right) else {
            self.count(|c| c.unposed += 1);
            return None;
        };
        let ticks = self.pairer.ticks(&left);
        let first = *self.first_timestamp.get_or_insert(ticks);
        let t_s = ticks.saturating_sub(first) as f64 / TICKS_PER_SECOND;
        if t_s <= self.last_t_s {
            self.count(|c| c.stale += 1);
            return None;
        }
        self.last_t_s = t_s;
        let index = self.next_index;
        self.next_index += 1;
        Some(SourceFrame {
            index,
            t_s,
            world_from_rig: Some(
                opencv_from_hl2ss_world() * world_from_node * self.rig.node_from_left,
            ),
            left: left.pixels,
            right: right.pixels,
        })
    }
}

/// hl2ss's world is right-handed with y up and z toward the viewer: WebXR's axes. Sessions of
/// the bridge say `"webxr"`, so the server (which works in OpenCV's axes, y down) is handed the
/// world turned by this half turn about x, and every viewer, in whatever convention it asks
/// for, sees the room the right way up.
pub fn opencv_from_hl2ss_world() -> Isometry3<f64> {
    // Exactly diag(1, -1, -1): a unit quaternion with w = 0, x = 1.
    Isometry3::from_parts(
        nalgebra::Translation3::identity(),
        nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(0.0, 1.0, 0.0, 0.0)),
    )
}

impl FrameSource for Hl2ssSource {
    fn rig(&self) -> &StereoRig {
        &self.rig.rig
    }

    fn next_frame(&mut self) -> Option<Result<SourceFrame, ClientError>> {
        loop {
            // Everything that has arrived is paired; only when nothing is ready does it wait.
            while !self.finished {
                let received = if self.ready.is_empty() {
                    match self.frames.recv() {
                        Ok(r) => r,
                        Err(_) => {
                            self.end();
                            break;
                        }
                    }
                } else {
                    match self.frames.try_recv() {
                        Ok(r) => r,
                        Err(_) => break,
                    }
                };
                if let Err(e) = self.take(received) {
                    return Some(Err(e));
                }
            }
            // Behind by more than the backlog: the oldest pairs are skipped, not queued.
            while self.ready.len() > MAX_BACKLOG_PAIRS {
                self.ready.pop_front();
                self.count(|c| c.stale += 1);
            }
            let (left, right) = self.ready.pop_front()?;
            if let Some(frame) = self.convert(left, right) {
                return Some(Ok(frame));
            }
        }
    }
}
