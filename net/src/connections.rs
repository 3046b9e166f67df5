//! Connections, bounded before anyone is authenticated: a peer that opens sockets and
//! never speaks must not take the server's file descriptors.
//!
//! - [`Limited`] wraps the listener's stream of accepted sockets: at most
//!   `max_connections` are open at once, and at most `max_per_address` from one source
//!   address (an IPv6 address counts by its /64, what one host is usually given), so
//!   one address cannot take every place and lock the others out; a socket accepted
//!   beyond either bound is closed at once (the client sees its connection closed, the
//!   server keeps no descriptor for it). An accept error (EMFILE: the process is out of descriptors) pauses accepting
//!   briefly instead of spinning.
//! - [`Guarded`] wraps each accepted socket and holds its place. Its first
//!   [`HANDSHAKE_BYTES`] bytes (the HTTP/2 connection preface, or the start of a TLS
//!   handshake) must arrive within the handshake timeout; after that, a connection from
//!   which nothing at all is read for the idle timeout is closed. A live peer always
//!   sends something: the server's HTTP/2 keep-alive PINGs ([`crate::server`]) must be
//!   answered, and the idle timeout is longer than a ping's interval and timeout
//!   together. (The TLS handshake as a whole is bounded by the handshake timeout too,
//!   set on the TLS acceptor.)
//! - With a [`LinkEmulation`], each accepted socket is shaped beneath everything else
//!   (TLS included) by [`crate::emulate`]: both directions of every link are shaped once.

use std::collections::HashMap;
use std::future::Future;
use std::io;
use std::net::IpAddr;
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::TcpStream;
use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tokio::time::{Instant, Sleep};
use tokio_stream::Stream;
use tonic::transport::server::{Connected, TcpConnectInfo};

use crate::emulate::{LinkEmulation, MaybeEmulated};

/// Bytes a connection must send within the handshake timeout: the length of the
/// HTTP/2 client preface (`PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n`); a TLS ClientHello is
/// longer.
pub const HANDSHAKE_BYTES: usize = 24;

/// How long accepting pauses after an accept error such as EMFILE.
const ACCEPT_ERROR_PAUSE: Duration = Duration::from_millis(100);

/// Sockets refused in one poll before the accept loop yields to other tasks.
const REFUSALS_PER_POLL: usize = 64;

/// How connections are bounded; see the module.
#[derive(Clone, Copy, Debug)]
pub struct ConnectionLimits {
    /// Connections open at once; more are closed as soon as they are accepted.
    pub max_connections: usize,
    /// Connections open at once from one source address (see the module); more from
    /// it are closed as soon as they are accepted.
    pub max_per_address: usize,
    /// Time for a new connection's first [`HANDSHAKE_BYTES`] bytes (and for a TLS
    /// handshake).
    pub handshake_timeout: Duration,
    /// A connection from which nothing is read for this long is closed; `None` for
    /// never (only when HTTP/2 keep-alive is off: a quiet client would be cut).
    pub idle_timeout: Option<Duration>,
    /// Shape every connection as a link of this kind; `None` (the default) leaves
    /// sockets as they are.
    pub emulate: Option<LinkEmulation>,
}

/// The stream of accepted connections, bounded; see the module.
pub struct Limited<I> {
    inner: I,
    slots: Arc<Semaphore>,
    addresses: Arc<Mutex<HashMap<IpAddr, usize>>>,
    limits: ConnectionLimits,
    pause: Option<Pin<Box<Sleep>>>,
    /// Whether the last socket was refused (to warn once per burst, not per socket).
    refusing: bool,
}

impl<I> Limited<I> {
    /// `inner`'s connections, at most `limits.max_connections` (at least 1) at once.
    pub fn new(inner: I, limits: ConnectionLimits) -> Limited<I> {
        Limited {
            inner,
            slots: Arc::new(Semaphore::new(limits.max_connections.max(1))),
            addresses: Arc::default(),
            limits,
            pause: None,
            refusing: false,
        }
    }
}

impl<I> Stream for Limited<I>
where
    I: Stream<Item = io::Result<TcpStream>> + Unpin,
{
    type Item = io::Result<Guarded>;

    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        let this = &mut *self;
        for _ in 0..REFUSALS_PER_POLL {
            if let Some(pause) = this.pause.as_mut() {
                std::task::ready!(pause.as_mut().poll(cx));
                this.pause = None;
            }
            match std::task::ready!(Pin::new(&mut this.inner).poll_next(cx)) {
                None => return Poll::Ready(None),
                Some(Err(e)) => {
                    // Never end the server for an accept error. One connection's own
                    // failure is skipped; anything else (EMFILE: the process is out of
                    // descriptors) pauses accepting, or the loop would spin on it.
                    if matches!(
                        e.kind(),
                        io::ErrorKind::ConnectionAborted
                            | io::ErrorKind::ConnectionReset
                            | io::ErrorKind::Interrupted
                            | io::ErrorKind::WouldBlock
                    ) {
                        tracing::debug!(error = %e, "a connection failed before it was accepted");
                    } else {
                        tracing::warn!(error = %e, "cannot accept a connection; pausing accepts");
                        this.pause = Some(Box::pin(tokio::time::sleep(ACCEPT_ERROR_PAUSE)));
                    }
                }
                Some(Ok(stream)) => {
                    let address = AddressSlot::take(&this.addresses, &stream, &this.limits);
                    match (address, this.slots.clone().try_acquire_owned()) {
                        (Ok(address), Ok(slot)) => {
                            this.refusing = false;
                            return Poll::Ready(Some(Ok(Guarded::new(
                                stream,
                                slot,
                                address,
                                this.limits,
                            ))));
                        }
                        (address, _) => {
                            if !this.refusing {
                                match address {
                                    Err(peer) => tracing::warn!(
                                        %peer,
                                        limit = this.limits.max_per_address,
                                        "too many connections open from one address: its new ones are closed at once"
                                    ),
                                    Ok(_) => tracing::warn!(
                                        limit = this.limits.max_connections,
                                        "too many connections open: new ones are closed at once"
                                    ),
                                }
                            }
                            this.refusing = true;
                            drop(stream);
                        }
                    }
                }
            }
        }
        cx.waker().wake_by_ref();
        Poll::Pending
    }
}

/// One connection's place among its source address's (see the module): given back
/// when the connection is dropped.
struct AddressSlot {
    addresses: Arc<Mutex<HashMap<IpAddr, usize>>>,
    key: IpAddr,
}

impl AddressSlot {
    /// A place for `stream`'s source address, or that address when it has every place
    /// it may have. A socket whose peer cannot be read (already gone) takes no place.
    fn take(
        addresses: &Arc<Mutex<HashMap<IpAddr, usize>>>,
        stream: &TcpStream,
        limits: &ConnectionLimits,
    ) -> Result<Option<AddressSlot>, IpAddr> {
        let Ok(peer) = stream.peer_addr() else {
            return Ok(None);
        };
        let key = address_key(peer.ip());
        let mut map = dray_sync::lock(addresses);
        let n = map.entry(key).or_insert(0);
        if *n >= limits.max_per_address.max(1) {
            return Err(key);
        }
        *n += 1;
        Ok(Some(AddressSlot {
            addresses: addresses.clone(),
            key,
        }))
    }
}

impl Drop for AddressSlot {
    fn drop(&mut self) {
        let mut map = dray_sync::lock(&self.addresses);
        if let Some(n) = map.get_mut(&self.key) {
            *n = n.saturating_sub(1);
            if *n == 0 {
                map.remove(&self.key);
            }
        }
    }
}

/// What a source address counts as: an IPv4 address (an IPv4-mapped IPv6 one too) as
/// itself, an IPv6 address by its /64 (one host usually holds a whole /64, so counting
/// its addresses one by one would bound nothing).
pub fn address_key(ip: IpAddr) -> IpAddr {
    match ip {
        IpAddr::V4(_) => ip,
        IpAddr::V6(v6) => match v6.to_ipv4_mapped() {
            Some(v4) => IpAddr::V4(v4),
            None => {
                let s = v6.segments();
                IpAddr::V6(std::net::Ipv6Addr::new(s[0], s[1], s[2], s[3], 0, 0, 0, 0))
            }
        },
    }
}

/// An accepted connection holding its place; see the module.
pub struct Guarded {
    io: MaybeEmulated<TcpStream>,
    _slot: OwnedSemaphorePermit,
    address: Option<AddressSlot>,
    /// Bytes still owed before the handshake timeout stops applying (0 after).
    owed: usize,
    idle_timeout: Option<Duration>,
    last_read: Instant,
    /// When the connection is closed unless something is read first.
    deadline: Pin<Box<Sleep>>,
}

impl Guarded {
    /// The source address this connection counts against (its key: an IPv6 address by
    /// its /64); `None` when the peer could not be read as it was accepted.
    pub fn source(&self) -> Option<IpAddr> {
        self.address.as_ref().map(|a| a.key)
    }

    fn new(
        io: TcpStream,
        slot: OwnedSemaphorePermit,
        address: Option<AddressSlot>,
        limits: ConnectionLimits,
    ) -> Guarded {
        let now = Instant::now();
        Guarded {
            io: MaybeEmulated::new(io, limits.emulate),
            _slot: slot,
            address,
            owed: HANDSHAKE_BYTES,
            idle_timeout: limits.idle_timeout,
            last_read: now,
            deadline: Box::pin(tokio::time::sleep_until(now + limits.handshake_timeout)),
        }
    }

    /// Whether the deadline has passed with nothing read since it was set; moves it on
    /// when something was.
    fn expired(&mut self, cx: &mut Context<'_>) -> bool {
        loop {
            if self.deadline.as_mut().poll(cx).is_pending() {
                return false;
            }
            if self.owed > 0 {
                return true;
            }
            let Some(idle) = self.idle_timeout else {
                return false;
            };
            let next = self.last_read + idle;
            if next <= Instant::now() {
                return true;
            }
            self.deadline.as_mut().reset(next);
        }
    }
}

impl AsyncRead for Guarded {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = &mut *self;
        let before = buf.filled().len();
        match Pin::new(&mut this.io).poll_read(cx, buf) {
            Poll::Ready(Ok(())) => {
                let n = buf.filled().len() - before;
                if n > 0 {
                    this.last_read = Instant::now();
                    if this.owed > 0 {
                        this.owed = this.owed.saturating_sub(n);
                        if this.owed == 0 {
                            match this.idle_timeout {
                                Some(idle) => this.deadline.as_mut().reset(this.last_read + idle),
                                // Far enough never to fire while the connection lives.
                                None => this
                                    .deadline
                                    .as_mut()
                                    .reset(this.last_read + Duration::from_secs(86_400 * 365)),
                            }
                        }
                    }
                }
                Poll::Ready(Ok(()))
            }
            Poll::Ready(Err(e)) => Poll::Ready(Err(e)),
            Poll::Pending => {
                if this.expired(cx) {
                    let what = if this.owed > 0 {
                        "did not start its handshake"
                    } else {
                        "sent nothing"
                    };
                    tracing::debug!(peer = ?this.io.get_ref().peer_addr().ok(), "closing a connection that {what} in time");
                    return Poll::Ready(Err(io::Error::new(
                        io::ErrorKind::TimedOut,
                        format!("the connection {what} in time"),
                    )));
                }
                Poll::Pending
            }
        }
    }
}

impl AsyncWrite for Guarded {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.io).poll_write(cx, buf)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.io).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.io).poll_shutdown(cx)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.io).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.io.is_write_vectored()
    }
}

impl Connected for Guarded {
    /// The socket's own: handlers see the peer's address as before.
    type ConnectInfo = TcpConnectInfo;

    fn connect_info(&self) -> TcpConnectInfo {
        self.io.get_ref().connect_info()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio_stream::StreamExt;

    /// EMFILE from accept neither ends the server's stream of connections nor spins: the
    /// next connection is still served.
    #[tokio::test]
    async fn an_accept_error_pauses_and_accepting_goes_on() {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
            .await
            .expect("bind");
        let client = TcpStream::connect(listener.local_addr().expect("address"))
            .await
            .expect("connect");
        let (server_side, _) = listener.accept().await.expect("accept");
        let emfile = io::Error::from_raw_os_error(24);
        let accepted = tokio_stream::iter(vec![Err(emfile), Ok(server_side)]);
        let mut limited = Limited::new(
            accepted,
            ConnectionLimits {
                max_connections: 1,
                max_per_address: 1,
                handshake_timeout: Duration::from_secs(10),
                idle_timeout: None,
                emulate: None,
            },
        );
        let first = limited.next().await.expect("a connection, not the end");
        let guarded = first.expect("the connection after the error");
        assert_eq!(
            guarded.connect_info().remote_addr(),
            client.local_addr().ok()
        );
        assert!(limited.next().await.is_none());
    }

    #[test]
    fn ipv6_addresses_count_by_their_64_and_mapped_ipv4_as_ipv4() {
        let a: IpAddr = "2001:db8:1:2:aaaa::1".parse().expect("address");
        let b: IpAddr = "2001:db8:1:2:bbbb::7".parse().expect("address");
        let c: IpAddr = "2001:db8:1:3::1".parse().expect("address");
        assert_eq!(address_key(a), address_key(b));
        assert_ne!(address_key(a), address_key(c));
        let mapped: IpAddr = "::ffff:127.0.0.2".parse().expect("address");
        assert_eq!(
            address_key(mapped),
            "127.0.0.2".parse::<IpAddr>().expect("v4")
        );
    }
}
