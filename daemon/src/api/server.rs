//! The HTTP server under the router: hyper's connection handling with the limits a
//! daemon on a lab network needs, so that no client, however slow or numerous, can
//! hold the process's file descriptors or wait forever.
//!
//! - **Header read timeout** (hyper's own `header_read_timeout`, with a timer, which
//!   `axum::serve` does not install): a connection must deliver each request's headers
//!   within `[api] header-timeout-s` of the server starting to wait for them. That also
//!   bounds an idle keep-alive connection (hyper re-arms the timer while it waits for
//!   the next request) and a client trickling one header line at a time.
//! - **Connection cap**: at most `[api] max-connections` connections at once, and never
//!   more than the process's descriptor limit less a reserve for the instrument (run
//!   files, serial ports, the capture's log): at the cap the server stops accepting
//!   until a connection closes, and what waits stays in the kernel's backlog, costing
//!   the process nothing.
//! - **Write timeout** (`tokio-io-timeout`'s `TimeoutStream` under hyper): a
//!   connection whose client takes none of a response's bytes for `[api]
//!   request-timeout-s` is closed. `request-timeout-s` itself ends when a response's
//!   headers go out, so without this a client that stops reading a download or an
//!   event stream would hold its socket, and the download or stream slot, forever.
//! - **Read buffer** (hyper's `max_buf_size`, [`MAX_BUF`]): a request's head must fit
//!   64 KiB, so a connection holds no more than that before it is authenticated.
//! - **HTTP/1.1 only**: a protocol detector (hyper-util's `auto`) would read the first
//!   bytes of every connection before hyper's timer starts, so a silent client would
//!   never be timed out.
//! - **Graceful shutdown** (hyper-util's `GracefulShutdown`): on a stop signal every
//!   connection finishes its request in flight and closes.
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use axum::Router;
use axum::extract::connect_info::IntoMakeServiceWithConnectInfo;
use hyper::server::conn::http1;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::server::graceful::GracefulShutdown;
use hyper_util::service::TowerToHyperService;
use tokio::net::TcpListener;
use tokio::sync::Semaphore;
use tower::Service as _;

/// The most a connection's read (and write) buffer holds, so the most of a request's
/// head held before it is parsed whole: hyper's default is about 400 KB, which 512
/// connections trickling one long header each (no key needed to send headers) made
/// 200 MB. A head past it is answered 431 and the connection closed; bodies stream
/// through it in pieces.
pub const MAX_BUF: usize = 64 << 10;

/// How long connections have to finish after a stop signal.
const SHUTDOWN_GRACE: Duration = Duration::from_secs(1);

/// File descriptors kept free for the instrument whatever the connections take: the
/// run's files and log, the serial ports, the USB device, the blocking pool's reads.
pub const FD_RESERVE: usize = 64;

/// Most connections the server holds at once: `configured`, lowered to the process's
/// descriptor limit (`nofile`, where it is known) less [`FD_RESERVE`], and at least 8.
pub fn connection_cap(configured: usize, nofile: Option<u64>) -> usize {
    let by_fds = nofile.map_or(usize::MAX, |n| {
        usize::try_from(n)
            .unwrap_or(usize::MAX)
            .saturating_sub(FD_RESERVE)
    });
    configured.min(by_fds).max(8)
}

/// The soft limit on open files of this process, from `/proc/self/limits` (Linux);
/// `None` where it cannot be read or is unlimited.
pub fn open_files_limit() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/self/limits").ok()?;
    let line = text.lines().find(|l| l.starts_with("Max open files"))?;
    line.split_whitespace().nth(3)?.parse().ok()
}

/// The connection limits of [`serve_connections`].
#[derive(Clone, Copy, Debug)]
pub struct ConnectionLimits {
    /// Longest wait for a request's headers (and for the next request on an idle
    /// keep-alive connection).
    pub header_timeout: Duration,
    /// Most connections at once.
    pub max_connections: usize,
    /// Longest a write may wait for the client to take bytes.
    pub write_timeout: Duration,
}

/// Serves `app` on `listener` until `shutdown` completes, then lets the connections
/// finish the requests they are answering and returns.
pub async fn serve_connections(
    listener: TcpListener,
    app: Router,
    limits: ConnectionLimits,
    shutdown: impl std::future::Future<Output = ()>,
) -> std::io::Result<()> {
    let slots = Arc::new(Semaphore::new(limits.max_connections));
    let graceful = GracefulShutdown::new();
    let mut make: IntoMakeServiceWithConnectInfo<Router, SocketAddr> =
        app.into_make_service_with_connect_info::<SocketAddr>();
    // HTTP/1.1 only (what the dashboard, curl and scripts speak on plain HTTP): an
    // HTTP/2-or-1 detector reads the connection's first bytes before any timer runs,
    // and would hold a silent connection forever.
    let mut builder = http1::Builder::new();
    builder
        .timer(TokioTimer::new())
        .header_read_timeout(limits.header_timeout)
        .max_buf_size(MAX_BUF)
        .keep_alive(true);
    tokio::pin!(shutdown);
    let mut warned_full = false;
    loop {
        // A free slot first: at the cap, connections wait in the kernel's backlog.
        let permit = tokio::select! {
            biased;
            () = &mut shutdown => break,
            permit = Arc::clone(&slots).acquire_owned() => match permit {
                Ok(p) => p,
                Err(_) => break,
            },
        };
        if slots.available_permits() == 0 && !warned_full {
            tracing::warn!(
                max = limits.max_connections,
                "the API holds its most connections; further clients wait until one closes"
            );
            warned_full = true;
        } else if slots.available_permits() > limits.max_connections / 2 {
            warned_full = false;
        }
        let (stream, peer) = tokio::select! {
            biased;
            () = &mut shutdown => break,
            accepted = listener.accept() => match accepted {
                Ok(a) => a,
                Err(e) => {
                    // Out of descriptors (or a connection reset before accept): the
                    // reserve keeps the instrument going; try again shortly.
                    tracing::warn!(error = %e, "accept failed; retrying in 50 ms");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                    continue;
                }
            },
        };
        let _ = stream.set_nodelay(true);
        let mut stream = tokio_io_timeout::TimeoutStream::new(stream);
        stream.set_write_timeout(Some(limits.write_timeout));
        let Ok(service) = make.call(peer).await;
        let service = TowerToHyperService::new(service);
        let conn = builder.serve_connection(TokioIo::new(Box::pin(stream)), service);
        let conn = graceful.watch(conn);
        tokio::spawn(async move {
            // Held until the connection closes.
            let _permit = permit;
            if let Err(e) = conn.await {
                tracing::debug!(peer = %peer, error = %e, "connection closed with an error");
            }
        });
    }
    drop(listener);
    // Requests in flight finish; a client that keeps its connection past the grace is
    // cut off (event streams end with the service's shutdown before this).
    if tokio::time::timeout(SHUTDOWN_GRACE, graceful.shutdown())
        .await
        .is_err()
    {
        tracing::debug!("connections still open after the shutdown grace; closing them");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_cap_keeps_a_reserve_of_descriptors() {
        assert_eq!(connection_cap(1024, Some(256)), 256 - FD_RESERVE);
        assert_eq!(connection_cap(100, Some(65_536)), 100);
        assert_eq!(connection_cap(100, None), 100);
        assert_eq!(connection_cap(1024, Some(16)), 8);
    }

    #[test]
    fn the_open_files_limit_is_read_on_linux() {
        if cfg!(target_os = "linux") {
            let n = open_files_limit().expect("Max open files in /proc/self/limits");
            assert!(n >= 16, "{n}");
        }
    }
}
