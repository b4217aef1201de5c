//! The HTTP server under the router: hyper's connection handling with the limits a
//! daemon on a lab network needs, so that no client, however slow or numerous, can
//! hold the process's file descriptors or wait forever.
//!
//! - **Header read timeout** (hyper's own `header_read_timeout`, with a timer, which
//!   `axum::serve` does not install): a connection must deliver each request's headers
//!   within `[api] header-timeout-s` of the server starting to wait for them. That also
//!   bounds an idle keep-alive connection (hyper re-arms the timer while it waits for
//!   the next request) and a client trickling one header line at a time.
//! - **Connection caps**: at most `[api] max-connections` connections at once, never
//!   more than the process's descriptor limit less a reserve for the instrument (run
//!   files, serial ports, the capture's log), and at most `[api]
//!   max-connections-per-peer` from one remote address. Loopback has
//!   [`LOOPBACK_RESERVE`] more of its own, so the instrument's own computer always
//!   reaches the e-stop and the health check, whatever other hosts hold. A connection
//!   past its cap is accepted and closed at once (until 2026-12-06 the server stopped
//!   accepting at the cap: one remote host holding idle connections, reconnecting as
//!   each timed out, kept the e-stop from connecting for a minute).
//! - **Send buffer** ([`SEND_BUFFER`]): fixed, not the kernel's autotuned up to 4 MiB,
//!   so an event stream a client does not read fills it within minutes and the write
//!   timeout closes it (with 4 MiB, about two hours on the idle instrument stream).
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

/// Connections kept for loopback peers (the instrument's own computer) beyond
/// `[api] max-connections`.
pub const LOOPBACK_RESERVE: usize = 16;

/// Each connection's socket send buffer, bytes: 256 KiB keeps a download at LAN speed
/// (it covers 2 Gb/s at 1 ms round trip) and lets a client that stops reading fill it.
pub const SEND_BUFFER: usize = 256 << 10;

/// How long connections have to finish after a stop signal.
const SHUTDOWN_GRACE: Duration = Duration::from_secs(1);

/// File descriptors kept free for the instrument whatever the connections take: the
/// run's files and log, the serial ports, the USB device, the blocking pool's reads.
pub const FD_RESERVE: usize = 64;

/// Most connections the server holds at once for any peer: `configured`, lowered to
/// the process's descriptor limit (`nofile`, where it is known) less [`FD_RESERVE`]
/// and [`LOOPBACK_RESERVE`], and at least 8.
pub fn connection_cap(configured: usize, nofile: Option<u64>) -> usize {
    let by_fds = nofile.map_or(usize::MAX, |n| {
        usize::try_from(n)
            .unwrap_or(usize::MAX)
            .saturating_sub(FD_RESERVE + LOOPBACK_RESERVE)
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
    /// Most connections at once (loopback has [`LOOPBACK_RESERVE`] more).
    pub max_connections: usize,
    /// Most connections one remote address holds at once.
    pub max_per_peer: usize,
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
    let loopback_slots = Arc::new(Semaphore::new(LOOPBACK_RESERVE));
    let peers = Arc::new(PeerCounts::default());
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
        // A slot for the peer, or the connection closed at once: a host at its own cap,
        // or the server at its cap, gives way; loopback takes its reserve after that.
        let ip = peer.ip().to_canonical();
        let Some(peer_slot) = PeerSlot::take(&peers, ip, limits.max_per_peer) else {
            tracing::debug!(peer = %peer, "a connection past its host's cap: closed");
            continue;
        };
        let permit = match Arc::clone(&slots).try_acquire_owned() {
            Ok(p) => p,
            Err(_) => match ip
                .is_loopback()
                .then(|| Arc::clone(&loopback_slots).try_acquire_owned())
            {
                Some(Ok(p)) => p,
                _ => {
                    if !warned_full {
                        tracing::warn!(
                            max = limits.max_connections,
                            "the API holds its most connections; further ones are closed until one ends \
                             (loopback has {LOOPBACK_RESERVE} of its own)"
                        );
                        warned_full = true;
                    }
                    continue;
                }
            },
        };
        if slots.available_permits() > limits.max_connections / 2 {
            warned_full = false;
        }
        let _ = stream.set_nodelay(true);
        let _ = socket2::SockRef::from(&stream).set_send_buffer_size(SEND_BUFFER);
        let mut stream = tokio_io_timeout::TimeoutStream::new(stream);
        stream.set_write_timeout(Some(limits.write_timeout));
        let Ok(service) = make.call(peer).await;
        let service = TowerToHyperService::new(service);
        let conn = builder.serve_connection(TokioIo::new(Box::pin(stream)), service);
        let conn = graceful.watch(conn);
        tokio::spawn(async move {
            // Held until the connection closes.
            let _permit = permit;
            let _peer_slot = peer_slot;
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

/// Open connections by remote address.
#[derive(Default)]
struct PeerCounts(std::sync::Mutex<std::collections::HashMap<std::net::IpAddr, usize>>);

/// One connection counted against its peer's cap, given back when dropped.
struct PeerSlot {
    peers: Arc<PeerCounts>,
    ip: std::net::IpAddr,
}

impl PeerSlot {
    /// A slot for `ip`, if it holds fewer than `max` (loopback is not counted).
    fn take(peers: &Arc<PeerCounts>, ip: std::net::IpAddr, max: usize) -> Option<PeerSlot> {
        if !ip.is_loopback() {
            let mut counts = peers.0.lock().unwrap_or_else(|p| p.into_inner());
            let n = counts.entry(ip).or_insert(0);
            if *n >= max {
                return None;
            }
            *n += 1;
        }
        Some(PeerSlot {
            peers: Arc::clone(peers),
            ip,
        })
    }
}

impl Drop for PeerSlot {
    fn drop(&mut self) {
        if self.ip.is_loopback() {
            return;
        }
        let mut counts = self.peers.0.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(n) = counts.get_mut(&self.ip) {
            *n -= 1;
            if *n == 0 {
                counts.remove(&self.ip);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_cap_keeps_a_reserve_of_descriptors() {
        assert_eq!(
            connection_cap(1024, Some(256)),
            256 - FD_RESERVE - LOOPBACK_RESERVE
        );
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
