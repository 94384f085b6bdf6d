//! A viewer connection (`/v1/watch`): lists sessions, subscribes to one or all, and receives
//! their vector batches in the convention it asked for.

use std::sync::atomic::Ordering;
use std::sync::Arc;

use axum::extract::ws::{CloseFrame, Message, WebSocket};
use futures_util::{SinkExt, StreamExt};
use tokio::sync::broadcast::error::{RecvError, TryRecvError};

use super::{Hub, HubEvent, Keepalive};
use crate::protocol::{
    parse_text, Convention, ErrorCode, ProtocolError, ServerMessage, ViewerMessage, VIEWER_TYPES,
};

#[derive(Debug, Clone, Copy, PartialEq)]
enum Target {
    All,
    One(u32),
}

struct Subscription {
    target: Target,
    convention: Convention,
    /// Batches with each vector's velocity errors.
    uncertainty: bool,
}

/// Keeps the session's viewer count right however the subscription ends.
struct Viewer {
    hub: Arc<Hub>,
    subscription: Option<Subscription>,
}

impl Viewer {
    fn set(&mut self, subscription: Option<Subscription>) {
        self.count(-1);
        self.subscription = subscription;
        self.count(1);
    }

    fn count(&self, delta: isize) {
        let Some(s) = &self.subscription else {
            return;
        };
        let apply = |counter: &std::sync::atomic::AtomicUsize| {
            if delta > 0 {
                counter.fetch_add(1, Ordering::Relaxed);
            } else {
                counter.fetch_sub(1, Ordering::Relaxed);
            }
        };
        match s.target {
            Target::All => apply(&self.hub.wildcard_viewers),
            Target::One(number) => {
                if let Some(session) = self.hub.sessions().get(&number) {
                    apply(&session.viewers);
                }
            }
        }
    }

    /// What this viewer is sent for a hub event, if anything.
    fn message_for(&mut self, event: HubEvent, sessions: impl Fn() -> Message) -> Option<Message> {
        match event {
            HubEvent::Batch(published) => {
                let uncertainty = self.subscription.as_ref().is_some_and(|s| s.uncertainty);
                self.wants(published.batch.session_number)
                    .map(|convention| Message::Binary(published.encoded(convention, uncertainty)))
            }
            HubEvent::Field(field) => self
                .wants(field.session_number)
                .map(|convention| Message::Text(field.encoded(convention).into())),
            HubEvent::SessionsChanged => Some(sessions()),
            HubEvent::Status {
                session_number,
                id,
                counters,
            } => self.wants(session_number).map(|_| {
                text(&ServerMessage::Status {
                    session: id,
                    counters,
                })
            }),
            HubEvent::Ended {
                session_number,
                id,
                counters,
            } => {
                if self.subscription.as_ref().map(|s| s.target) == Some(Target::One(session_number))
                {
                    // Its session is gone: the count it held went with it.
                    self.subscription = None;
                }
                Some(text(&ServerMessage::SessionEnded {
                    session: id,
                    counters,
                }))
            }
        }
    }

    fn wants(&self, session_number: u32) -> Option<Convention> {
        let s = self.subscription.as_ref()?;
        (s.target == Target::All || s.target == Target::One(session_number)).then_some(s.convention)
    }
}

impl Drop for Viewer {
    fn drop(&mut self) {
        self.count(-1);
    }
}

fn text(message: &ServerMessage) -> Message {
    Message::Text(message.to_json().into())
}

pub(crate) async fn serve_viewer(socket: WebSocket, hub: Arc<Hub>) {
    let _guard = hub.connection();
    let (sink, stream) = socket.split();
    run_viewer(sink, stream, hub).await;
}

/// The viewer loop, over any message sink and stream (a socket, or channels in tests). Events
/// are taken from the hub's broadcast ring one at a time and sent; while a send waits on a slow
/// viewer the ring moves on, and the viewer skips what it missed (newest wins).
async fn run_viewer<S, R, E>(mut sink: S, mut stream: R, hub: Arc<Hub>)
where
    S: futures_util::Sink<Message> + Unpin,
    R: futures_util::Stream<Item = Result<Message, E>> + Unpin,
{
    let mut events = hub.events.subscribe();
    let mut shutdown = hub.shutdown.clone();
    let send_timeout = hub.options.send_timeout;
    let mut viewer = Viewer {
        hub: Arc::clone(&hub),
        subscription: None,
    };
    let sessions = || {
        text(&ServerMessage::Sessions {
            sessions: hub.session_list(),
        })
    };
    // On shutdown the viewer keeps receiving until the sessions have drained (their last
    // batches and `session_ended`), then gets its bye; never longer than half the drain time.
    let mut closing_by: Option<tokio::time::Instant> = hub
        .shutting_down()
        .then(|| tokio::time::Instant::now() + hub.options.drain_timeout / 2);
    let mut reply = Some(sessions());
    let mut lagged: u64 = 0;
    let mut keepalive = Keepalive::start(hub.options.idle_timeout).await;
    let mut reason = "server shutting down".to_string();
    loop {
        if let Some(message) = reply.take() {
            // A viewer that cannot take one message in `send_timeout` is gone.
            match tokio::time::timeout(send_timeout, sink.send(message)).await {
                Ok(Ok(())) => {}
                Ok(Err(_)) => return,
                Err(_) => {
                    tracing::info!("viewer not reading for {send_timeout:?}: disconnecting it");
                    return;
                }
            }
        }
        if closing_by.is_some() && hub.session_count() == 0 {
            // A session leaves the hub only after its `session_ended` and `sessions` events are
            // in the ring: what is still waiting there goes out before the bye.
            let mut drained = Vec::new();
            loop {
                match events.try_recv() {
                    Ok(event) => drained.extend(viewer.message_for(event, sessions)),
                    Err(TryRecvError::Lagged(_)) => {}
                    Err(_) => break,
                }
            }
            let flushed = tokio::time::timeout(send_timeout, async {
                for message in drained {
                    sink.send(message).await?;
                }
                Ok::<_, S::Error>(())
            })
            .await;
            if !matches!(flushed, Ok(Ok(()))) {
                return;
            }
            break;
        }
        let deadline = closing_by.unwrap_or_else(|| tokio::time::Instant::now() + send_timeout);
        reply = tokio::select! {
            event = events.recv() => match event {
                Ok(event) => viewer.message_for(event, sessions),
                Err(RecvError::Lagged(n)) => {
                    lagged += n;
                    tracing::debug!(lagged, "viewer too slow: skipped {n} events");
                    None
                }
                Err(RecvError::Closed) => break,
            },
            message = stream.next() => {
                keepalive.heard();
                match message {
                    Some(Ok(Message::Text(t))) => Some(text(&handle_request(&hub, &mut viewer, t.as_str()))),
                    Some(Ok(Message::Binary(_))) => Some(text(&ServerMessage::error(
                        ErrorCode::UnknownType,
                        "viewers send only text messages (subscribe, unsubscribe, list)",
                    ))),
                    Some(Ok(Message::Ping(_) | Message::Pong(_))) => None,
                    Some(Ok(Message::Close(_))) => {
                        // Flushes the close frame the WebSocket queued in answer (RFC 6455
                        // 5.5.1): the viewer sees a clean close, not 1006.
                        let _ = tokio::time::timeout(send_timeout, sink.close()).await;
                        return;
                    }
                    Some(Err(_)) | None => return,
                }
            },
            // Browsers answer WebSocket pings by themselves: only a vanished viewer goes silent.
            due = keepalive.ping_due() => {
                if let Err(idle) = due {
                    reason = idle;
                    tracing::info!("viewer {reason}: disconnecting it");
                    break;
                }
                Some(Message::Ping(Default::default()))
            },
            // Once seen (or once the sender is gone), `changed` would fire at once forever.
            _ = shutdown.changed(), if closing_by.is_none() => {
                closing_by = Some(tokio::time::Instant::now() + hub.options.drain_timeout / 2);
                None
            }
            _ = tokio::time::sleep_until(deadline), if closing_by.is_some() => break,
        };
    }
    // 1000 whatever the reason, as for headsets: the bye before it says why.
    let close = Message::Close(Some(CloseFrame {
        code: 1000,
        reason: reason.clone().into(),
    }));
    let bye = text(&ServerMessage::Bye {
        reason,
        counters: None,
    });
    let _ = tokio::time::timeout(send_timeout, async {
        if sink.send(bye).await.is_ok() && sink.send(close).await.is_ok() {
            let _ = sink.close().await;
        }
    })
    .await;
}

/// Viewers of the target's session, or of the most watched session for `All`.
fn viewers_of(hub: &Hub, target: Target) -> usize {
    let sessions = hub.sessions();
    let subscribed = match target {
        Target::One(number) => sessions
            .get(&number)
            .map_or(0, |s| s.viewers.load(Ordering::Relaxed)),
        Target::All => sessions
            .values()
            .map(|s| s.viewers.load(Ordering::Relaxed))
            .max()
            .unwrap_or(0),
    };
    subscribed + hub.wildcard_viewers.load(Ordering::Relaxed)
}

fn handle_request(hub: &Hub, viewer: &mut Viewer, text: &str) -> ServerMessage {
    let request = match parse_text::<ViewerMessage>(text, VIEWER_TYPES) {
        Ok(r) => r,
        Err(e) => return e.to_message(),
    };
    match request {
        ViewerMessage::List {} => ServerMessage::Sessions {
            sessions: hub.session_list(),
        },
        ViewerMessage::Ping { id } => ServerMessage::Pong { id },
        ViewerMessage::Unsubscribe {} => {
            viewer.set(None);
            ServerMessage::Unsubscribed
        }
        ViewerMessage::ResetField { session } => {
            let sessions = hub.sessions();
            let reset: Vec<&super::SessionShared> = if session == "*" {
                sessions.values().map(|s| s.as_ref()).collect()
            } else if let Some(s) = sessions.values().find(|s| s.id() == session) {
                vec![s.as_ref()]
            } else {
                return ProtocolError::new(
                    ErrorCode::UnknownSession,
                    format!("no live session {session:?} (GET /v1/sessions lists them; \"*\" resets all)"),
                )
                .to_message();
            };
            for s in &reset {
                s.reset_field.store(true, Ordering::Relaxed);
            }
            ServerMessage::FieldReset {
                sessions: reset.iter().map(|s| s.id().to_string()).collect(),
            }
        }
        ViewerMessage::Subscribe {
            session,
            convention,
            uncertainty,
        } => {
            let target = if session == "*" {
                Target::All
            } else if let Some(s) = hub.session_by_id(&session) {
                Target::One(s.number)
            } else {
                return ProtocolError::new(
                    ErrorCode::UnknownSession,
                    format!("no live session {session:?} (GET /v1/sessions lists them; \"*\" subscribes to all)"),
                )
                .to_message();
            };
            let _one_at_a_time = hub
                .subscribing
                .lock()
                .unwrap_or_else(|poisoned| poisoned.into_inner());
            let already = viewer.subscription.as_ref().map(|s| s.target) == Some(target);
            let max = hub.options.max_viewers_per_session;
            if !already && viewers_of(hub, target) >= max {
                return ProtocolError::new(
                    ErrorCode::LimitReached,
                    format!("{session}: {max} viewers are watching, the most this server allows per session (--max-viewers)"),
                )
                .to_message();
            }
            viewer.set(Some(Subscription {
                target,
                convention,
                uncertainty,
            }));
            ServerMessage::Subscribed {
                session,
                convention,
                uncertainty,
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::{decode_batch, Batch, BatchKind};
    use crate::server::{PublishedBatch, ServerOptions};
    use futures_channel::mpsc;

    fn batch(frame_index: u64) -> HubEvent {
        HubEvent::Batch(Arc::new(PublishedBatch::new(Batch {
            kind: BatchKind::Causal,
            session_number: 1,
            frame_index,
            t_s: frame_index as f64,
            world: false,
            processing_us: 0,
            age_us: 0,
            vectors: Vec::new(),
        })))
    }

    #[tokio::test]
    async fn a_stalled_viewer_loses_the_oldest_events_and_then_gets_the_newest() {
        let (_shutdown, shutdown_rx) = tokio::sync::watch::channel(false);
        let options = ServerOptions {
            viewer_buffer: 4,
            ..Default::default()
        };
        let hub = Arc::new(Hub::new(options, shutdown_rx));
        // A sink with no buffer: a send completes only when the test reads.
        let (to_viewer, mut received) = mpsc::channel::<Message>(0);
        let (requests, from_viewer) =
            mpsc::unbounded::<Result<Message, std::convert::Infallible>>();
        let subscribe = r#"{"type":"subscribe","session":"*"}"#;
        requests
            .unbounded_send(Ok(Message::Text(subscribe.into())))
            .expect("queued");
        let viewer = tokio::spawn(run_viewer(to_viewer, from_viewer, Arc::clone(&hub)));
        let mut texts = 0;
        while texts < 2 {
            // The session list, then the subscription.
            match received.next().await.expect("viewer alive") {
                Message::Text(t) => {
                    texts += 1;
                    assert!(
                        texts == 1 || t.as_str().contains("subscribed"),
                        "{}",
                        t.as_str()
                    );
                }
                other => panic!("{other:?}"),
            }
        }
        // Publishing never waits for the viewer, however many events go out.
        for i in 0..50 {
            hub.events.send(batch(i)).expect("a subscriber");
        }
        let mut seen = Vec::new();
        while seen.last() != Some(&49) {
            match received.next().await.expect("viewer alive") {
                Message::Binary(b) => seen.push(decode_batch(&b).expect("batch").frame_index),
                other => panic!("{other:?}"),
            }
        }
        assert!(seen.len() < 10, "the oldest were skipped: {seen:?}");
        assert_eq!(
            &seen[seen.len() - 4..],
            &[46, 47, 48, 49],
            "the newest arrive: {seen:?}"
        );
        drop(requests);
        viewer.await.expect("viewer ends when its stream ends");
    }
}
