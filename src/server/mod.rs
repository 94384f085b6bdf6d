//! `mrptv serve`: the live host service (protocol: `protocol/README.md`).
//!
//! ## Layout
//! - [`run`] takes a bound listener, options and a shutdown future (tests bind port 0).
//! - `ingest`: one task per headset WebSocket reads messages, validates them and hands frames to
//!   the session's pipeline thread through a `queue::DropOldestQueue` (bounded: the oldest frame
//!   is dropped and reported when the pipeline falls behind). The pipeline thread runs
//!   [`mrptv_engine::Pipeline`], sends the headset its vector batches first, then publishes them to
//!   viewers and hands the frame to the session's recorder thread.
//! - `watch`: one task per viewer WebSocket; all sessions publish to one `broadcast` channel, so a
//!   slow viewer lags (loses the oldest messages) and never holds up a pipeline or other viewers.
//! - Shutdown: the future resolves, every connection is told through a `watch` channel, each
//!   session drains its queue, completes its recording and says bye; viewers get the last
//!   batches, then their bye. `run` waits for the connections (`drain_timeout`; a peer that stopped
//!   reading is dropped) and, with no time limit, for every pipeline thread: no frame the server
//!   took goes unprocessed or unrecorded.
//!
//! Threads: the tokio runtime runs the network tasks; each session's pipeline and recorder run
//! on their own OS threads, so CPU-bound work never stalls the sockets.

pub mod access;
mod guard;
mod ingest;
mod queue;
mod tls_listener;
mod watch;
mod web;

use std::collections::BTreeMap;
use std::future::Future;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, OnceLock};
use std::time::Duration;

use axum::body::Bytes;
use axum::extract::{Query, State, WebSocketUpgrade};
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::serve::ListenerExt;
use axum::{Json, Router};
use serde::{Deserialize, Serialize};
use tokio::sync::{broadcast, watch as watch_channel, Notify};

use crate::protocol::{
    Batch, Convention, Counters, ErrorCode, FieldMessage, ServerMessage, SessionDescription,
    SessionInfo, PROTOCOL_VERSION,
};
use crate::rerun_log::RerunOptions;
use mrptv_engine::field::{CellSummary, FieldGrid};
use mrptv_engine::PipelineConfig;

/// Everything `mrptv serve` can be told; `Default` gives the documented defaults.
#[derive(Debug, Clone)]
pub struct ServerOptions {
    /// Pipeline parameters for sessions whose hello brings none.
    pub config: PipelineConfig,
    /// Frames a session holds before dropping the oldest.
    pub queue_frames: usize,
    /// Messages buffered for a headset that is slow to read before batches are dropped.
    pub headset_buffer: usize,
    /// Events buffered per viewer before the oldest are skipped.
    pub viewer_buffer: usize,
    /// Record every session's frames under this directory (`DIR/<session>-<unix ms>/`).
    pub record_dir: Option<PathBuf>,
    /// Log every session to Rerun; a `File` sink names a directory that receives
    /// `<session>-<unix ms>.rrd` per session.
    pub rerun: Option<RerunOptions>,
    pub status_interval: Duration,
    /// Largest WebSocket message accepted, bytes.
    pub max_message_bytes: usize,
    /// A peer that takes longer than this to accept one message is disconnected.
    pub send_timeout: Duration,
    /// How long shutdown waits for connections to close. Sessions' frames are processed and
    /// their recordings completed whatever this is.
    pub drain_timeout: Duration,
    /// Serve HTTPS/WSS only (`mrptv serve --tls`); plain HTTP/WS when `None`.
    pub tls: Option<Arc<rustls::ServerConfig>>,
    /// Secrets for headsets and viewers; open to all by default.
    pub access: access::AccessControl,
    /// A client must finish its TLS handshake, then its HTTP request head, and a headset must
    /// send its `hello`, each within this.
    pub handshake_timeout: Duration,
    /// A connection silent this long (no byte, no WebSocket pong) is closed. Peers are pinged
    /// every third of it.
    pub idle_timeout: Duration,
    /// Connections open at once (HTTP and WebSocket); more are closed on accept.
    pub max_connections: usize,
    /// Live sessions at once; a further `hello` is refused (`limit_reached`).
    pub max_sessions: usize,
    /// Viewers subscribed to one session (subscribers to every session count for each).
    pub max_viewers_per_session: usize,
    /// Largest image width or height a `hello` may declare, pixels.
    pub max_image_side: u32,
    /// Frames per second a session takes, averaged over a second (a burst of one second's worth
    /// passes); faster frames are refused (`rate_limited`). 0: no limit.
    pub max_frame_rate_hz: f64,
    /// Each session's mean-flow field.
    pub field: FieldOptions,
}

/// How a live session bins its vectors into a mean-flow field (`field` messages to viewers).
#[derive(Debug, Clone, PartialEq)]
pub struct FieldOptions {
    /// Cell side, metres; `None`: sized from the session's first vectors (`field::default_cell_m`).
    pub cell_m: Option<f64>,
    /// Forget samples older than this, seconds of sensor time; `None`: keep the whole session.
    pub window_s: Option<f64>,
    /// At most one `field` message per session this often.
    pub interval: Duration,
    /// The most cells a `field` message carries (the best-sampled).
    pub max_cells: usize,
}

impl Default for FieldOptions {
    fn default() -> Self {
        Self {
            cell_m: None,
            window_s: None,
            interval: Duration::from_secs(1),
            max_cells: 4096,
        }
    }
}

impl Default for ServerOptions {
    fn default() -> Self {
        Self {
            config: PipelineConfig::default(),
            queue_frames: 4,
            headset_buffer: 256,
            viewer_buffer: 1024,
            record_dir: None,
            rerun: None,
            status_interval: Duration::from_secs(1),
            max_message_bytes: 64 << 20,
            send_timeout: Duration::from_secs(10),
            drain_timeout: Duration::from_secs(10),
            tls: None,
            access: Default::default(),
            handshake_timeout: Duration::from_secs(10),
            idle_timeout: Duration::from_secs(30),
            max_connections: 256,
            max_sessions: 16,
            max_viewers_per_session: 64,
            max_image_side: 4096,
            max_frame_rate_hz: 120.0,
            field: FieldOptions::default(),
        }
    }
}

/// A batch on its way to viewers, encoded at most once per convention however many watch.
#[derive(Debug)]
pub(crate) struct PublishedBatch {
    pub(crate) batch: Batch,
    /// Per convention, without and with the velocity errors.
    encoded: [[OnceLock<Bytes>; 2]; 3],
}

impl PublishedBatch {
    pub(crate) fn new(batch: Batch) -> Self {
        Self {
            batch,
            encoded: Default::default(),
        }
    }

    pub(crate) fn encoded(&self, convention: Convention, uncertainty: bool) -> Bytes {
        self.encoded[usize::from(convention.code())][usize::from(uncertainty)]
            .get_or_init(|| self.batch.encode_with(convention, uncertainty).into())
            .clone()
    }
}

/// A session's mean-flow field, published to its viewers; encoded per convention on demand.
#[derive(Debug)]
pub(crate) struct PublishedField {
    pub(crate) session_number: u32,
    /// The message in OpenCV axes without its rows: each convention's is made from it.
    pub(crate) head: FieldMessage,
    /// World frame, OpenCV axes.
    pub(crate) cells: Vec<CellSummary>,
    encoded: [OnceLock<String>; 3],
}

impl PublishedField {
    pub(crate) fn new(
        session_number: u32,
        session: String,
        frame: (u64, f64),
        grid: &FieldGrid,
        max_cells: usize,
    ) -> Self {
        let mut cells: Vec<CellSummary> = grid.cells().collect();
        let truncated = cells.len() > max_cells;
        if truncated {
            // The best-sampled cells, sent in index order.
            cells.sort_by(|a, b| b.samples.cmp(&a.samples).then(a.index.cmp(&b.index)));
            cells.truncate(max_cells);
            cells.sort_by_key(|c| c.index);
        }
        Self {
            session_number,
            head: FieldMessage::new(session, frame, grid, &[], truncated, Convention::OpenCv),
            cells,
            encoded: Default::default(),
        }
    }

    pub(crate) fn message(&self, convention: Convention) -> FieldMessage {
        FieldMessage {
            convention,
            cells: FieldMessage::rows(&self.cells, convention),
            ..self.head.clone()
        }
    }

    pub(crate) fn encoded(&self, convention: Convention) -> String {
        self.encoded[usize::from(convention.code())]
            .get_or_init(|| ServerMessage::Field(Box::new(self.message(convention))).to_json())
            .clone()
    }
}

/// What a session's pipeline publishes to viewers.
#[derive(Debug, Clone)]
pub(crate) enum HubEvent {
    Batch(Arc<PublishedBatch>),
    Field(Arc<PublishedField>),
    SessionsChanged,
    Status {
        session_number: u32,
        id: String,
        counters: Counters,
    },
    Ended {
        session_number: u32,
        id: String,
        counters: Counters,
    },
}

/// One live session as others see it.
pub(crate) struct SessionShared {
    pub(crate) number: u32,
    pub(crate) description: SessionDescription,
    pub(crate) counters: Mutex<Counters>,
    /// Viewers subscribed to this session by name.
    pub(crate) viewers: AtomicUsize,
    /// A viewer asked for the mean-flow field to be emptied; the pipeline thread does it.
    pub(crate) reset_field: AtomicBool,
    /// Closes the session's frame queue: its pipeline then finishes what is queued and ends.
    pub(crate) close_queue: Box<dyn Fn() + Send + Sync>,
}

impl SessionShared {
    pub(crate) fn id(&self) -> &str {
        &self.description.id
    }

    pub(crate) fn counters(&self) -> MutexGuard<'_, Counters> {
        self.counters
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }
}

/// State shared by every connection.
pub(crate) struct Hub {
    pub(crate) options: ServerOptions,
    sessions: Mutex<BTreeMap<u32, Arc<SessionShared>>>,
    next_session: AtomicU32,
    /// Viewers subscribed to every session.
    pub(crate) wildcard_viewers: AtomicUsize,
    pub(crate) events: broadcast::Sender<HubEvent>,
    pub(crate) shutdown: watch_channel::Receiver<bool>,
    connections: AtomicUsize,
    connections_changed: Notify,
    /// Session pipeline threads still running.
    workers: AtomicUsize,
    workers_changed: Notify,
    /// Sessions started or starting, against `max_sessions`.
    session_slots: AtomicUsize,
    /// Serialises viewers' subscription changes, so the per-session limit cannot be overrun by
    /// viewers subscribing at the same moment.
    pub(crate) subscribing: Mutex<()>,
}

/// A place among `max_sessions`, held by a session from before its hello is accepted until it
/// ends; freed when dropped.
pub(crate) struct SessionSlot(Arc<Hub>);

impl Drop for SessionSlot {
    fn drop(&mut self) {
        self.0.session_slots.fetch_sub(1, Ordering::SeqCst);
    }
}

/// Held by each session's pipeline thread; shutdown waits until all are dropped.
pub(crate) struct WorkerGuard(Arc<Hub>);

impl Drop for WorkerGuard {
    fn drop(&mut self) {
        self.0.workers.fetch_sub(1, Ordering::SeqCst);
        self.0.workers_changed.notify_waiters();
    }
}

/// Held by each WebSocket connection; shutdown waits until all are dropped.
pub(crate) struct ConnectionGuard(Arc<Hub>);

impl Drop for ConnectionGuard {
    fn drop(&mut self) {
        self.0.connections.fetch_sub(1, Ordering::SeqCst);
        self.0.connections_changed.notify_waiters();
    }
}

impl Hub {
    pub(crate) fn new(options: ServerOptions, shutdown: watch_channel::Receiver<bool>) -> Self {
        let (events, _) = broadcast::channel(options.viewer_buffer.max(1));
        Self {
            options,
            sessions: Mutex::new(BTreeMap::new()),
            next_session: AtomicU32::new(0),
            wildcard_viewers: AtomicUsize::new(0),
            events,
            shutdown,
            connections: AtomicUsize::new(0),
            connections_changed: Notify::new(),
            workers: AtomicUsize::new(0),
            workers_changed: Notify::new(),
            session_slots: AtomicUsize::new(0),
            subscribing: Mutex::new(()),
        }
    }

    /// A session slot, or `None` when `max_sessions` are taken (checked and taken atomically).
    pub(crate) fn reserve_session(self: &Arc<Self>) -> Option<SessionSlot> {
        let max = self.options.max_sessions;
        self.session_slots
            .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |n| {
                (n < max).then_some(n + 1)
            })
            .ok()
            .map(|_| SessionSlot(Arc::clone(self)))
    }

    pub(crate) fn worker(self: &Arc<Self>) -> WorkerGuard {
        self.workers.fetch_add(1, Ordering::SeqCst);
        WorkerGuard(Arc::clone(self))
    }

    fn sessions(&self) -> MutexGuard<'_, BTreeMap<u32, Arc<SessionShared>>> {
        self.sessions
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }

    pub(crate) fn connection(self: &Arc<Self>) -> ConnectionGuard {
        self.connections.fetch_add(1, Ordering::SeqCst);
        ConnectionGuard(Arc::clone(self))
    }

    pub(crate) fn next_session_number(&self) -> u32 {
        self.next_session.fetch_add(1, Ordering::SeqCst) + 1
    }

    pub(crate) fn add_session(&self, session: Arc<SessionShared>) {
        self.sessions().insert(session.number, session);
        let _ = self.events.send(HubEvent::SessionsChanged);
    }

    /// The session's `session_ended` and `sessions` events are published before the lock is
    /// released: whoever sees the session gone finds both in the ring (a viewer closing at
    /// shutdown relies on it to send them before its bye).
    pub(crate) fn remove_session(&self, number: u32) {
        let mut sessions = self.sessions();
        if let Some(s) = sessions.remove(&number) {
            let counters = *s.counters();
            let _ = self.events.send(HubEvent::Ended {
                session_number: number,
                id: s.id().to_string(),
                counters,
            });
            let _ = self.events.send(HubEvent::SessionsChanged);
        }
        drop(sessions);
    }

    pub(crate) fn session_by_id(&self, id: &str) -> Option<Arc<SessionShared>> {
        self.sessions().values().find(|s| s.id() == id).cloned()
    }

    pub(crate) fn session_list(&self) -> Vec<SessionInfo> {
        let wildcard = self.wildcard_viewers.load(Ordering::Relaxed);
        self.sessions()
            .values()
            .map(|s| SessionInfo {
                session: s.description.clone(),
                viewers: s.viewers.load(Ordering::Relaxed) + wildcard,
                counters: *s.counters(),
            })
            .collect()
    }

    pub(crate) fn shutting_down(&self) -> bool {
        *self.shutdown.borrow()
    }

    pub(crate) fn session_count(&self) -> usize {
        self.sessions().len()
    }
}

/// A WebSocket peer's liveness: a ping is due every third of the idle timeout, and a peer that
/// has sent nothing (not even a pong) for the whole timeout is to be closed.
pub(crate) struct Keepalive {
    ticks: tokio::time::Interval,
    idle_timeout: Duration,
    last_heard: tokio::time::Instant,
}

impl Keepalive {
    pub(crate) async fn start(idle_timeout: Duration) -> Self {
        let mut ticks = tokio::time::interval((idle_timeout / 3).max(Duration::from_millis(10)));
        ticks.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        ticks.tick().await;
        Self {
            ticks,
            idle_timeout,
            last_heard: tokio::time::Instant::now(),
        }
    }

    /// The peer sent something.
    pub(crate) fn heard(&mut self) {
        self.last_heard = tokio::time::Instant::now();
    }

    /// Resolves when the next ping is due; `Err` (the reason to close) once the peer has been
    /// silent for the idle timeout.
    pub(crate) async fn ping_due(&mut self) -> Result<(), String> {
        self.ticks.tick().await;
        if self.last_heard.elapsed() > self.idle_timeout {
            Err(format!(
                "idle: nothing received for {} s",
                self.idle_timeout.as_secs_f64()
            ))
        } else {
            Ok(())
        }
    }
}

/// Waits until `count` reads 0, re-checking whenever `changed` is notified.
async fn until_zero(count: &AtomicUsize, changed: &Notify) {
    loop {
        let notified = changed.notified();
        if count.load(Ordering::SeqCst) == 0 {
            return;
        }
        notified.await;
    }
}

/// How a shutdown went.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ShutdownReport {
    /// Connections still open after `drain_timeout` (peers that stopped reading); they were
    /// dropped. Their sessions' frames were still all processed and recorded.
    pub connections_dropped: usize,
}

/// Serves until `shutdown` resolves, then closes every session cleanly (queues drained,
/// recordings complete, a bye to each headset and viewer) and returns.
pub async fn run(
    listener: tokio::net::TcpListener,
    options: ServerOptions,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> std::io::Result<ShutdownReport> {
    let (shutdown_tx, shutdown_rx) = watch_channel::channel(false);
    let drain_timeout = options.drain_timeout;
    let hub = Arc::new(Hub::new(options, shutdown_rx));
    let signal = async move {
        shutdown.await;
        tracing::info!("shutting down: closing sessions");
        let _ = shutdown_tx.send(true);
    };
    match hub.options.tls.clone() {
        Some(config) => {
            let handshake_timeout = hub.options.handshake_timeout;
            let listener = tls_listener::TlsListener::new(listener, config, handshake_timeout)?;
            serve_guarded(listener, &hub, signal).await?;
        }
        None => serve_guarded(listener.tap_io(|tcp| set_nodelay(tcp)), &hub, signal).await?,
    }
    // Upgraded WebSocket connections outlive axum's own connection tracking: wait for them.
    let drained = tokio::time::timeout(
        drain_timeout,
        until_zero(&hub.connections, &hub.connections_changed),
    )
    .await;
    let connections_dropped = if drained.is_err() {
        let open = hub.connections.load(Ordering::SeqCst);
        tracing::warn!(
            connections = open,
            "shutdown: {open} connection(s) still open after {drain_timeout:?}; dropping them"
        );
        for session in hub.sessions().values() {
            (session.close_queue)();
        }
        open
    } else {
        0
    };
    // Pipelines end once their queues are closed and drained, and only after their recordings
    // are complete: no time limit here, the work left is bounded by the queue sizes.
    until_zero(&hub.workers, &hub.workers_changed).await;
    Ok(ShutdownReport {
        connections_dropped,
    })
}

/// Serves the hub's routes on `listener` until `signal`, every connection held to the guard's
/// limits.
async fn serve_guarded<L>(
    listener: L,
    hub: &Arc<Hub>,
    signal: impl Future<Output = ()> + Send + 'static,
) -> std::io::Result<()>
where
    L: axum::serve::Listener,
    L::Addr: std::fmt::Debug,
{
    let options = &hub.options;
    let listener = guard::GuardedListener::new(
        listener,
        options.max_connections,
        options.handshake_timeout,
        options.idle_timeout,
    );
    axum::serve(listener, router(Arc::clone(hub)))
        .with_graceful_shutdown(signal)
        .await
}

/// Largest message a viewer may send.
const VIEWER_MESSAGE_BYTES: usize = 64 << 10;

fn router(hub: Arc<Hub>) -> Router {
    Router::new()
        .route("/", get(web::index))
        .route("/app/{*path}", get(web::app))
        .route("/vendor/{*path}", get(web::vendor))
        .route("/healthz", get(healthz))
        .route("/v1/sessions", get(sessions))
        .route(
            "/v1/ingest",
            get(|ws, headers, Query(query), State(hub)| {
                upgrade(access::Role::Ingest, ws, headers, query, hub)
            }),
        )
        .route(
            "/v1/watch",
            get(|ws, headers, Query(query), State(hub)| {
                upgrade(access::Role::Watch, ws, headers, query, hub)
            }),
        )
        .layer(axum::middleware::map_response(one_request_per_connection))
        .with_state(hub)
}

/// Plain HTTP requests get `Connection: close`: each connection carries one request (or one
/// WebSocket upgrade), so the request-head deadline of `guard` covers every request a client
/// makes, and a client cannot park a keep-alive connection and trickle its next request.
async fn one_request_per_connection(mut response: Response) -> Response {
    if response.status() != StatusCode::SWITCHING_PROTOCOLS {
        response.headers_mut().insert(
            header::CONNECTION,
            header::HeaderValue::from_static("close"),
        );
    }
    response
}

/// `?token=SECRET`, for clients that cannot set an `Authorization` header.
#[derive(Deserialize)]
struct TokenQuery {
    token: Option<String>,
}

/// The 401 (with the protocol's error message) for a request without the role's secret.
fn refusal(
    hub: &Hub,
    role: access::Role,
    headers: &HeaderMap,
    query: &TokenQuery,
) -> Option<Response> {
    let message = hub
        .options
        .access
        .check(role, headers, query.token.as_deref())
        .err()?;
    tracing::info!(?role, "refused: {message}");
    let body = ServerMessage::error(ErrorCode::Unauthorized, message).to_json();
    Some(
        (
            StatusCode::UNAUTHORIZED,
            [
                (header::WWW_AUTHENTICATE, "Bearer"),
                (header::CONTENT_TYPE, "application/json"),
            ],
            body,
        )
            .into_response(),
    )
}

/// A headset's (`Ingest`) or a viewer's (`Watch`) WebSocket: refused without the role's secret,
/// else upgraded with the role's message limit and served by the role's task.
async fn upgrade(
    role: access::Role,
    ws: WebSocketUpgrade,
    headers: HeaderMap,
    query: TokenQuery,
    hub: Arc<Hub>,
) -> Response {
    if let Some(refused) = refusal(&hub, role, &headers, &query) {
        return refused;
    }
    let max = match role {
        access::Role::Ingest => hub.options.max_message_bytes,
        // Viewers send small JSON requests: a frame must not buffer more than a message may hold.
        access::Role::Watch => VIEWER_MESSAGE_BYTES,
    };
    let ws = ws.max_message_size(max).max_frame_size(max);
    match role {
        access::Role::Ingest => ws.on_upgrade(move |socket| ingest::serve_headset(socket, hub)),
        access::Role::Watch => ws.on_upgrade(move |socket| watch::serve_viewer(socket, hub)),
    }
}

#[derive(Serialize)]
struct Health {
    status: &'static str,
    protocol: u32,
    version: &'static str,
    sessions: usize,
}

async fn healthz(State(hub): State<Arc<Hub>>) -> Json<Health> {
    Json(Health {
        status: if hub.shutting_down() {
            "shutting_down"
        } else {
            "ok"
        },
        protocol: PROTOCOL_VERSION,
        version: env!("CARGO_PKG_VERSION"),
        sessions: hub.sessions().len(),
    })
}

#[derive(Serialize)]
struct Sessions {
    sessions: Vec<SessionInfo>,
}

async fn sessions(
    headers: HeaderMap,
    Query(query): Query<TokenQuery>,
    State(hub): State<Arc<Hub>>,
) -> Response {
    if let Some(refused) = refusal(&hub, access::Role::Watch, &headers, &query) {
        return refused;
    }
    Json(Sessions {
        sessions: hub.session_list(),
    })
    .into_response()
}

/// Batches are small and latency-critical: no Nagle delay.
fn set_nodelay(tcp: &tokio::net::TcpStream) {
    if let Err(e) = tcp.set_nodelay(true) {
        tracing::warn!("cannot set TCP_NODELAY: {e}");
    }
}

/// Milliseconds since the Unix epoch, for session start times and recording names.
pub(crate) fn unix_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}
