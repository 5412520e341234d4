//! Serving the viewer's connections (HTTP/1.1 on hyper, upgrades to the live socket allowed)
//! with the two timeouts that keep a held connection from holding the daemon:
//!
//! - **header read**: a request's head must arrive within [`Timeouts::header`] of the server
//!   waiting for it (a client that trickles header bytes, "slowloris", is cut off);
//! - **idle**: a connection with no request being answered and no byte read or written for
//!   [`Timeouts::idle`] is closed (a keep-alive connection left open, a client that stops
//!   reading its response). A request being answered (a large render) is never cut.
//!
//! The live socket, once upgraded, keeps itself alive with pings ([`super::live`]).
//! On `stop` the server accepts no more and lets every connection finish its request.

use axum::Router;
use hyper::body::Incoming;
use hyper_util::rt::{TokioIo, TokioTimer};
use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::{Duration, Instant};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tower::ServiceExt;

/// Seconds a request's head may take to arrive, by default (`http_header_timeout_secs`).
pub const DEFAULT_HEADER_SECS: f64 = 10.0;
/// Seconds a connection may sit idle, by default (`http_idle_secs`).
pub const DEFAULT_IDLE_SECS: f64 = 60.0;

/// The connection timeouts.
#[derive(Clone, Copy, Debug)]
pub struct Timeouts {
    /// Longest wait for a request's head.
    pub header: Duration,
    /// Longest time with no request being answered and nothing read or written.
    pub idle: Duration,
}

impl Default for Timeouts {
    fn default() -> Self {
        Self {
            header: Duration::from_secs_f64(DEFAULT_HEADER_SECS),
            idle: Duration::from_secs_f64(DEFAULT_IDLE_SECS),
        }
    }
}

/// Serves `router` on every connection `listener` accepts until `stop` resolves, then waits
/// for the connections' requests in flight.
pub async fn serve<L>(
    mut listener: L,
    router: Router,
    timeouts: Timeouts,
    stop: impl Future<Output = ()> + Send,
) where
    L: axum::serve::Listener,
    L::Io: AsyncRead + AsyncWrite + Unpin + Send + 'static,
{
    // Each connection holds a receiver; the server waits for all of them to drop.
    let (closing, open) = tokio::sync::watch::channel(false);
    let mut stop = std::pin::pin!(stop);
    loop {
        let (io, _) = tokio::select! {
            accepted = listener.accept() => accepted,
            () = &mut stop => break,
        };
        tokio::spawn(connection(io, router.clone(), timeouts, open.clone()));
    }
    let _ = closing.send(true);
    drop(open);
    closing.closed().await;
}

/// One connection, until it ends, times out, or the server stops (then after its request).
async fn connection<Io>(
    io: Io,
    router: Router,
    timeouts: Timeouts,
    mut closing: tokio::sync::watch::Receiver<bool>,
) where
    Io: AsyncRead + AsyncWrite + Unpin + Send + 'static,
{
    let activity = Arc::new(Activity::new());
    let io = TokioIo::new(Watched {
        io,
        activity: activity.clone(),
    });
    let answering = activity.clone();
    let service = hyper::service::service_fn(move |req: hyper::Request<Incoming>| {
        let busy = Busy::new(answering.clone());
        let answer = router.clone().oneshot(req.map(axum::body::Body::new));
        async move {
            let response = answer.await;
            drop(busy);
            response
        }
    });
    let mut builder = hyper::server::conn::http1::Builder::new();
    builder
        .timer(TokioTimer::new())
        .header_read_timeout(timeouts.header);
    let conn = builder.serve_connection(io, service).with_upgrades();
    let mut conn = std::pin::pin!(conn);
    let mut stopping = false;
    loop {
        let idle_for = activity.idle_for();
        let check_in = timeouts
            .idle
            .saturating_sub(idle_for)
            .max(Duration::from_millis(50));
        tokio::select! {
            result = conn.as_mut() => {
                if let Err(e) = result {
                    tracing::debug!("viewer connection ended: {e}");
                }
                return;
            }
            changed = closing.changed(), if !stopping => {
                if changed.is_err() || *closing.borrow() {
                    stopping = true;
                    conn.as_mut().graceful_shutdown();
                }
            }
            () = tokio::time::sleep(check_in) => {
                if activity.busy() == 0 && activity.idle_for() >= timeouts.idle {
                    tracing::debug!(idle_secs = timeouts.idle.as_secs_f64(), "closing an idle viewer connection");
                    return;
                }
            }
        }
    }
}

/// When a connection last moved a byte, and how many of its requests are being answered.
struct Activity {
    start: Instant,
    /// Milliseconds after `start` of the last byte read or written.
    last_ms: AtomicU64,
    busy: AtomicUsize,
}

impl Activity {
    fn new() -> Self {
        Self {
            start: Instant::now(),
            last_ms: AtomicU64::new(0),
            busy: AtomicUsize::new(0),
        }
    }

    fn touch(&self) {
        let ms = self.start.elapsed().as_millis() as u64;
        self.last_ms.store(ms, Ordering::Relaxed);
    }

    fn idle_for(&self) -> Duration {
        let last = Duration::from_millis(self.last_ms.load(Ordering::Relaxed));
        self.start.elapsed().saturating_sub(last)
    }

    fn busy(&self) -> usize {
        self.busy.load(Ordering::Relaxed)
    }
}

/// A request being answered: the connection is not idle while it lives.
struct Busy(Arc<Activity>);

impl Busy {
    fn new(a: Arc<Activity>) -> Self {
        a.busy.fetch_add(1, Ordering::Relaxed);
        Self(a)
    }
}

impl Drop for Busy {
    fn drop(&mut self) {
        self.0.touch();
        self.0.busy.fetch_sub(1, Ordering::Relaxed);
    }
}

/// An I/O stream noting each byte moved in its [`Activity`].
struct Watched<Io> {
    io: Io,
    activity: Arc<Activity>,
}

impl<Io: AsyncRead + Unpin> AsyncRead for Watched<Io> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        let before = buf.filled().len();
        let r = Pin::new(&mut self.io).poll_read(cx, buf);
        if buf.filled().len() > before {
            self.activity.touch();
        }
        r
    }
}

impl<Io: AsyncWrite + Unpin> AsyncWrite for Watched<Io> {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        let r = Pin::new(&mut self.io).poll_write(cx, buf);
        if matches!(r, Poll::Ready(Ok(n)) if n > 0) {
            self.activity.touch();
        }
        r
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.io).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.io).poll_shutdown(cx)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::routing::get;
    use std::io::{Read, Write};

    /// A server of `/` (at once) and `/slow` (after 1.5 s) with 0.5 s timeouts.
    async fn server() -> std::net::SocketAddr {
        let router = Router::new().route("/", get(|| async { "ok" })).route(
            "/slow",
            get(|| async {
                tokio::time::sleep(Duration::from_millis(1500)).await;
                "slow"
            }),
        );
        let tcp = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = tcp.local_addr().unwrap();
        let t = Timeouts {
            header: Duration::from_millis(500),
            idle: Duration::from_millis(500),
        };
        tokio::spawn(serve(tcp, router, t, std::future::pending()));
        addr
    }

    /// Reads until the server closes; the bytes read and the seconds it took.
    fn until_closed(s: &mut std::net::TcpStream) -> (String, f64) {
        let t0 = Instant::now();
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        let mut out = Vec::new();
        let _ = s.read_to_end(&mut out);
        (
            String::from_utf8_lossy(&out).into_owned(),
            t0.elapsed().as_secs_f64(),
        )
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn trickled_headers_and_idle_connections_are_closed_but_slow_answers_are_not() {
        let addr = server().await;
        tokio::task::spawn_blocking(move || {
            // A head sent a byte every 100 ms never completes: cut off after 0.5 s.
            let mut s = std::net::TcpStream::connect(addr).unwrap();
            let t0 = Instant::now();
            for b in b"GET / HTTP/1.1\r\nHost: x\r\nX-Slow: yyyyyyyyyyyyyyyyyyyyyyyyyyyyyyy" {
                if s.write_all(&[*b]).is_err() {
                    break;
                }
                std::thread::sleep(Duration::from_millis(100));
            }
            let held = t0.elapsed().as_secs_f64();
            assert!(held < 4.0, "the trickle was let on for {held} s");
            // A keep-alive connection answered once, then left: closed when idle.
            let mut s = std::net::TcpStream::connect(addr).unwrap();
            s.write_all(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n").unwrap();
            let (answer, secs) = until_closed(&mut s);
            assert!(
                answer.starts_with("HTTP/1.1 200") && answer.ends_with("ok"),
                "{answer}"
            );
            assert!((0.3..3.0).contains(&secs), "closed after {secs} s");
            // A connection that never sends: closed too.
            let mut s = std::net::TcpStream::connect(addr).unwrap();
            let (answer, secs) = until_closed(&mut s);
            assert!(answer.is_empty() && secs < 3.0, "{answer:?} after {secs} s");
            // An answer that takes longer than both timeouts is still given.
            let mut s = std::net::TcpStream::connect(addr).unwrap();
            s.write_all(b"GET /slow HTTP/1.1\r\nHost: x\r\n\r\n")
                .unwrap();
            let (answer, secs) = until_closed(&mut s);
            assert!(answer.ends_with("slow"), "{answer:?} after {secs} s");
        })
        .await
        .unwrap();
    }
}
