//! Connection limits below HTTP: at most `max_connections` open at once (more are closed on
//! accept), a deadline for the client's request head (a peer that connects and sends nothing,
//! or trickles, is cut off), and an idle timeout once it is served.
//!
//! The request deadline runs until the server first writes: HTTP/1 answers only a complete
//! request head, so the first write marks the end of the handshake. From then on the connection
//! is closed after `idle` with no byte either way; WebSocket peers are pinged well within that.

use std::future::Future;
use std::io;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use axum::serve::Listener;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tokio::time::{Instant, Sleep};

pub(super) struct GuardedListener<L> {
    inner: L,
    slots: Arc<Semaphore>,
    max_connections: usize,
    handshake: Duration,
    idle: Duration,
    last_refusal_logged: Option<Instant>,
}

impl<L: Listener> GuardedListener<L> {
    pub(crate) fn new(
        inner: L,
        max_connections: usize,
        handshake: Duration,
        idle: Duration,
    ) -> Self {
        let max_connections = max_connections.max(1);
        Self {
            inner,
            slots: Arc::new(Semaphore::new(max_connections)),
            max_connections,
            handshake,
            idle,
            last_refusal_logged: None,
        }
    }
}

impl<L: Listener> Listener for GuardedListener<L> {
    type Io = GuardedIo<L::Io>;
    type Addr = L::Addr;

    async fn accept(&mut self) -> (Self::Io, Self::Addr) {
        loop {
            let (io, addr) = self.inner.accept().await;
            match Arc::clone(&self.slots).try_acquire_owned() {
                Ok(permit) => return (GuardedIo::new(io, permit, self.handshake, self.idle), addr),
                Err(_) => {
                    // Dropping the stream closes it. Say so at most once a second.
                    let now = Instant::now();
                    if self
                        .last_refusal_logged
                        .is_none_or(|t| now - t > Duration::from_secs(1))
                    {
                        self.last_refusal_logged = Some(now);
                        tracing::warn!(
                            "{} connections open (--max-connections): closing new ones",
                            self.max_connections
                        );
                    }
                }
            }
        }
    }

    fn local_addr(&self) -> io::Result<Self::Addr> {
        self.inner.local_addr()
    }
}

/// A connection with a request deadline, then an idle timeout, and a slot of the listener's.
pub(super) struct GuardedIo<T> {
    inner: T,
    deadline: Pin<Box<Sleep>>,
    /// Still waiting for the first request head to be answered.
    handshaking: bool,
    idle: Duration,
    _slot: OwnedSemaphorePermit,
}

impl<T> GuardedIo<T> {
    fn new(inner: T, slot: OwnedSemaphorePermit, handshake: Duration, idle: Duration) -> Self {
        Self {
            inner,
            deadline: Box::pin(tokio::time::sleep(handshake)),
            handshaking: true,
            idle,
            _slot: slot,
        }
    }

    fn progressed(&mut self) {
        self.deadline.as_mut().reset(Instant::now() + self.idle);
    }

    /// After the inner IO returned `Pending`: an error once the deadline has passed, else still
    /// pending (the deadline's waker is registered either way).
    fn pending<R>(&mut self, cx: &mut Context<'_>) -> Poll<io::Result<R>> {
        if self.deadline.as_mut().poll(cx).is_pending() {
            return Poll::Pending;
        }
        let what = if self.handshaking {
            "no complete request within the handshake timeout"
        } else {
            "idle timeout"
        };
        Poll::Ready(Err(io::Error::new(io::ErrorKind::TimedOut, what)))
    }
}

impl<T> GuardedIo<T> {
    /// A write that went through ends the handshake (the server answers only complete request
    /// heads) and counts as traffic.
    fn after_write(
        &mut self,
        cx: &mut Context<'_>,
        polled: Poll<io::Result<usize>>,
    ) -> Poll<io::Result<usize>> {
        match polled {
            Poll::Ready(Ok(n)) => {
                if n > 0 {
                    self.handshaking = false;
                    self.progressed();
                }
                Poll::Ready(Ok(n))
            }
            Poll::Pending => self.pending(cx),
            other => other,
        }
    }
}

impl<T: AsyncRead + Unpin> AsyncRead for GuardedIo<T> {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        let before = buf.filled().len();
        match Pin::new(&mut this.inner).poll_read(cx, buf) {
            Poll::Ready(Ok(())) => {
                // During the handshake, bytes read do not extend the deadline: a trickle
                // must still finish in time.
                if buf.filled().len() > before && !this.handshaking {
                    this.progressed();
                }
                Poll::Ready(Ok(()))
            }
            Poll::Pending => this.pending(cx),
            other => other,
        }
    }
}

impl<T: AsyncWrite + Unpin> AsyncWrite for GuardedIo<T> {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        data: &[u8],
    ) -> Poll<io::Result<usize>> {
        let this = self.get_mut();
        let polled = Pin::new(&mut this.inner).poll_write(cx, data);
        this.after_write(cx, polled)
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().inner).poll_flush(cx)
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().inner).poll_shutdown(cx)
    }

    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        let this = self.get_mut();
        let polled = Pin::new(&mut this.inner).poll_write_vectored(cx, bufs);
        this.after_write(cx, polled)
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    fn guarded(
        io: tokio::io::DuplexStream,
        handshake_ms: u64,
        idle_ms: u64,
    ) -> GuardedIo<tokio::io::DuplexStream> {
        let slot = Arc::new(Semaphore::new(1))
            .try_acquire_owned()
            .expect("a free slot");
        GuardedIo::new(
            io,
            slot,
            Duration::from_millis(handshake_ms),
            Duration::from_millis(idle_ms),
        )
    }

    #[tokio::test]
    async fn a_peer_that_trickles_its_request_is_cut_off_at_the_deadline() {
        let (mut client, server) = tokio::io::duplex(64);
        let mut server = guarded(server, 300, 60_000);
        let trickle = tokio::spawn(async move {
            for _ in 0..100 {
                if client.write_all(b"G").await.is_err() {
                    break;
                }
                tokio::time::sleep(Duration::from_millis(30)).await;
            }
            client
        });
        let started = Instant::now();
        let mut buf = [0; 16];
        let error = loop {
            match server.read(&mut buf).await {
                Ok(0) => panic!("closed"),
                Ok(_) => {}
                Err(e) => break e,
            }
        };
        assert_eq!(error.kind(), io::ErrorKind::TimedOut);
        let waited = started.elapsed();
        // Bytes kept arriving all along: only the deadline ended it.
        assert!(
            waited >= Duration::from_millis(300) && waited < Duration::from_millis(2000),
            "{waited:?}"
        );
        drop(server);
        drop(trickle.await);
    }

    #[tokio::test]
    async fn once_answered_only_silence_longer_than_idle_closes() {
        let (mut client, server) = tokio::io::duplex(64);
        let mut server = guarded(server, 200, 600);
        let mut buf = [0; 64];
        client
            .write_all(b"GET / HTTP/1.1\r\n\r\n")
            .await
            .expect("writes");
        assert!(server.read(&mut buf).await.expect("reads") > 0);
        server
            .write_all(b"HTTP/1.1 101\r\n")
            .await
            .expect("answers");
        // Well past the handshake deadline, traffic within the idle time keeps it open.
        for _ in 0..5 {
            tokio::time::sleep(Duration::from_millis(300)).await;
            client.write_all(b"x").await.expect("writes");
            assert_eq!(server.read(&mut buf).await.expect("reads"), 1);
        }
        let started = Instant::now();
        let error = server.read(&mut buf).await.expect_err("idle");
        assert_eq!(error.kind(), io::ErrorKind::TimedOut);
        assert!(started.elapsed() >= Duration::from_millis(550));
    }
}
