//! A headset connection (`/v1/ingest`) and its session: connection task, pipeline thread,
//! recorder thread.

use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::sync::mpsc as std_mpsc;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use axum::body::Bytes;
use axum::extract::ws::{CloseFrame, Message, WebSocket};
use futures_util::{SinkExt, StreamExt};
use nalgebra::Isometry3;
use tokio::sync::{mpsc, oneshot};

use super::queue::{DropOldestQueue, Pushed};
use super::{
    unix_ms, FieldOptions, Hub, HubEvent, Keepalive, PublishedBatch, PublishedField, SessionShared,
    SessionSlot,
};
use crate::offline::RunTotals;
use crate::protocol::{
    decode_frame, parse_text, Batch, BatchKind, Counters, Encoding, ErrorCode, HeadsetMessage,
    Hello, ProtocolError, ServerMessage, SessionDescription, HEADSET_TYPES, PROTOCOL_VERSION,
};
use crate::recording::{FrameEntry, RecordingWriter};
use crate::rerun_log::{FrameLog, RerunLogger, RerunSink};
use mrptv_engine::field::StreamField;
use mrptv_engine::geometry::StereoRig;
use mrptv_engine::{ImageView, Pipeline, PipelineConfig, PipelineError, StereoFrame};

/// A frame accepted from the socket, waiting for the pipeline.
struct QueuedFrame {
    index: u64,
    t_s: f64,
    /// OpenCV convention.
    world_from_rig: Option<Isometry3<f64>>,
    encoding: Encoding,
    left: Bytes,
    right: Bytes,
    received: Instant,
    /// The session's last index before this frame's, given back if the pipeline refuses it.
    index_before: Option<u64>,
}

/// The frame index a new frame's must exceed: that of the last frame accepted and not refused
/// (indices name recorded files). A refused frame leaves no trace, so it may be sent again,
/// corrected, with the same index, unless a later frame was accepted since.
#[derive(Debug, Default)]
struct FrameIndices(Mutex<Option<u64>>);

impl FrameIndices {
    fn last(&self) -> Option<u64> {
        *self.0.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Takes `index`; what was last before it.
    fn spend(&self, index: u64) -> Option<u64> {
        self.0
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .replace(index)
    }

    /// A frame the pipeline refused gives its index back, unless a later one was taken since.
    fn give_back(&self, index: u64, before: Option<u64>) {
        let mut last = self.0.lock().unwrap_or_else(|p| p.into_inner());
        if *last == Some(index) {
            *last = before;
        }
    }
}

/// The connection's live session.
struct Session {
    shared: Arc<SessionShared>,
    queue: Arc<DropOldestQueue<QueuedFrame>>,
    frame_indices: Arc<FrameIndices>,
    /// Resolves when the pipeline thread has drained the queue and closed the recording.
    worker_done: oneshot::Receiver<()>,
    /// Its place among `--max-sessions`, given back when the session ends.
    _slot: SessionSlot,
}

struct Connection {
    hub: Arc<Hub>,
    out: mpsc::Sender<Message>,
    session: Option<Session>,
    rate: FrameRateLimit,
}

/// A token bucket: `rate_hz` frames a second on average, bursts of up to a second's worth.
struct FrameRateLimit {
    rate_hz: f64,
    tokens: f64,
    last: Option<Instant>,
}

impl FrameRateLimit {
    fn new(rate_hz: f64) -> Self {
        Self {
            rate_hz,
            tokens: rate_hz.max(1.0),
            last: None,
        }
    }

    /// Takes one frame at `now`; `false` when over the limit.
    fn admit(&mut self, now: Instant) -> bool {
        if self.rate_hz.is_nan() || self.rate_hz <= 0.0 {
            return true;
        }
        let capacity = self.rate_hz.max(1.0);
        if let Some(last) = self.last {
            self.tokens = (self.tokens + (now - last).as_secs_f64() * self.rate_hz).min(capacity);
        }
        self.last = Some(now);
        if self.tokens >= 1.0 {
            self.tokens -= 1.0;
            true
        } else {
            false
        }
    }
}

/// Serves one headset until it says bye, disconnects, or the server shuts down.
pub(crate) async fn serve_headset(socket: WebSocket, hub: Arc<Hub>) {
    let _guard = hub.connection();
    let (mut sink, mut stream) = socket.split();
    let (out, mut outgoing) = mpsc::channel::<Message>(hub.options.headset_buffer.max(1));
    let send_timeout = hub.options.send_timeout;
    let writer = tokio::spawn(async move {
        while let Some(message) = outgoing.recv().await {
            let closing = matches!(message, Message::Close(_));
            match tokio::time::timeout(send_timeout, sink.send(message)).await {
                Ok(Ok(())) if !closing => {}
                Ok(_) => break,
                Err(_) => {
                    tracing::info!("headset not reading for {send_timeout:?}: disconnecting it");
                    return;
                }
            }
        }
        // Flushes a close frame: ours after a bye, or the one the WebSocket queued in answer
        // to the headset's own (RFC 6455 5.5.1), so the headset sees a clean close.
        let _ = tokio::time::timeout(send_timeout, sink.close()).await;
    });
    let mut shutdown = hub.shutdown.clone();
    let mut status = tokio::time::interval(hub.options.status_interval);
    status.tick().await;
    let mut keepalive = Keepalive::start(hub.options.idle_timeout).await;
    let mut hello_by = tokio::time::Instant::now() + hub.options.handshake_timeout;
    let mut conn = Connection {
        hub: Arc::clone(&hub),
        out,
        session: None,
        rate: FrameRateLimit::new(hub.options.max_frame_rate_hz),
    };
    if hub.shutting_down() {
        conn.finish(Some("server shutting down")).await;
    } else {
        loop {
            tokio::select! {
                message = stream.next() => {
                    keepalive.heard();
                    match message {
                        Some(Ok(Message::Text(text))) => {
                            if conn.on_text(text.as_str()).await {
                                break;
                            }
                            // A refused hello may be corrected: the time runs from the refusal.
                            if conn.session.is_none() {
                                hello_by = tokio::time::Instant::now() + hub.options.handshake_timeout;
                            }
                        }
                        Some(Ok(Message::Binary(bytes))) => conn.on_binary(bytes),
                        Some(Ok(Message::Ping(_) | Message::Pong(_))) => {}
                        Some(Ok(Message::Close(_))) | None => {
                            // Answered at once: nothing else can reach a headset that closed.
                            let _ = conn.out.try_send(Message::Close(None));
                            conn.finish(None).await;
                            break;
                        }
                        Some(Err(e)) => {
                            // Includes a message over --max-message-bytes: tell the headset why
                            // before the connection goes.
                            tracing::info!("headset connection failed: {e}");
                            conn.send(&ServerMessage::error(ErrorCode::BadFrame, format!("connection failed: {e}")));
                            conn.finish(None).await;
                            break;
                        }
                    }
                },
                _ = shutdown.changed() => {
                    conn.finish(Some("server shutting down")).await;
                    break;
                }
                _ = status.tick() => conn.send_status(),
                due = keepalive.ping_due() => {
                    if let Err(reason) = due {
                        tracing::info!("headset {reason}: disconnecting it");
                        conn.finish(Some(&reason)).await;
                        break;
                    }
                    // Answered by any WebSocket client library: a live but quiet headset
                    // (paused by its wearer) stays connected.
                    conn.send_raw(Message::Ping(Bytes::new()));
                }
                _ = tokio::time::sleep_until(hello_by), if conn.session.is_none() => {
                    let reason = format!("no hello within {} s", hub.options.handshake_timeout.as_secs_f64());
                    tracing::info!("headset sent {reason}: disconnecting it");
                    conn.finish(Some(&reason)).await;
                    break;
                }
            }
        }
    }
    drop(conn);
    // The writer ends once it has sent what is queued, or when its peer stops reading.
    let writer_abort = writer.abort_handle();
    if tokio::time::timeout(send_timeout, writer).await.is_err() {
        writer_abort.abort();
    }
}

impl Connection {
    fn send(&self, message: &ServerMessage) {
        self.send_raw(Message::Text(message.to_json().into()));
    }

    fn send_raw(&self, message: Message) {
        if self.out.try_send(message).is_err() {
            if let Some(s) = &self.session {
                s.shared.counters().batches_dropped += 1;
            }
        }
    }

    fn reject(&self, error: ProtocolError) {
        tracing::debug!(code = ?error.code, "refused: {}", error.message);
        self.send(&error.to_message());
    }

    /// Refuses a binary message; in a session, every one counts as a rejected frame.
    fn reject_frame(&self, error: ProtocolError) {
        if let Some(s) = &self.session {
            s.shared.counters().frames_rejected += 1;
        }
        self.reject(error);
    }

    /// Handles a text message; `true` ends the connection.
    async fn on_text(&mut self, text: &str) -> bool {
        match parse_text::<HeadsetMessage>(text, HEADSET_TYPES) {
            Err(e) => self.reject(e),
            Ok(HeadsetMessage::Bye {}) => {
                self.finish(Some("client said bye")).await;
                return true;
            }
            Ok(HeadsetMessage::Hello(hello)) => {
                if let Some(s) = &self.session {
                    let message = format!(
                        "session {} is already started on this connection; reconnect to start another",
                        s.shared.id()
                    );
                    self.reject(ProtocolError::new(ErrorCode::AlreadyStarted, message));
                } else if let Err(e) = self.start(*hello).await {
                    self.reject(e);
                }
            }
        }
        false
    }

    async fn start(&mut self, hello: Hello) -> Result<(), ProtocolError> {
        let (slot, rig, pipeline) = self.admit(&hello)?;
        let number = self.hub.next_session_number();
        let id = format!("s{number}");
        let started_unix_ms = unix_ms();
        let queue = Arc::new(DropOldestQueue::<QueuedFrame>::new(
            self.hub.options.queue_frames,
        ));
        let shared = Arc::new(SessionShared {
            number,
            description: SessionDescription {
                id: id.clone(),
                client: hello.client.clone(),
                width: rig.width,
                height: rig.height,
                encoding: hello.image.encoding,
                convention: hello.convention,
                started_unix_ms,
            },
            counters: Default::default(),
            viewers: Default::default(),
            reset_field: Default::default(),
            close_queue: {
                let queue = Arc::clone(&queue);
                Box::new(move || queue.close())
            },
        });
        let recorder = match &self.hub.options.record_dir {
            Some(dir) => {
                let dir = dir.join(format!("{id}-{started_unix_ms}"));
                let config = pipeline.config().clone();
                Some(
                    self.start_recorder(dir, rig.clone(), config, &shared)
                        .await?,
                )
            }
            None => None,
        };
        let welcome = ServerMessage::Welcome {
            protocol: PROTOCOL_VERSION,
            server: format!("mrptv {}", env!("CARGO_PKG_VERSION")),
            session: id.clone(),
            session_number: number,
            convention: hello.convention,
            config: Box::new(pipeline.config().clone()),
            queue_frames: self.hub.options.queue_frames.max(1),
            refined_delay_frames: pipeline.config().velocity.half_window_frames,
        };
        let rerun = self.start_rerun(&id, started_unix_ms, &rig);
        let frame_indices = Arc::new(FrameIndices::default());
        let worker = Worker {
            frame_indices: Arc::clone(&frame_indices),
            shared: Arc::clone(&shared),
            pipeline,
            out: self.out.clone(),
            events: self.hub.events.clone(),
            recorder,
            queue: Arc::clone(&queue),
            totals: RunTotals::default(),
            rerun,
            frames_processed: 0,
            uncertainty: hello.uncertainty,
            field: LiveField::new(&self.hub.options.field),
        };
        let worker_done = self.spawn_worker(&id, worker)?;
        tracing::info!(session = %id, client = %hello.client, width = rig.width, height = rig.height,
            encoding = ?hello.image.encoding, convention = ?hello.convention, "session started");
        self.send(&welcome);
        self.hub.add_session(Arc::clone(&shared));
        self.session = Some(Session {
            shared,
            queue,
            frame_indices,
            worker_done,
            _slot: slot,
        });
        Ok(())
    }

    /// Whether the server takes the session `hello` asks for: not shutting down, images within
    /// the limit, a place among `--max-sessions`, a rig and config the pipeline accepts.
    fn admit(&self, hello: &Hello) -> Result<(SessionSlot, StereoRig, Pipeline), ProtocolError> {
        if self.hub.shutting_down() {
            return Err(ProtocolError::new(
                ErrorCode::ShuttingDown,
                "the server is shutting down",
            ));
        }
        let max_side = self.hub.options.max_image_side;
        if hello.image.width > max_side || hello.image.height > max_side {
            return Err(ProtocolError::new(
                ErrorCode::LimitReached,
                format!(
                    "image is {}x{}: this server takes images up to {max_side} pixels a side (--max-image-size)",
                    hello.image.width, hello.image.height
                ),
            ));
        }
        let Some(slot) = self.hub.reserve_session() else {
            let max = self.hub.options.max_sessions;
            return Err(ProtocolError::new(
                ErrorCode::LimitReached,
                format!("{max} sessions are live, the most this server takes (--max-sessions); try again later"),
            ));
        };
        let rig = StereoRig::from_file(&hello.rig)
            .map_err(|e| ProtocolError::new(ErrorCode::BadCalibration, format!("rig: {e}")))?;
        if (hello.image.width, hello.image.height) != (rig.width, rig.height) {
            return Err(ProtocolError::new(
                ErrorCode::BadHello,
                format!(
                    "image is {}x{} but rig.image_size is {}x{}",
                    hello.image.width, hello.image.height, rig.width, rig.height
                ),
            ));
        }
        let config = hello
            .config
            .clone()
            .unwrap_or_else(|| self.hub.options.config.clone());
        let pipeline = Pipeline::new(rig.clone(), config).map_err(|e| match e {
            PipelineError::Calibration(e) => {
                ProtocolError::new(ErrorCode::BadCalibration, format!("rig: {e}"))
            }
            other => ProtocolError::new(ErrorCode::BadConfig, other.to_string()),
        })?;
        Ok((slot, rig, pipeline))
    }

    /// The session's recorder, writing under `dir`.
    async fn start_recorder(
        &self,
        dir: PathBuf,
        rig: StereoRig,
        config: PipelineConfig,
        shared: &Arc<SessionShared>,
    ) -> Result<Recorder, ProtocolError> {
        let ack = self.durable_ack(shared);
        // Creating and syncing files blocks: off the network threads.
        tokio::task::spawn_blocking(move || Recorder::start(dir, &rig, &config, ack))
            .await
            .map_err(|e| {
                ProtocolError::new(
                    ErrorCode::Internal,
                    format!("cannot start the recorder: {e}"),
                )
            })?
    }

    /// Runs the session's pipeline on its own thread; resolves when it has drained the queue
    /// and closed the recording.
    fn spawn_worker(
        &self,
        id: &str,
        worker: Worker,
    ) -> Result<oneshot::Receiver<()>, ProtocolError> {
        let (done_tx, worker_done) = oneshot::channel();
        let guard = self.hub.worker();
        std::thread::Builder::new()
            .name(format!("pipeline-{id}"))
            .spawn(move || {
                worker.run();
                let _ = done_tx.send(());
                drop(guard);
            })
            .map_err(|e| {
                ProtocolError::new(
                    ErrorCode::Internal,
                    format!("cannot start a pipeline thread: {e}"),
                )
            })?;
        Ok(worker_done)
    }

    /// Tells the headset, from the recorder thread, which frames are safely on disk. Each
    /// `recorded` covers every frame before it, so one lost to a full send buffer is made good by
    /// the next; the final count is in the session's counters too.
    fn durable_ack(&self, shared: &Arc<SessionShared>) -> Box<dyn Fn(u64, u64) + Send> {
        let out = self.out.clone();
        let shared = Arc::clone(shared);
        Box::new(move |through_frame_index, frames_recorded| {
            shared.counters().frames_recorded = frames_recorded;
            let message = ServerMessage::Recorded {
                session: shared.id().to_string(),
                through_frame_index,
                frames_recorded,
            };
            let _ = out.try_send(Message::Text(message.to_json().into()));
        })
    }

    /// The session's Rerun logger, if asked for. A sink that cannot be opened is reported to the
    /// headset and the log; the session goes on without it.
    fn start_rerun(&self, id: &str, started_unix_ms: u64, rig: &StereoRig) -> Option<RerunLogger> {
        let options = self.hub.options.rerun.as_ref()?;
        let sinks: Vec<RerunSink> = options
            .sinks
            .iter()
            .map(|sink| match sink {
                RerunSink::File(dir) => {
                    RerunSink::File(dir.join(format!("{id}-{started_unix_ms}.rrd")))
                }
                other => other.clone(),
            })
            .collect();
        for sink in &sinks {
            if let RerunSink::File(path) = sink {
                if let Some(dir) = path.parent() {
                    let _ = std::fs::create_dir_all(dir);
                }
            }
        }
        // `Serve` sinks were turned into connections to one proxy when the server started.
        match RerunLogger::start(id, &sinks, rig, options) {
            Ok(logger) => Some(logger),
            Err(e) => {
                tracing::error!(session = %id, "{e}");
                self.send(&ServerMessage::error(
                    ErrorCode::Internal,
                    format!("{e}; the session goes on without Rerun logging"),
                ));
                None
            }
        }
    }

    fn on_binary(&mut self, bytes: Bytes) {
        let Some(session) = &self.session else {
            self.reject(ProtocolError::new(
                ErrorCode::NotReady,
                "frame before hello: send a hello and wait for the welcome first",
            ));
            return;
        };
        let frame = match decode_frame(&bytes) {
            Ok(f) => f,
            Err(e) => return self.reject_frame(e),
        };
        let shared = &session.shared;
        let index = frame.frame_index;
        let at_frame = |code, message: String| {
            let mut e = ProtocolError::new(code, message);
            e.frame_index = Some(index);
            e
        };
        if let Some(last) = session.frame_indices.last().filter(|&last| index <= last) {
            let message =
                format!("frame {index}: frame_index must increase (the previous frame was {last})");
            return self.reject_frame(at_frame(ErrorCode::BadFrame, message));
        }
        if !self.rate.admit(Instant::now()) {
            let message = format!(
                "frame {index}: more than {} frames/s (--max-frame-rate); frame refused",
                self.hub.options.max_frame_rate_hz
            );
            return self.reject_frame(at_frame(ErrorCode::RateLimited, message));
        }
        if frame.encoding != shared.description.encoding {
            let message = format!(
                "frame {index}: images are {:?} but the hello declared {:?}",
                frame.encoding, shared.description.encoding
            );
            return self.reject_frame(at_frame(ErrorCode::BadFrame, message));
        }
        if frame.encoding == Encoding::Raw8 {
            let expected = shared.description.width as usize * shared.description.height as usize;
            for (camera, image) in [("left", frame.left), ("right", frame.right)] {
                if image.len() != expected {
                    let message = format!(
                        "frame {index}: {camera} image has {} bytes, a {}x{} raw8 image has {expected}",
                        image.len(),
                        shared.description.width,
                        shared.description.height
                    );
                    return self.reject_frame(at_frame(ErrorCode::BadImage, message));
                }
            }
        }
        let world_from_rig = match frame.world_from_rig {
            Some(pose) => match shared.description.convention.flip_pose(&pose) {
                Some(p) => Some(p),
                None => {
                    let message = format!("frame {index}: world_from_rig is not rigid");
                    return self.reject_frame(at_frame(ErrorCode::BadFrame, message));
                }
            },
            None => None,
        };
        let queued = QueuedFrame {
            index,
            t_s: frame.t_s,
            world_from_rig,
            encoding: frame.encoding,
            left: bytes.slice_ref(frame.left),
            right: bytes.slice_ref(frame.right),
            received: Instant::now(),
            index_before: session.frame_indices.spend(index),
        };
        shared.counters().frames_received += 1;
        match session.queue.push(queued) {
            Pushed::Queued => {}
            Pushed::DroppedOldest(old) => {
                let total = {
                    let mut c = shared.counters();
                    c.frames_dropped += 1;
                    c.frames_dropped
                };
                tracing::debug!(session = %shared.id(), frame = old.index, "queue full: dropped the oldest frame");
                self.send(&ServerMessage::Dropped {
                    session: shared.id().to_string(),
                    frame_indices: vec![old.index],
                    frames_dropped: total,
                });
            }
            Pushed::Closed(_) => {
                let message = format!("frame {index}: the session is closing");
                self.reject_frame(at_frame(ErrorCode::ShuttingDown, message));
            }
        }
    }

    fn send_status(&self) {
        let Some(session) = &self.session else {
            return;
        };
        let shared = &session.shared;
        let counters = {
            let mut c = shared.counters();
            c.queue_depth = session.queue.len();
            *c
        };
        self.send(&ServerMessage::Status {
            session: shared.id().to_string(),
            counters,
        });
        let _ = self.hub.events.send(HubEvent::Status {
            session_number: shared.number,
            id: shared.id().to_string(),
            counters,
        });
    }

    /// Ends the session: the pipeline drains what is queued (its batches still go out), the
    /// recording is completed, then a bye (when `reason` is given: the headset is still there)
    /// and a close frame.
    async fn finish(&mut self, reason: Option<&str>) {
        let counters = match self.session.take() {
            Some(session) => {
                session.queue.close();
                let _ = session.worker_done.await;
                let counters = *session.shared.counters();
                self.hub.remove_session(session.shared.number);
                tracing::info!(session = %session.shared.id(), reason = reason.unwrap_or("disconnected"),
                    received = counters.frames_received, processed = counters.frames_processed,
                    dropped = counters.frames_dropped, rejected = counters.frames_rejected, "session ended");
                Some(counters)
            }
            None => None,
        };
        let Some(reason) = reason else {
            return;
        };
        let bye = ServerMessage::Bye {
            reason: reason.to_string(),
            counters,
        };
        // The bye must arrive after every batch: wait for room rather than drop it, but never
        // for long (a headset that stopped reading must not hold up shutdown).
        let deliver = async {
            self.out
                .send(Message::Text(bye.to_json().into()))
                .await
                .ok()?;
            self.out
                .send(Message::Close(Some(CloseFrame {
                    code: 1000,
                    reason: reason.to_string().into(),
                })))
                .await
                .ok()
        };
        let _ = tokio::time::timeout(Duration::from_secs(2), deliver).await;
    }
}

/// The session's pipeline thread.
struct Worker {
    shared: Arc<SessionShared>,
    pipeline: Pipeline,
    out: mpsc::Sender<Message>,
    events: tokio::sync::broadcast::Sender<HubEvent>,
    recorder: Option<Recorder>,
    queue: Arc<DropOldestQueue<QueuedFrame>>,
    frame_indices: Arc<FrameIndices>,
    /// Over the session: its health figures and mean processing time.
    totals: RunTotals,
    rerun: Option<RerunLogger>,
    frames_processed: u64,
    /// The headset asked for batches with velocity errors.
    uncertainty: bool,
    field: LiveField,
}

/// A session's mean-flow field: its refined vectors binned as they come, published to its
/// viewers at most once per `FieldOptions::interval`.
struct LiveField {
    stream: StreamField,
    interval: Duration,
    max_cells: usize,
    last_published: Option<Instant>,
}

impl LiveField {
    fn new(options: &FieldOptions) -> Self {
        Self {
            // The options were checked when the server started.
            stream: StreamField::new(options.cell_m, options.window_s).unwrap_or_default(),
            interval: options.interval,
            max_cells: options.max_cells,
            last_published: None,
        }
    }

    /// The field to publish now, if it is time (and there is a grid).
    fn due(&mut self, shared: &SessionShared, frame: (u64, f64)) -> Option<PublishedField> {
        let grid = self.stream.grid()?;
        if self
            .last_published
            .is_some_and(|at| at.elapsed() < self.interval)
        {
            return None;
        }
        self.last_published = Some(Instant::now());
        Some(PublishedField::new(
            shared.number,
            shared.id().to_string(),
            frame,
            grid,
            self.max_cells,
        ))
    }
}

impl Worker {
    fn run(mut self) {
        while let Some(frame) = self.queue.pop() {
            self.process(frame);
        }
        if let Some(recorder) = self.recorder.take() {
            if let Err(e) = recorder.finish() {
                self.send_error(ProtocolError::new(ErrorCode::Internal, e));
            }
        }
        if let Some(logger) = self.rerun.take() {
            let summary = logger.finish();
            tracing::info!(session = %self.shared.id(), logged = summary.frames_logged,
                dropped = summary.frames_dropped, errors = summary.errors, "rerun log closed");
        }
    }

    /// `false` when the headset's buffer was full and the message was dropped.
    fn send(&self, message: Message) -> bool {
        let sent = self.out.try_send(message).is_ok();
        if !sent {
            self.shared.counters().batches_dropped += 1;
        }
        sent
    }

    fn send_error(&self, error: ProtocolError) {
        self.send(Message::Text(error.to_message().to_json().into()));
    }

    /// Sends a batch to the headset; the number of vectors delivered.
    fn send_batch(&self, batch: &PublishedBatch) -> u64 {
        let bytes = batch.encoded(self.shared.description.convention, self.uncertainty);
        if self.send(Message::Binary(bytes)) {
            batch.batch.vectors.len() as u64
        } else {
            0
        }
    }

    fn reject(&self, frame: &QueuedFrame, error: ProtocolError) {
        self.frame_indices
            .give_back(frame.index, frame.index_before);
        self.shared.counters().frames_rejected += 1;
        tracing::debug!(session = %self.shared.id(), "frame refused: {}", error.message);
        self.send_error(error);
    }

    /// The frame's left and right pixels. Raw pixels stay in the message's buffer: no copy on
    /// the way to the pipeline or the recorder.
    fn decode_images(&self, frame: &QueuedFrame) -> Result<(Bytes, Bytes), ProtocolError> {
        let (w, h) = (
            self.shared.description.width,
            self.shared.description.height,
        );
        let decode = |camera: &str, bytes: &Bytes| -> Result<Bytes, ProtocolError> {
            match frame.encoding {
                Encoding::Raw8 => Ok(bytes.clone()),
                other => other
                    .decode_image(bytes, w, h)
                    .map(Bytes::from)
                    .map_err(|m| {
                        frame_error(
                            frame.index,
                            ErrorCode::BadImage,
                            format!("frame {}: {camera} image: {m}", frame.index),
                        )
                    }),
            }
        };
        decode("left", &frame.left).and_then(|l| Ok((l, decode("right", &frame.right)?)))
    }

    fn process(&mut self, frame: QueuedFrame) {
        let started = Instant::now();
        let (w, h) = (
            self.shared.description.width,
            self.shared.description.height,
        );
        let (left, right) = match self.decode_images(&frame) {
            Ok(images) => images,
            Err(e) => return self.reject(&frame, e),
        };
        let stereo = StereoFrame {
            index: frame.index,
            t_s: frame.t_s,
            world_from_rig: frame.world_from_rig,
            left: image_view(w, h, &left),
            right: image_view(w, h, &right),
        };
        let output = match self.pipeline.push(&stereo) {
            Ok(o) => o,
            Err(e) => {
                let code = match e {
                    PipelineError::Timestamp { .. } => ErrorCode::BadTimestamp,
                    PipelineError::ImageSize { .. } => ErrorCode::BadImage,
                    _ => ErrorCode::Internal,
                };
                let error = frame_error(frame.index, code, e.to_string());
                return self.reject(&frame, error);
            }
        };
        let processing_s = started.elapsed().as_secs_f64();
        self.totals.add(&output.stats, processing_s);
        let processing_us = (processing_s * 1e6).min(u32::MAX as f64) as u32;
        let rerun_log = self.rerun.as_ref().map(|logger| {
            let mut log = FrameLog::from_output(&output, frame.world_from_rig);
            log.processing_ms = processing_s * 1e3;
            if logger.wants_images(self.frames_processed) {
                log.images = Some((left.to_vec().into(), right.to_vec().into()));
            }
            log
        });
        let age_us = (frame.received.elapsed().as_secs_f64() * 1e6).min(u32::MAX as f64) as u32;
        let causal = PublishedBatch::new(Batch {
            kind: BatchKind::Causal,
            session_number: self.shared.number,
            frame_index: output.frame_index,
            t_s: output.t_s,
            world: frame.world_from_rig.is_some(),
            processing_us,
            age_us,
            vectors: output.causal_vectors,
        });
        let mut sent = self.send_batch(&causal);
        if self.shared.reset_field.swap(false, Ordering::Relaxed) {
            self.field.stream.reset();
        }
        self.field.stream.add_vectors(&output.vectors);
        let field = output
            .centred_frame
            .and_then(|centre| self.field.due(&self.shared, (centre.index, centre.t_s)));
        let refined = output.centred_frame.map(|centre| {
            PublishedBatch::new(Batch {
                kind: BatchKind::Refined,
                session_number: self.shared.number,
                frame_index: centre.index,
                t_s: centre.t_s,
                world: centre.posed,
                processing_us,
                age_us,
                vectors: output.vectors,
            })
        });
        if let Some(r) = &refined {
            sent += self.send_batch(r);
        }
        let latency_ms = frame.received.elapsed().as_secs_f64() * 1e3;
        if let (Some(logger), Some(mut log)) = (&self.rerun, rerun_log) {
            log.latency_ms = Some(latency_ms);
            logger.log(log);
        }
        self.frames_processed += 1;
        let _ = self.events.send(HubEvent::Batch(Arc::new(causal)));
        if let Some(r) = refined {
            let _ = self.events.send(HubEvent::Batch(Arc::new(r)));
        }
        if let Some(field) = field {
            self.publish_field(field);
        }
        self.count_processed(processing_s, sent);
        tracing::trace!(session = %self.shared.id(), frame = frame.index, vectors = sent,
            processing_ms = processing_s * 1e3, "frame processed");
        self.record(&frame, left, right);
    }

    /// The session's mean-flow field to its viewers and its Rerun log.
    fn publish_field(&self, field: PublishedField) {
        if let Some(logger) = &self.rerun {
            let head = &field.head;
            logger.log_field(head.frame_index, head.t_s, field.cells.clone(), false);
        }
        let _ = self.events.send(HubEvent::Field(Arc::new(field)));
    }

    /// A frame processed in `processing_s` and `sent` vectors, in the session's counters.
    fn count_processed(&self, processing_s: f64, sent: u64) {
        let mut c: std::sync::MutexGuard<'_, Counters> = self.shared.counters();
        c.frames_processed += 1;
        c.vectors_sent += sent;
        c.processing_ms_last = processing_s * 1e3;
        c.processing_ms_mean = self.totals.pipeline_s * 1e3 / c.frames_processed as f64;
        c.queue_depth = self.queue.len();
        let health = self.totals.figures();
        c.detections_per_image = health.detections_per_image;
        c.linked_fraction = health.linked_fraction;
        c.matched_fraction = health.matched_fraction;
        c.velocity_fraction = health.velocity_fraction;
        c.stereo_candidates_per_particle = health.stereo_candidates_per_particle;
    }

    /// Hands the frame to the recorder; a recorder that fails is stopped and the headset told.
    fn record(&mut self, frame: &QueuedFrame, left: Bytes, right: Bytes) {
        if let Some(recorder) = &mut self.recorder {
            let entry = FrameEntry {
                index: frame.index,
                t_s: frame.t_s,
                world_from_rig: frame.world_from_rig,
            };
            if let Err(e) = recorder.write(entry, left, right) {
                self.recorder = None;
                tracing::error!(session = %self.shared.id(), "recording stopped: {e}");
                self.send_error(ProtocolError::new(
                    ErrorCode::Internal,
                    format!("recording stopped: {e}"),
                ));
            }
        }
    }
}

/// The error `code` with `message`, about frame `index`.
fn frame_error(index: u64, code: ErrorCode, message: String) -> ProtocolError {
    let mut e = ProtocolError::new(code, message);
    e.frame_index = Some(index);
    e
}

fn image_view(width: u32, height: u32, pixels: &[u8]) -> ImageView<'_> {
    ImageView {
        width: width as usize,
        height: height as usize,
        pixels,
    }
}

type RecordedFrame = (FrameEntry, Bytes, Bytes);

/// Writes a session's processed frames on its own thread (PNG encoding is slower than the
/// pipeline). The channel is bounded: a recorder that cannot keep up slows the pipeline, whose
/// queue then drops frames *before* they are processed, so the recording always holds exactly
/// the frames the session processed.
struct Recorder {
    dir: PathBuf,
    frames: Option<std_mpsc::SyncSender<RecordedFrame>>,
    thread: Option<std::thread::JoinHandle<Result<usize, String>>>,
}

impl Recorder {
    /// Creates the recording, with the session's config as its `mrptv.toml` so that
    /// `mrptv process` on it uses the parameters the session used.
    fn start(
        dir: PathBuf,
        rig: &StereoRig,
        config: &PipelineConfig,
        on_durable: Box<dyn Fn(u64, u64) + Send>,
    ) -> Result<Self, ProtocolError> {
        let cannot = |e: String| {
            ProtocolError::new(
                ErrorCode::Internal,
                format!("cannot record to {}: {e}", dir.display()),
            )
        };
        if dir.exists() {
            return Err(cannot("it already exists".into()));
        }
        let mut writer = RecordingWriter::create(&dir, rig, true)
            .and_then(RecordingWriter::into_durable)
            .map_err(|e| cannot(e.to_string()))?;
        let toml = dir.join("mrptv.toml");
        std::fs::write(&toml, crate::config::to_toml(config))
            .and_then(|()| std::fs::File::open(&toml)?.sync_all())
            .and_then(|()| std::fs::File::open(&dir)?.sync_all())
            .map_err(|e| cannot(e.to_string()))?;
        let (tx, rx) = std_mpsc::sync_channel::<RecordedFrame>(8);
        let thread = std::thread::Builder::new()
            .name("recorder".into())
            .spawn(move || {
                let mut written = 0;
                // Whatever has piled up is written, then synced once: at 30 Hz that is one
                // frame, when the disk is slow it is several.
                while let Ok(first) = rx.recv() {
                    let mut last = first.0.index;
                    let mut frames = vec![first];
                    frames.extend(rx.try_iter().take(15));
                    for (entry, left, right) in &frames {
                        writer
                            .write_frame(entry, left, right)
                            .map_err(|e| e.to_string())?;
                        last = entry.index;
                    }
                    writer.sync().map_err(|e| e.to_string())?;
                    written += frames.len();
                    on_durable(last, written as u64);
                }
                Ok(written)
            })
            .map_err(|e| cannot(e.to_string()))?;
        tracing::info!(dir = %dir.display(), "recording");
        Ok(Self {
            dir,
            frames: Some(tx),
            thread: Some(thread),
        })
    }

    fn write(&mut self, entry: FrameEntry, left: Bytes, right: Bytes) -> Result<(), String> {
        let sent = self
            .frames
            .as_ref()
            .is_some_and(|tx| tx.send((entry, left, right)).is_ok());
        if sent {
            Ok(())
        } else {
            // The thread ended early: its error says why.
            self.join()
        }
    }

    fn join(&mut self) -> Result<(), String> {
        self.frames = None;
        match self.thread.take().map(|t| t.join()) {
            Some(Ok(Ok(written))) => {
                tracing::info!(dir = %self.dir.display(), frames = written, "recording complete");
                Ok(())
            }
            Some(Ok(Err(e))) => Err(e),
            Some(Err(_)) => Err("the recorder thread panicked".into()),
            None => Err("the recorder has stopped".into()),
        }
    }

    /// Flushes every frame handed over and closes the recording.
    fn finish(mut self) -> Result<(), String> {
        self.join()
    }
}
