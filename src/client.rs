//! The reference headset client: `mrptv replay` streams a recording to a server, and
//! `mrptv serve --demo` streams an endless synthetic scene through the same code.
//!
//! Frames come from a [`FrameSource`] read on its own thread (PNG reading is blocking work);
//! a reader task timestamps every incoming message on arrival, so latency is measured from
//! "frame handed to the socket" to "causal batch off the socket".

use std::collections::HashMap;
use std::future::Future;
use std::io::Write;
use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant};

use futures_util::{SinkExt, StreamExt};
use nalgebra::Isometry3;
use tokio::sync::mpsc;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;
use tokio_tungstenite::tungstenite::http::header::{HeaderValue, AUTHORIZATION};
use tokio_tungstenite::tungstenite::Message;

use crate::protocol::{
    decode_batch, encode_frame, BatchKind, Convention, Counters, DecodedBatch, Encoding, ErrorCode,
    FrameMessage, HeadsetMessage, Hello, ImageFormat, ServerMessage, PROTOCOL_VERSION,
};
use crate::recording::{read_gray_png, Recording, RecordingError};
use crate::tables;
use mrptv_engine::geometry::StereoRig;
use mrptv_engine::synth::{ScenarioSpec, Synthesizer};
use mrptv_engine::PipelineConfig;

#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    #[error("cannot connect to {url}: {error}")]
    Connect {
        url: String,
        error: tokio_tungstenite::tungstenite::Error,
    },
    #[error("connection: {0}")]
    Socket(#[from] tokio_tungstenite::tungstenite::Error),
    #[error("the server refused the session ({code:?}): {message}")]
    Refused { code: ErrorCode, message: String },
    #[error("protocol: {0}")]
    Protocol(String),
    #[error(transparent)]
    Source(#[from] RecordingError),
    #[error("{0}")]
    Image(String),
}

/// One frame ready to send: images already in the session's encoding.
#[derive(Debug, Clone)]
pub struct SourceFrame {
    pub index: u64,
    pub t_s: f64,
    /// OpenCV convention (as in `frames.csv`).
    pub world_from_rig: Option<Isometry3<f64>>,
    pub left: Vec<u8>,
    pub right: Vec<u8>,
}

pub trait FrameSource: Send + 'static {
    fn rig(&self) -> &StereoRig;
    /// `None` at the end.
    fn next_frame(&mut self) -> Option<Result<SourceFrame, ClientError>>;
    /// The next frame's `t_s`, when known without producing it.
    fn peek_t_s(&self) -> Option<f64> {
        None
    }
    /// Passes over the next frame; `false` at the end. A live camera that has moved on does not
    /// encode what it no longer needs to send.
    fn skip_frame(&mut self) -> bool {
        self.next_frame().is_some()
    }
}

/// A recording directory, frame by frame. PNG files are sent as they are for `Encoding::Png`.
pub struct RecordingSource {
    recording: Recording,
    next: usize,
    encoding: Encoding,
}

impl RecordingSource {
    pub fn new(recording: Recording, encoding: Encoding) -> Self {
        Self {
            recording,
            next: 0,
            encoding,
        }
    }
}

impl FrameSource for RecordingSource {
    fn rig(&self) -> &StereoRig {
        &self.recording.rig
    }

    fn next_frame(&mut self) -> Option<Result<SourceFrame, ClientError>> {
        let entry = *self.recording.frames.get(self.next)?;
        self.next += 1;
        let (w, h) = (self.recording.rig.width, self.recording.rig.height);
        let read = |path: std::path::PathBuf| -> Result<Vec<u8>, ClientError> {
            match self.encoding {
                Encoding::Png => std::fs::read(&path).map_err(|error| {
                    ClientError::Source(RecordingError::Io {
                        path: path.clone(),
                        error,
                    })
                }),
                other => other
                    .encode_image(&read_gray_png(&path, w, h)?, w, h)
                    .map_err(ClientError::Image),
            }
        };
        Some((|| {
            Ok(SourceFrame {
                index: entry.index,
                t_s: entry.t_s,
                world_from_rig: entry.world_from_rig,
                left: read(self.recording.left_path(entry.index))?,
                right: read(self.recording.right_path(entry.index))?,
            })
        })())
    }

    fn peek_t_s(&self) -> Option<f64> {
        self.recording.frames.get(self.next).map(|e| e.t_s)
    }

    fn skip_frame(&mut self) -> bool {
        let more = self.next < self.recording.frames.len();
        self.next += usize::from(more);
        more
    }
}

/// A synthetic scenario rendered on the fly, lap after lap (each lap a fresh seed), with frame
/// indices and times carrying on across laps: an endless headset for `serve --demo`.
pub struct SyntheticSource {
    spec: ScenarioSpec,
    particles: usize,
    seed: u64,
    frames_per_lap: usize,
    laps: Option<u64>,
    encoding: Encoding,
    synth: Synthesizer,
    lap: u64,
    in_lap: usize,
}

impl SyntheticSource {
    /// `laps: None` never ends.
    pub fn new(spec: ScenarioSpec, seed: u64, laps: Option<u64>, encoding: Encoding) -> Self {
        let particles = spec.default_particles;
        let frames_per_lap = spec.default_frames.max(1);
        let synth = Synthesizer::new(spec.clone(), particles, seed);
        Self {
            spec,
            particles,
            seed,
            frames_per_lap,
            laps,
            encoding,
            synth,
            lap: 0,
            in_lap: 0,
        }
    }
}

impl FrameSource for SyntheticSource {
    fn rig(&self) -> &StereoRig {
        &self.spec.rig
    }

    fn next_frame(&mut self) -> Option<Result<SourceFrame, ClientError>> {
        if self.in_lap == self.frames_per_lap {
            self.lap += 1;
            if self.laps.is_some_and(|laps| self.lap >= laps) {
                return None;
            }
            self.in_lap = 0;
            self.synth = Synthesizer::new(
                self.spec.clone(),
                self.particles,
                self.seed.wrapping_add(self.lap),
            );
        }
        self.in_lap += 1;
        let f = self.synth.next_frame();
        let lap_frames = self.lap * self.frames_per_lap as u64;
        let encode = |pixels: Vec<u8>| match self.encoding {
            Encoding::Raw8 => Ok(pixels),
            other => other
                .encode_image(&pixels, self.spec.rig.width, self.spec.rig.height)
                .map_err(ClientError::Image),
        };
        Some((|| {
            Ok(SourceFrame {
                index: lap_frames + f.index,
                t_s: lap_frames as f64 * self.spec.frame_interval_s + f.t_s,
                world_from_rig: f.world_from_rig,
                left: encode(f.left)?,
                right: encode(f.right)?,
            })
        })())
    }
}

/// How fast frames are sent.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Rate {
    /// At the recording's own timestamps.
    Recorded,
    /// As fast as the server answers, with at most `max_in_flight` frames unanswered.
    Max,
    Hz(f64),
}

impl Rate {
    /// When a paced frame is due: `t_s` after the first frame's `t0`, or its `position` in the
    /// stream at `Hz`; at once with `Max`.
    fn due(self, started: Instant, t0: f64, t_s: f64, position: u64) -> Instant {
        match self {
            Rate::Recorded => started + Duration::from_secs_f64((t_s - t0).max(0.0)),
            Rate::Hz(hz) => started + Duration::from_secs_f64(position as f64 / hz),
            Rate::Max => started,
        }
    }
}

impl std::str::FromStr for Rate {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "recorded" => Ok(Rate::Recorded),
            "max" => Ok(Rate::Max),
            hz => match hz.parse::<f64>() {
                Ok(v) if v > 0.0 && v.is_finite() => Ok(Rate::Hz(v)),
                _ => Err(format!(
                    "{s:?}: expected \"recorded\", \"max\" or a frame rate in Hz"
                )),
            },
        }
    }
}

#[derive(Debug, Clone)]
pub struct ReplayOptions {
    /// `ws://HOST:PORT/v1/ingest`
    pub url: String,
    pub client_name: String,
    pub encoding: Encoding,
    pub convention: Convention,
    pub rate: Rate,
    /// Frames sent but not yet answered (by a causal batch, an error or a drop notice) at most,
    /// with `Rate::Max`.
    pub max_in_flight: usize,
    /// With a paced rate (a live source): frames unanswered at most. A frame due while the
    /// window is full waits, and is skipped once a newer frame is due: a live source sends its
    /// newest frame, so a link slower than the stream costs frames, never a growing backlog.
    pub live_window: usize,
    /// With a paced rate: once a frame has gone unanswered this long the link is backed up,
    /// and due frames wait (and are skipped for newer ones) until answers come.
    pub live_backlog: Duration,
    /// Pipeline parameters to ask for; the server's when `None`.
    pub config: Option<PipelineConfig>,
    /// Keep every batch received in the report (off for endless sources).
    pub keep_batches: bool,
    /// How long to wait for the server's bye after ours.
    pub finish_timeout: Duration,
    /// Trust for `wss://` URLs; `None`: the public web roots only.
    pub tls: Option<Arc<rustls::ClientConfig>>,
    /// The server's ingest secret, sent as `Authorization: Bearer`.
    pub secret: Option<String>,
}

impl ReplayOptions {
    pub fn new(url: impl Into<String>) -> Self {
        Self {
            url: url.into(),
            client_name: format!("mrptv-replay {}", env!("CARGO_PKG_VERSION")),
            encoding: Encoding::Raw8,
            convention: Convention::OpenCv,
            rate: Rate::Recorded,
            max_in_flight: 2,
            live_window: 8,
            live_backlog: Duration::from_millis(250),
            config: None,
            keep_batches: true,
            finish_timeout: Duration::from_secs(30),
            tls: None,
            secret: None,
        }
    }
}

/// What a replay saw.
#[derive(Debug, Clone, Default)]
pub struct ReplayReport {
    pub session: String,
    pub frames_sent: u64,
    pub causal_batches: u64,
    pub refined_batches: u64,
    pub causal_vectors: u64,
    pub refined_vectors: u64,
    /// Kept when `keep_batches`.
    pub causal: Vec<DecodedBatch>,
    pub refined: Vec<DecodedBatch>,
    /// Frame sent -> its causal batch received, seconds, in frame order.
    pub latencies_s: Vec<f64>,
    /// Frame due (captured, for a live source) -> its causal batch received, seconds, in frame
    /// order: how old the vectors are that the wearer sees, link and waiting included.
    pub ages_s: Vec<f64>,
    /// Frames a paced source skipped unsent: a newer one was due before they could go.
    pub frames_skipped: u64,
    /// The newest frame a causal batch answered.
    pub last_causal_frame: Option<u64>,
    pub errors: Vec<(ErrorCode, String)>,
    pub dropped_frames: Vec<u64>,
    /// From the server's bye (or its last status).
    pub counters: Option<Counters>,
    pub bye_reason: Option<String>,
    /// With a recording server: the last frame it said is on disk (`recorded`), and how many.
    pub recorded_through: Option<u64>,
    pub frames_recorded: u64,
    /// First frame sent to last message received, seconds.
    pub elapsed_s: f64,
}

impl ReplayReport {
    /// Nearest-rank percentile of the latencies, seconds.
    pub fn latency_percentile_s(&self, percent: f64) -> Option<f64> {
        let mut sorted = self.latencies_s.clone();
        sorted.sort_by(f64::total_cmp);
        let rank = ((percent / 100.0) * sorted.len() as f64).ceil() as usize;
        sorted.get(rank.clamp(1, sorted.len().max(1)) - 1).copied()
    }
}

/// Writes received vectors as `tracks.csv` rows (header included), in the session's convention.
pub fn write_batches_csv(out: &mut impl Write, batches: &[DecodedBatch]) -> std::io::Result<()> {
    writeln!(out, "{}", tables::TRACKS_HEADER)?;
    for b in batches {
        for v in &b.vectors {
            let [x, y, z] = v.position_m;
            let [u, vv, w] = v.velocity_m_per_s;
            writeln!(
                out,
                "{},{},{},{x},{y},{z},{u},{vv},{w}",
                b.frame_index, b.t_s, v.track_id
            )?;
        }
    }
    Ok(())
}

/// A frame and its position in the source's stream (skipped frames count).
type Positioned = (u64, SourceFrame);

/// Produces the source's frames ahead, on a thread. Once `started` is set, a paced source
/// behaves as a live camera: a frame already more than a frame interval late when its turn
/// comes is passed over unproduced (its successor is being captured), so a source slower than
/// its rate, or a sender held up by the link, loses frames rather than falling ever further
/// behind.
fn spawn_source(
    mut source: impl FrameSource,
    rate: Rate,
    started: Arc<OnceLock<Instant>>,
) -> mpsc::Receiver<Result<Positioned, ClientError>> {
    let (tx, rx) = mpsc::channel(2);
    std::thread::spawn(move || {
        let mut position = 0u64;
        let mut t0 = None;
        let mut interval_s = 1.0 / 30.0;
        let mut last_t_s: Option<f64> = None;
        loop {
            if let (Some(&started), Some(t0), Some(t_s)) = (started.get(), t0, source.peek_t_s()) {
                let late = rate != Rate::Max
                    && Instant::now()
                        > rate.due(started, t0, t_s, position)
                            + Duration::from_secs_f64(interval_s);
                if late && source.skip_frame() {
                    position += 1;
                    last_t_s = Some(t_s);
                    continue;
                }
            }
            let Some(frame) = source.next_frame() else {
                break;
            };
            let frame = frame.map(|f| {
                t0.get_or_insert(f.t_s);
                if let Some(last) = last_t_s.filter(|&last| f.t_s > last) {
                    interval_s = f.t_s - last;
                }
                last_t_s = Some(f.t_s);
                (position, f)
            });
            position += 1;
            let failed = frame.is_err();
            if tx.blocking_send(frame).is_err() || failed {
                break;
            }
        }
    });
    rx
}

/// A WebSocket upgrade request to `url`, with `Authorization: Bearer SECRET` when given (the
/// server's ingest or watch secret).
pub(crate) fn authorized_request(
    url: &str,
    secret: Option<&str>,
) -> Result<tokio_tungstenite::tungstenite::handshake::client::Request, ClientError> {
    let mut request = url
        .into_client_request()
        .map_err(|error| ClientError::Connect {
            url: url.to_string(),
            error,
        })?;
    if let Some(secret) = secret {
        let value = HeaderValue::from_str(&format!("Bearer {secret}"))
            .map_err(|_| ClientError::Protocol("the secret must be printable ASCII".into()))?;
        request.headers_mut().insert(AUTHORIZATION, value);
    }
    Ok(request)
}

/// The protocol error an HTTP refusal of the upgrade carries (a wrong secret: 401).
fn refusal(error: &tokio_tungstenite::tungstenite::Error) -> Option<ClientError> {
    let tokio_tungstenite::tungstenite::Error::Http(response) = error else {
        return None;
    };
    let body = response.body().as_deref()?;
    match serde_json::from_slice::<ServerMessage>(body).ok()? {
        ServerMessage::Error { code, message, .. } => Some(ClientError::Refused { code, message }),
        _ => None,
    }
}

type Socket =
    tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>>;

/// Streams `source` to the server at `options.url` until it ends or `stop` resolves, then says
/// bye and waits for the server's. `progress` gets the number of frames sent.
pub async fn replay(
    source: impl FrameSource,
    options: &ReplayOptions,
    stop: impl Future<Output = ()>,
    mut progress: impl FnMut(u64),
) -> Result<ReplayReport, ClientError> {
    let (socket, session) = open_session(source.rig(), options).await?;
    let mut link = Link::new(socket, session, options);
    let started_at = Arc::new(OnceLock::new());
    let mut frames = spawn_source(source, options.rate, Arc::clone(&started_at));
    let started = *started_at.get_or_init(Instant::now);
    let mut first_t_s = None;
    let mut next = frames.recv().await.transpose()?;
    let mut finished = false;
    tokio::pin!(stop);
    let paced = options.rate != Rate::Max;
    let window = if paced {
        options.live_window.max(1)
    } else {
        options.max_in_flight.max(1)
    };
    // A frame taken from the source ahead of its turn, to see whether it overtook the current.
    let mut ahead: Option<Positioned> = None;
    // The position the next frame would have if none were skipped.
    let mut expected_position = 0u64;
    while let Some((position, frame)) = next.take() {
        // The source passed over these, late.
        link.answers.report.frames_skipped += position.saturating_sub(expected_position);
        expected_position = position + 1;
        let t0 = *first_t_s.get_or_insert(frame.t_s);
        let due_of =
            |frame: &SourceFrame, position: u64| options.rate.due(started, t0, frame.t_s, position);
        let due = due_of(&frame, position);
        if paced && Instant::now() >= due {
            if ahead.is_none() {
                ahead = frames.try_recv().ok().transpose()?;
            }
            if ahead
                .as_ref()
                .is_some_and(|(at, newer)| Instant::now() >= due_of(newer, *at))
            {
                link.answers.report.frames_skipped += 1;
                next = ahead.take();
                continue;
            }
        }
        let open = link.answers.pending.len() < window && !(paced && link.backed_up());
        if open && Instant::now() >= due {
            if link.send(&frame, paced.then_some(due)).await? {
                finished = true;
                break;
            }
            progress(link.answers.report.frames_sent + link.answers.report.frames_skipped);
            next = match ahead.take() {
                Some(frame) => Some(frame),
                None => frames.recv().await.transpose()?,
            };
            continue;
        }
        next = Some((position, frame));
        expected_position = position;
        // Backed up, the wait ends with an answer, or when the next frame is due (to skip this
        // one for it).
        let wake = if open {
            due
        } else {
            let interval = Duration::from_secs_f64(1.0 / 30.0);
            due.max(Instant::now()) + interval
        };
        tokio::select! {
            event = link.events.recv() => match event {
                Some((at, m)) => {
                    if link.take(at, m)? {
                        finished = true;
                        break;
                    }
                }
                None => { finished = true; break; }
            },
            _ = tokio::time::sleep_until(wake.into()), if paced || open => {}
            _ = &mut stop => break,
        }
    }
    link.finish(finished, started).await
}

/// Connects, says hello with `rig` and waits for the welcome; the socket and the session's id.
async fn open_session(
    rig: &StereoRig,
    options: &ReplayOptions,
) -> Result<(Socket, String), ClientError> {
    // Frames are large and batches small: Nagle's algorithm would hold batches back ~40 ms.
    let connector = options
        .tls
        .clone()
        .map(tokio_tungstenite::Connector::Rustls);
    let request = authorized_request(&options.url, options.secret.as_deref())?;
    let (mut socket, _) =
        tokio_tungstenite::connect_async_tls_with_config(request, None, true, connector)
            .await
            .map_err(|error| {
                refusal(&error).unwrap_or(ClientError::Connect {
                    url: options.url.clone(),
                    error,
                })
            })?;
    let hello = HeadsetMessage::Hello(Box::new(Hello {
        protocol: PROTOCOL_VERSION,
        client: options.client_name.clone(),
        rig: rig.to_file(),
        image: ImageFormat {
            width: rig.width,
            height: rig.height,
            encoding: options.encoding,
        },
        convention: options.convention,
        config: options.config.clone(),
        uncertainty: false,
    }));
    let hello = serde_json::to_string(&hello).map_err(|e| ClientError::Protocol(e.to_string()))?;
    socket.send(Message::text(hello)).await?;
    // The welcome, or the reason there is none.
    loop {
        let message = tokio::time::timeout(Duration::from_secs(30), socket.next())
            .await
            .map_err(|_| ClientError::Protocol("no welcome within 30 s".into()))?;
        match message {
            Some(Ok(Message::Text(t))) => match serde_json::from_str::<ServerMessage>(t.as_str()) {
                Ok(ServerMessage::Welcome { session, .. }) => return Ok((socket, session)),
                Ok(ServerMessage::Error { code, message, .. }) => {
                    return Err(ClientError::Refused { code, message })
                }
                _ => {}
            },
            Some(Ok(_)) => {}
            Some(Err(e)) => return Err(e.into()),
            None => return Err(ClientError::Protocol("closed before the welcome".into())),
        }
    }
}

/// A welcomed session's link: frames out through `sink`; the server's messages in, stamped on
/// arrival by a reader task, and what they said so far.
struct Link<'a> {
    options: &'a ReplayOptions,
    sink: futures_util::stream::SplitSink<Socket, Message>,
    events: mpsc::Receiver<(Instant, Message)>,
    reader: tokio::task::JoinHandle<()>,
    answers: Answers,
    /// When the last server message arrived.
    last_event: Option<Instant>,
}

impl<'a> Link<'a> {
    fn new(socket: Socket, session: String, options: &'a ReplayOptions) -> Self {
        let (sink, mut stream) = socket.split();
        let (event_tx, events) = mpsc::channel::<(Instant, Message)>(4096);
        let reader = tokio::spawn(async move {
            while let Some(Ok(m)) = stream.next().await {
                if event_tx.send((Instant::now(), m)).await.is_err() {
                    break;
                }
            }
        });
        Self {
            options,
            sink,
            events,
            reader,
            answers: Answers {
                report: ReplayReport {
                    session,
                    ..Default::default()
                },
                pending: HashMap::new(),
                latencies: Vec::new(),
                keep_batches: options.keep_batches,
            },
            last_event: None,
        }
    }

    /// Takes one server message received at `at`; `true` once the session is over.
    fn take(&mut self, at: Instant, message: Message) -> Result<bool, ClientError> {
        self.last_event = Some(at);
        self.answers.take(at, message)
    }

    /// A live frame waits while the link is backed up: some frame has gone unanswered for
    /// `live_backlog` (big frames on a slow link: more would only queue in the socket).
    fn backed_up(&self) -> bool {
        self.answers
            .pending
            .values()
            .any(|(sent, _)| sent.elapsed() >= self.options.live_backlog)
    }

    /// Sends `frame`, due at `due` when paced (unpaced, a frame is due when it can go); `true`
    /// when the send failed because the server had already ended the session.
    async fn send(
        &mut self,
        frame: &SourceFrame,
        due: Option<Instant>,
    ) -> Result<bool, ClientError> {
        let options = self.options;
        let message = encode_frame(&FrameMessage {
            encoding: options.encoding,
            frame_index: frame.index,
            t_s: frame.t_s,
            world_from_rig: frame
                .world_from_rig
                .and_then(|p| options.convention.flip_pose(&p)),
            left: &frame.left,
            right: &frame.right,
        })
        .map_err(|e| ClientError::Protocol(e.message))?;
        let now = Instant::now();
        self.answers
            .pending
            .insert(frame.index, (now, due.unwrap_or(now)));
        if let Err(e) = self.sink.send(Message::binary(message)).await {
            // The server may have said bye (shutting down) while this frame was going out.
            let mut finished = false;
            while let Ok((at, m)) = self.events.try_recv() {
                if self.take(at, m)? {
                    finished = true;
                }
            }
            if finished {
                return Ok(true);
            }
            return Err(e.into());
        }
        self.answers.report.frames_sent += 1;
        Ok(false)
    }

    /// Unless the session is over already, says bye and takes what the server still sends
    /// until its bye; then closes and reports, its time counted from `started`.
    async fn finish(
        mut self,
        finished: bool,
        started: Instant,
    ) -> Result<ReplayReport, ClientError> {
        if !finished {
            self.sink.send(Message::text(r#"{"type":"bye"}"#)).await?;
            let finish_timeout = self.options.finish_timeout;
            let drain = async {
                while let Some((at, m)) = self.events.recv().await {
                    if self.take(at, m)? {
                        break;
                    }
                }
                Ok::<(), ClientError>(())
            };
            match tokio::time::timeout(finish_timeout, drain).await {
                Ok(r) => r?,
                Err(_) => tracing::warn!("no bye from the server within {finish_timeout:?}"),
            }
        }
        let _ = self.sink.close().await;
        self.reader.abort();
        let Answers {
            mut report,
            mut latencies,
            ..
        } = self.answers;
        latencies.sort_by_key(|(index, ..)| *index);
        report.ages_s = latencies.iter().map(|l| l.2).collect();
        report.latencies_s = latencies.into_iter().map(|l| l.1).collect();
        report.elapsed_s = (self.last_event.unwrap_or(started) - started).as_secs_f64();
        Ok(report)
    }
}

/// What the server has answered so far, and the frames it has yet to answer.
struct Answers {
    report: ReplayReport,
    /// Per unanswered frame: when it was sent, and when it was due.
    pending: HashMap<u64, (Instant, Instant)>,
    /// Per answered frame: its index, latency and age, seconds.
    latencies: Vec<(u64, f64, f64)>,
    keep_batches: bool,
}

impl Answers {
    /// Takes one server message received at `at`; `true` once the session is over (its bye,
    /// or a close).
    fn take(&mut self, at: Instant, message: Message) -> Result<bool, ClientError> {
        match message {
            Message::Binary(b) => self.take_batch(at, &b)?,
            Message::Text(t) => return Ok(self.take_text(t.as_str())),
            Message::Close(_) => return Ok(true),
            _ => {}
        }
        Ok(false)
    }

    fn take_batch(&mut self, at: Instant, bytes: &[u8]) -> Result<(), ClientError> {
        let batch = decode_batch(bytes).map_err(|e| ClientError::Protocol(e.message))?;
        let report = &mut self.report;
        match batch.kind {
            BatchKind::Causal => {
                if let Some((sent, due)) = self.pending.remove(&batch.frame_index) {
                    self.latencies.push((
                        batch.frame_index,
                        (at - sent).as_secs_f64(),
                        (at - due).as_secs_f64(),
                    ));
                }
                report.causal_batches += 1;
                report.last_causal_frame = report.last_causal_frame.max(Some(batch.frame_index));
                report.causal_vectors += batch.vectors.len() as u64;
                if self.keep_batches {
                    report.causal.push(batch);
                }
            }
            BatchKind::Refined => {
                report.refined_batches += 1;
                report.refined_vectors += batch.vectors.len() as u64;
                if self.keep_batches {
                    report.refined.push(batch);
                }
            }
        }
        Ok(())
    }

    /// `true` on the server's bye.
    fn take_text(&mut self, text: &str) -> bool {
        let report = &mut self.report;
        match serde_json::from_str::<ServerMessage>(text) {
            Ok(ServerMessage::Error {
                code,
                message,
                frame_index,
            }) => {
                if let Some(i) = frame_index {
                    self.pending.remove(&i);
                }
                tracing::warn!("server: {message}");
                report.errors.push((code, message));
            }
            Ok(ServerMessage::Dropped { frame_indices, .. }) => {
                for i in frame_indices {
                    self.pending.remove(&i);
                    report.dropped_frames.push(i);
                }
            }
            Ok(ServerMessage::Status { counters, .. }) => report.counters = Some(counters),
            Ok(ServerMessage::Recorded {
                through_frame_index,
                frames_recorded,
                ..
            }) => {
                report.recorded_through = Some(through_frame_index);
                report.frames_recorded = frames_recorded;
            }
            Ok(ServerMessage::Bye { reason, counters }) => {
                report.bye_reason = Some(reason);
                if counters.is_some() {
                    report.counters = counters;
                }
                return true;
            }
            Ok(_) => {}
            Err(e) => tracing::debug!("unreadable server message ignored: {e}"),
        }
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rates_parse_and_bad_ones_are_explained() {
        assert_eq!("max".parse::<Rate>(), Ok(Rate::Max));
        assert_eq!("recorded".parse::<Rate>(), Ok(Rate::Recorded));
        assert_eq!("30".parse::<Rate>(), Ok(Rate::Hz(30.0)));
        assert!("-1".parse::<Rate>().is_err());
        assert!("fast".parse::<Rate>().expect_err("refused").contains("max"));
    }

    #[test]
    fn percentiles_use_the_nearest_rank() {
        let report = ReplayReport {
            latencies_s: (1..=100).map(|i| i as f64).collect(),
            ..Default::default()
        };
        assert_eq!(report.latency_percentile_s(50.0), Some(50.0));
        assert_eq!(report.latency_percentile_s(99.0), Some(99.0));
        assert_eq!(report.latency_percentile_s(100.0), Some(100.0));
        assert_eq!(ReplayReport::default().latency_percentile_s(50.0), None);
    }

    #[test]
    fn synthetic_laps_keep_indices_and_times_increasing() {
        let spec = ScenarioSpec::new(mrptv_engine::synth::Scenario::Flume);
        let mut source = SyntheticSource {
            frames_per_lap: 3,
            ..SyntheticSource::new(spec, 1, Some(2), Encoding::Raw8)
        };
        let frames: Vec<SourceFrame> = std::iter::from_fn(|| source.next_frame())
            .collect::<Result<_, _>>()
            .expect("renders");
        assert_eq!(frames.len(), 6);
        assert!(frames
            .windows(2)
            .all(|w| w[1].index == w[0].index + 1 && w[1].t_s > w[0].t_s));
    }
}
