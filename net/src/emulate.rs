//! An emulated interconnect: each connection between dray processes behaves like a link
//! of a real cluster (a bandwidth and a per-message latency) instead of loopback, which is
//! nearly free. It prices a distributed render's communication on one machine; it is off
//! unless asked for (`--emulate-link`), and with it off nothing in this module runs.
//!
//! What is modelled, per connection and per direction:
//! - a **delay line**: bytes written reach the other side no earlier than `latency` after
//!   they were written. Written bytes are timestamped and released when due, so latency
//!   never caps throughput (many messages are in flight at once, as on a wire), and
//! - a **token bucket** of `bandwidth_bits_per_s`: bytes leave the delay line no faster
//!   than the bandwidth, after a burst of [`LinkEmulation::burst_bytes`].
//!
//! A message of `n` bytes thus arrives `latency + n / bandwidth` after it was written, as
//! on a link with that propagation delay and serialization rate.
//!
//! What is not modelled: loss, reordering, a switch shared by several links, or one NIC
//! shared by all the connections of a process (each connection has its own buckets).
//!
//! Where: [`crate::connections`] wraps every connection a server accepts (beneath TLS,
//! at the byte level), so both directions of every link between dray processes are shaped
//! exactly once: clients connect to servers, and the client end is left alone.
//!
//! Timers: tokio's timer wheel ticks in milliseconds, far coarser than the tens of
//! microseconds being emulated, so each shaped connection waits on its own `timerfd`
//! (a high-resolution kernel timer, readable when it fires) through tokio's reactor.

use std::collections::VecDeque;
use std::fmt;
use std::io;
use std::os::fd::OwnedFd;
use std::pin::Pin;
use std::str::FromStr;
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use bytes::{Buf, Bytes};
use rustix::time::{
    Itimerspec, TimerfdClockId, TimerfdFlags, TimerfdTimerFlags, Timespec, timerfd_create,
    timerfd_settime,
};
use tokio::io::unix::AsyncFd;
use tokio::io::{AsyncRead, AsyncWrite, Interest, ReadBuf};

/// The smallest token bucket: a burst of this many bytes may leave at once.
pub const MIN_BURST_BYTES: u64 = 8 * 1024;
/// The bucket holds at least the bytes the bandwidth carries in this long, so a fast link
/// is not woken for every few KiB.
const BURST_TIME: Duration = Duration::from_micros(50);
/// The least a delay line holds before its writer waits (as on a full socket buffer).
const MIN_QUEUE_BYTES: u64 = 1 << 20;
/// The longest latency accepted: more would trip the servers' handshake and keep-alive
/// timeouts long before it told anything about a cluster.
pub const MAX_LATENCY: Duration = Duration::from_secs(10);
/// Bytes read from the socket at once.
const READ_CHUNK: usize = 64 * 1024;

/// How each link between dray processes behaves; see the module.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LinkEmulation {
    /// Bits per second each direction of a link carries; `None` for no limit.
    pub bandwidth_bits_per_s: Option<u64>,
    /// How long after it was written a byte reaches the other side (each direction).
    pub latency: Duration,
}

/// Why a link emulation spec was refused.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum LinkSpecError {
    #[error(
        "an empty link emulation: give bandwidth=RATE and/or latency=TIME, e.g. bandwidth=1gbit,latency=100us"
    )]
    Empty,
    #[error("`{0}` is not KEY=VALUE (keys: bandwidth, latency)")]
    NotKeyValue(String),
    #[error("unknown key `{0}` (keys: bandwidth, latency)")]
    UnknownKey(String),
    #[error("`{0}` is given more than once")]
    Repeated(String),
    #[error("bandwidth `{value}`: {why}")]
    Bandwidth { value: String, why: String },
    #[error("latency `{value}`: {why}")]
    Latency { value: String, why: String },
}

impl LinkEmulation {
    /// Bytes the token bucket holds: at least [`MIN_BURST_BYTES`], and what the bandwidth
    /// carries in 50 µs.
    pub fn burst_bytes(&self) -> u64 {
        let per_burst_time = self
            .bandwidth_bits_per_s
            .map_or(0, |b| (b as f64 / 8.0 * BURST_TIME.as_secs_f64()) as u64);
        MIN_BURST_BYTES.max(per_burst_time)
    }

    /// Bytes one direction's delay line holds before its writer waits: at least 1 MiB and
    /// twice the bandwidth-delay product, so the line never limits throughput.
    pub fn queue_bytes(&self) -> u64 {
        let bdp = self
            .bandwidth_bits_per_s
            .map_or(0, |b| (b as f64 / 8.0 * self.latency.as_secs_f64()) as u64);
        MIN_QUEUE_BYTES.max(bdp.saturating_mul(2))
    }
}

/// `KEY=VALUE,...` with keys `bandwidth` (a number and `bit`, `kbit`, `mbit`, `gbit` or
/// `tbit`, powers of 1000 as for network links) and `latency` (a number and `ns`, `us`,
/// `ms` or `s`); either may be left out (no limit, no delay).
impl FromStr for LinkEmulation {
    type Err = LinkSpecError;

    fn from_str(spec: &str) -> Result<LinkEmulation, LinkSpecError> {
        let mut bandwidth = None;
        let mut latency = None;
        for part in spec.split(',').map(str::trim).filter(|p| !p.is_empty()) {
            let (key, value) = part
                .split_once('=')
                .ok_or_else(|| LinkSpecError::NotKeyValue(part.to_string()))?;
            let (key, value) = (key.trim(), value.trim());
            match key {
                "bandwidth" if bandwidth.is_some() => {
                    return Err(LinkSpecError::Repeated(key.into()));
                }
                "bandwidth" => bandwidth = Some(parse_bandwidth(value)?),
                "latency" if latency.is_some() => return Err(LinkSpecError::Repeated(key.into())),
                "latency" => latency = Some(parse_latency(value)?),
                other => return Err(LinkSpecError::UnknownKey(other.to_string())),
            }
        }
        if bandwidth.is_none() && latency.is_none() {
            return Err(LinkSpecError::Empty);
        }
        Ok(LinkEmulation {
            bandwidth_bits_per_s: bandwidth,
            latency: latency.unwrap_or(Duration::ZERO),
        })
    }
}

/// The spec again, in units [`FromStr`] reads back exactly (for a child process).
impl fmt::Display for LinkEmulation {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        /// `x` in the largest of `units` that divides it exactly.
        fn exact(x: u128, units: &[(&'static str, u128)]) -> (u128, &'static str) {
            units
                .iter()
                .find(|(_, scale)| x.is_multiple_of(*scale))
                .map_or((x, ""), |(unit, scale)| (x / scale, unit))
        }
        let mut sep = "";
        if let Some(b) = self.bandwidth_bits_per_s {
            let (n, unit) = exact(
                b.into(),
                &[
                    ("tbit", 1_000_000_000_000),
                    ("gbit", 1_000_000_000),
                    ("mbit", 1_000_000),
                    ("kbit", 1_000),
                    ("bit", 1),
                ],
            );
            write!(f, "bandwidth={n}{unit}")?;
            sep = ",";
        }
        let (n, unit) = exact(
            self.latency.as_nanos(),
            &[
                ("s", 1_000_000_000),
                ("ms", 1_000_000),
                ("us", 1_000),
                ("ns", 1),
            ],
        );
        write!(f, "{sep}latency={n}{unit}")
    }
}

/// A number followed by a unit from `units` (longest suffixes first), scaled.
fn number_with_unit(value: &str, units: &[(&str, f64)]) -> Result<f64, String> {
    let lower = value.to_ascii_lowercase();
    let names: Vec<&str> = units.iter().map(|(u, _)| *u).collect();
    let Some((number, scale)) = units
        .iter()
        .find_map(|(unit, scale)| lower.strip_suffix(unit).map(|n| (n.trim(), *scale)))
    else {
        return Err(format!("needs a unit: one of {}", names.join(", ")));
    };
    let x: f64 = number
        .parse()
        .map_err(|_| format!("`{number}` is not a number"))?;
    if !x.is_finite() || x < 0.0 {
        return Err("must be a finite number, not negative".into());
    }
    Ok(x * scale)
}

fn parse_bandwidth(value: &str) -> Result<u64, LinkSpecError> {
    let fail = |why: String| LinkSpecError::Bandwidth {
        value: value.to_string(),
        why,
    };
    let bits = number_with_unit(
        value,
        &[
            ("tbit", 1e12),
            ("gbit", 1e9),
            ("mbit", 1e6),
            ("kbit", 1e3),
            ("bit", 1.0),
        ],
    )
    .map_err(fail)?;
    if bits < 8.0 {
        return Err(fail("must be at least 8bit (a byte per second)".into()));
    }
    if bits >= u64::MAX as f64 {
        return Err(fail("is too large".into()));
    }
    Ok(bits.round() as u64)
}

fn parse_latency(value: &str) -> Result<Duration, LinkSpecError> {
    let fail = |why: String| LinkSpecError::Latency {
        value: value.to_string(),
        why,
    };
    let secs = number_with_unit(
        value,
        &[
            ("ns", 1e-9),
            ("µs", 1e-6),
            ("us", 1e-6),
            ("ms", 1e-3),
            ("s", 1.0),
        ],
    )
    .map_err(fail)?;
    if secs > MAX_LATENCY.as_secs_f64() {
        return Err(fail(format!("must be at most {}s", MAX_LATENCY.as_secs())));
    }
    // Whole nanoseconds, so the spec prints back as it was read.
    Ok(Duration::from_nanos((secs * 1e9).round() as u64))
}

/// A token bucket in bytes, in its virtual-clock form (GCRA): `tat` is when the link
/// will have sent every byte let out so far, at `rate`; a byte may leave once that
/// instant is at most one burst's worth of time (`tolerance`) away. Equivalent to a
/// bucket of `burst` bytes, with one difference that matters here: bytes are charged
/// from the instant they became due, not the instant a wake-up got round to them, so a
/// late wake-up catches up instead of losing the link's capacity.
#[derive(Debug)]
struct TokenBucket {
    /// Bytes per second.
    rate: f64,
    /// `burst / rate`.
    tolerance: Duration,
    /// Bytes the next wait is for, at most (a burst: not a wake-up per few bytes).
    burst: usize,
    tat: Instant,
}

impl TokenBucket {
    fn new(bits_per_s: u64, burst: u64, now: Instant) -> TokenBucket {
        let rate = bits_per_s as f64 / 8.0;
        TokenBucket {
            rate,
            tolerance: Duration::from_secs_f64(burst as f64 / rate),
            burst: usize::try_from(burst).unwrap_or(usize::MAX),
            tat: now,
        }
    }

    fn seconds(&self, bytes: usize) -> Duration {
        Duration::from_secs_f64(bytes as f64 / self.rate)
    }

    /// How many of `len` bytes that became due at `due` may leave at `now`, or, if none,
    /// when a burst of them (or all, if fewer) may.
    fn allowed(&self, due: Instant, len: usize, now: Instant) -> Result<usize, Instant> {
        let start = self.tat.max(due);
        let budget = (now + self.tolerance).saturating_duration_since(start);
        let n = ((budget.as_secs_f64() * self.rate) as usize).min(len);
        if n > 0 {
            return Ok(n);
        }
        // (1 ns late rather than a rounding early, which would find nothing allowed.)
        let at = start + self.seconds(len.min(self.burst)) + Duration::from_nanos(1);
        Err(at.checked_sub(self.tolerance).unwrap_or(at))
    }

    /// `n` bytes that became due at `due` have left.
    fn take(&mut self, due: Instant, n: usize) {
        self.tat = self.tat.max(due) + self.seconds(n);
    }
}

/// What a delay line can do next.
enum Next<'a> {
    /// These bytes (the head of the oldest chunk) may leave now.
    Now(&'a [u8]),
    /// Something may leave at this instant.
    At(Instant),
    /// Nothing is queued.
    Empty,
}

/// One direction of a link: bytes timestamped on entry, released when due and allowed
/// by the bucket.
#[derive(Debug)]
struct DelayLine {
    /// Bytes with the instant they may leave, oldest first.
    chunks: VecDeque<(Instant, Bytes)>,
    queued: usize,
    capacity: usize,
    latency: Duration,
    bucket: Option<TokenBucket>,
}

impl DelayLine {
    fn new(link: &LinkEmulation, now: Instant) -> DelayLine {
        DelayLine {
            chunks: VecDeque::new(),
            queued: 0,
            capacity: usize::try_from(link.queue_bytes()).unwrap_or(usize::MAX),
            latency: link.latency,
            bucket: link
                .bandwidth_bits_per_s
                .map(|b| TokenBucket::new(b, link.burst_bytes(), now)),
        }
    }

    fn space(&self) -> usize {
        self.capacity.saturating_sub(self.queued)
    }

    /// Take as much of `data` as there is space for, entered at `now`; how much was taken.
    fn push(&mut self, now: Instant, data: &[u8]) -> usize {
        let n = data.len().min(self.space());
        if n > 0 {
            self.chunks
                .push_back((now + self.latency, Bytes::copy_from_slice(&data[..n])));
            self.queued += n;
        }
        n
    }

    fn next(&mut self, now: Instant) -> Next<'_> {
        let Some((due, head)) = self.chunks.front() else {
            return Next::Empty;
        };
        if *due > now {
            return Next::At(*due);
        }
        let allowed = match &self.bucket {
            None => head.len(),
            Some(bucket) => match bucket.allowed(*due, head.len(), now) {
                Ok(n) => n,
                Err(at) => return Next::At(at),
            },
        };
        Next::Now(&head[..allowed])
    }

    /// `n` bytes of the head have left.
    fn consume(&mut self, n: usize) {
        self.queued -= n;
        if let Some((due, head)) = self.chunks.front_mut() {
            if let Some(bucket) = &mut self.bucket {
                bucket.take(*due, n);
            }
            head.advance(n);
            if head.is_empty() {
                self.chunks.pop_front();
            }
        }
    }
}

/// A one-shot high-resolution timer (a non-blocking `timerfd` in tokio's reactor).
struct Timer {
    fd: AsyncFd<OwnedFd>,
    /// The instant it is set for, if set and not yet seen to fire.
    armed: Option<Instant>,
}

impl Timer {
    fn new() -> io::Result<Timer> {
        let fd = timerfd_create(
            TimerfdClockId::Monotonic,
            TimerfdFlags::NONBLOCK | TimerfdFlags::CLOEXEC,
        )?;
        // SAFETY: the `OwnedFd` is moved into the `AsyncFd` and never taken out or
        // replaced (only `get_ref` is used), so the descriptor stays open and the same
        // for the `AsyncFd`'s whole life, as `register_with_interest` requires.
        let fd = unsafe { AsyncFd::register_with_interest(fd, Interest::READABLE) }
            .map_err(io::Error::from)?;
        Ok(Timer { fd, armed: None })
    }

    /// Ready once `at` has passed; otherwise the task is woken then.
    fn poll_at(&mut self, cx: &mut Context<'_>, at: Instant) -> Poll<io::Result<()>> {
        if self.armed != Some(at) {
            let now = Instant::now();
            if at <= now {
                self.armed = None;
                return Poll::Ready(Ok(()));
            }
            // Relative, and at least 1 ns: a zero value would disarm the timer.
            let d = (at - now).max(Duration::from_nanos(1));
            let value = Timespec {
                tv_sec: d.as_secs() as i64,
                tv_nsec: d.subsec_nanos().into(),
            };
            let zero = Timespec {
                tv_sec: 0,
                tv_nsec: 0,
            };
            timerfd_settime(
                self.fd.get_ref(),
                TimerfdTimerFlags::empty(),
                &Itimerspec {
                    it_interval: zero,
                    it_value: value,
                },
            )?;
            self.armed = Some(at);
        }
        loop {
            let mut guard = std::task::ready!(self.fd.poll_read_ready(cx))?;
            let mut expirations = [0u8; 8];
            match rustix::io::read(self.fd.get_ref(), &mut expirations) {
                Ok(_) => {
                    self.armed = None;
                    return Poll::Ready(Ok(()));
                }
                Err(rustix::io::Errno::AGAIN) => guard.clear_ready(),
                Err(e) => return Poll::Ready(Err(e.into())),
            }
        }
    }
}

/// Which poll is driving the link (the others are woken if they can now go on).
#[derive(Clone, Copy, PartialEq, Eq)]
enum Side {
    Read,
    Write,
}

/// A connection's byte stream with both directions shaped; see the module.
///
/// Driven by whichever of its polls runs (each moves both directions on), so it expects
/// to be polled from one task, as hyper's connections are; a wake-up is set for the next
/// instant anything can move.
pub struct Emulated<S> {
    io: S,
    /// Written here, on the way to `io`.
    outbound: DelayLine,
    /// Read from `io`, on the way to the reader.
    inbound: DelayLine,
    scratch: Box<[u8]>,
    eof: bool,
    read_error: Option<io::Error>,
    write_error: Option<io::Error>,
    /// A write was refused for want of space (wake the writer when there is some).
    write_waiting: bool,
    /// Made on first need (inside a runtime).
    timer: Option<Timer>,
}

impl<S> Emulated<S> {
    /// `io`, shaped as `link` says in both directions.
    pub fn new(io: S, link: LinkEmulation) -> Emulated<S> {
        let now = Instant::now();
        Emulated {
            io,
            outbound: DelayLine::new(&link, now),
            inbound: DelayLine::new(&link, now),
            scratch: vec![0; READ_CHUNK].into_boxed_slice(),
            eof: false,
            read_error: None,
            write_error: None,
            write_waiting: false,
            timer: None,
        }
    }

    /// The wrapped stream.
    pub fn get_ref(&self) -> &S {
        &self.io
    }
}

impl<S: AsyncRead + AsyncWrite + Unpin> Emulated<S> {
    /// Move both directions on as far as they can go now, and set the timer for the next
    /// instant anything can move. Errors of the socket are kept for the poll they concern.
    fn pump(&mut self, cx: &mut Context<'_>, side: Side) -> io::Result<()> {
        loop {
            let now = Instant::now();
            // Whatever has arrived enters the inbound line now.
            while !self.eof && self.read_error.is_none() && self.inbound.space() > 0 {
                let want = self.inbound.space().min(self.scratch.len());
                let mut buf = ReadBuf::new(&mut self.scratch[..want]);
                match Pin::new(&mut self.io).poll_read(cx, &mut buf) {
                    Poll::Ready(Ok(())) if buf.filled().is_empty() => self.eof = true,
                    Poll::Ready(Ok(())) => {
                        let n = buf.filled().len();
                        let taken = self.inbound.push(now, &self.scratch[..n]);
                        debug_assert_eq!(taken, n);
                    }
                    Poll::Ready(Err(e)) => self.read_error = Some(e),
                    Poll::Pending => break,
                }
            }
            // Whatever is due leaves on the outbound line.
            let mut freed = false;
            let outbound_at = loop {
                if self.write_error.is_some() {
                    break None;
                }
                match self.outbound.next(now) {
                    Next::Empty => break None,
                    Next::At(at) => break Some(at),
                    Next::Now(bytes) => match Pin::new(&mut self.io).poll_write(cx, bytes) {
                        Poll::Ready(Ok(0)) => {
                            self.write_error = Some(io::ErrorKind::WriteZero.into());
                        }
                        Poll::Ready(Ok(n)) => {
                            self.outbound.consume(n);
                            freed = true;
                        }
                        Poll::Ready(Err(e)) => self.write_error = Some(e),
                        // The socket wakes us when it takes more.
                        Poll::Pending => break None,
                    },
                }
            };
            if freed && self.write_waiting && side != Side::Write {
                self.write_waiting = false;
                cx.waker().wake_by_ref();
            }
            let inbound_at = match self.inbound.next(now) {
                Next::Empty => None,
                Next::At(at) => Some(at),
                Next::Now(_) => {
                    // The reader can go on now: if this is not its poll, have it polled.
                    if side != Side::Read {
                        cx.waker().wake_by_ref();
                    }
                    None
                }
            };
            let Some(at) = [outbound_at, inbound_at].into_iter().flatten().min() else {
                return Ok(());
            };
            let timer = match &mut self.timer {
                Some(t) => t,
                None => self.timer.insert(Timer::new()?),
            };
            match timer.poll_at(cx, at)? {
                // The instant has passed while we worked: go round again.
                Poll::Ready(()) => continue,
                Poll::Pending => return Ok(()),
            }
        }
    }
}

impl<S: AsyncRead + AsyncWrite + Unpin> AsyncRead for Emulated<S> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = &mut *self;
        this.pump(cx, Side::Read)?;
        if let Next::Now(bytes) = this.inbound.next(Instant::now()) {
            let n = bytes.len().min(buf.remaining());
            buf.put_slice(&bytes[..n]);
            this.inbound.consume(n);
            return Poll::Ready(Ok(()));
        }
        if this.inbound.chunks.is_empty() {
            if let Some(e) = this.read_error.take() {
                return Poll::Ready(Err(e));
            }
            if this.eof {
                return Poll::Ready(Ok(()));
            }
        }
        Poll::Pending
    }
}

impl<S: AsyncRead + AsyncWrite + Unpin> AsyncWrite for Emulated<S> {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        let this = &mut *self;
        if let Some(e) = this.write_error.take() {
            return Poll::Ready(Err(e));
        }
        let mut n = this.outbound.push(Instant::now(), buf);
        this.pump(cx, Side::Write)?;
        if n == 0 && !buf.is_empty() {
            // The line was full: take what the pump let out.
            n = this.outbound.push(Instant::now(), buf);
            if n == 0 {
                this.write_waiting = true;
                return Poll::Pending;
            }
            this.pump(cx, Side::Write)?;
        }
        Poll::Ready(Ok(n))
    }

    /// Ready once the bytes are in the delay line (as a socket's flush is once they are
    /// in the kernel's buffer); they leave when due.
    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let this = &mut *self;
        this.pump(cx, Side::Write)?;
        if let Some(e) = this.write_error.take() {
            return Poll::Ready(Err(e));
        }
        Pin::new(&mut this.io).poll_flush(cx)
    }

    /// Waits for the delay line to empty, then shuts the stream down.
    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let this = &mut *self;
        this.pump(cx, Side::Write)?;
        if let Some(e) = this.write_error.take() {
            return Poll::Ready(Err(e));
        }
        if !this.outbound.chunks.is_empty() {
            return Poll::Pending;
        }
        Pin::new(&mut this.io).poll_shutdown(cx)
    }
}

/// A connection's stream, shaped or not: no emulation costs one branch per call.
pub enum MaybeEmulated<S> {
    Direct(S),
    Emulated(Box<Emulated<S>>),
}

impl<S> MaybeEmulated<S> {
    /// `io`, shaped when `link` is given.
    pub fn new(io: S, link: Option<LinkEmulation>) -> MaybeEmulated<S> {
        match link {
            None => MaybeEmulated::Direct(io),
            Some(link) => MaybeEmulated::Emulated(Box::new(Emulated::new(io, link))),
        }
    }

    /// The wrapped stream.
    pub fn get_ref(&self) -> &S {
        match self {
            MaybeEmulated::Direct(io) => io,
            MaybeEmulated::Emulated(e) => e.get_ref(),
        }
    }
}

impl<S: AsyncRead + AsyncWrite + Unpin> AsyncRead for MaybeEmulated<S> {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        match self.get_mut() {
            MaybeEmulated::Direct(io) => Pin::new(io).poll_read(cx, buf),
            MaybeEmulated::Emulated(e) => Pin::new(e.as_mut()).poll_read(cx, buf),
        }
    }
}

impl<S: AsyncRead + AsyncWrite + Unpin> AsyncWrite for MaybeEmulated<S> {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        match self.get_mut() {
            MaybeEmulated::Direct(io) => Pin::new(io).poll_write(cx, buf),
            MaybeEmulated::Emulated(e) => Pin::new(e.as_mut()).poll_write(cx, buf),
        }
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match self.get_mut() {
            MaybeEmulated::Direct(io) => Pin::new(io).poll_flush(cx),
            MaybeEmulated::Emulated(e) => Pin::new(e.as_mut()).poll_flush(cx),
        }
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match self.get_mut() {
            MaybeEmulated::Direct(io) => Pin::new(io).poll_shutdown(cx),
            MaybeEmulated::Emulated(e) => Pin::new(e.as_mut()).poll_shutdown(cx),
        }
    }

    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        match self.get_mut() {
            MaybeEmulated::Direct(io) => Pin::new(io).poll_write_vectored(cx, bufs),
            MaybeEmulated::Emulated(e) => Pin::new(e.as_mut()).poll_write_vectored(cx, bufs),
        }
    }

    fn is_write_vectored(&self) -> bool {
        match self {
            MaybeEmulated::Direct(io) => io.is_write_vectored(),
            MaybeEmulated::Emulated(e) => e.is_write_vectored(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::{AsyncReadExt, AsyncWriteExt, DuplexStream};

    fn link(spec: &str) -> LinkEmulation {
        spec.parse().expect("a valid spec")
    }

    /// A connection whose first end is shaped as `spec` says.
    fn pair(spec: &str) -> (Emulated<DuplexStream>, DuplexStream) {
        let (a, b) = tokio::io::duplex(64 * 1024);
        (Emulated::new(a, link(spec)), b)
    }

    /// `n` bytes that are not all alike (so a reordering would show).
    fn pattern(n: usize, seed: u8) -> Vec<u8> {
        (0..n)
            .map(|i| (i as u32).wrapping_mul(2_654_435_761).to_le_bytes()[1] ^ seed)
            .collect()
    }

    #[test]
    fn specs_parse_in_their_units() {
        assert_eq!(
            link("bandwidth=1gbit,latency=100us"),
            LinkEmulation {
                bandwidth_bits_per_s: Some(1_000_000_000),
                latency: Duration::from_micros(100),
            }
        );
        assert_eq!(
            link(" latency = 20µs , bandwidth = 2.5Gbit "),
            LinkEmulation {
                bandwidth_bits_per_s: Some(2_500_000_000),
                latency: Duration::from_micros(20),
            }
        );
        assert_eq!(link("bandwidth=10mbit").latency, Duration::ZERO);
        assert_eq!(link("latency=1.5ms").bandwidth_bits_per_s, None);
        assert_eq!(link("latency=2s").latency, Duration::from_secs(2));
        assert_eq!(link("bandwidth=64kbit").bandwidth_bits_per_s, Some(64_000));
    }

    #[test]
    fn a_spec_prints_back_as_itself() {
        for spec in [
            "bandwidth=1gbit,latency=100us",
            "bandwidth=10gbit,latency=20us",
            "latency=7ns",
            "bandwidth=1mbit",
            "bandwidth=1234567bit,latency=1500us",
            "latency=3s",
        ] {
            let l = link(spec);
            assert_eq!(
                l.to_string(),
                spec.replace("bandwidth=1mbit", "bandwidth=1mbit,latency=0s")
            );
            assert_eq!(link(&l.to_string()), l, "{spec} -> {l}");
        }
    }

    #[test]
    fn bad_specs_name_the_key_or_value() {
        let err = |s: &str| s.parse::<LinkEmulation>().expect_err(s);
        assert_eq!(err(""), LinkSpecError::Empty);
        assert_eq!(err(" , "), LinkSpecError::Empty);
        assert_eq!(err("fast"), LinkSpecError::NotKeyValue("fast".into()));
        assert_eq!(
            err("jitter=1ms"),
            LinkSpecError::UnknownKey("jitter".into())
        );
        assert_eq!(
            err("latency=1ms,latency=2ms"),
            LinkSpecError::Repeated("latency".into())
        );
        for (spec, value, says) in [
            ("bandwidth=1g", "1g", "needs a unit"),
            ("bandwidth=1gbps", "1gbps", "needs a unit"),
            ("bandwidth=abcbit", "abcbit", "`abc` is not a number"),
            ("bandwidth=0bit", "0bit", "at least 8bit"),
            ("bandwidth=-1gbit", "-1gbit", "not negative"),
            ("bandwidth=infgbit", "infgbit", "finite"),
        ] {
            let e = err(spec);
            assert!(
                matches!(&e, LinkSpecError::Bandwidth { value: v, why } if v == value && why.contains(says)),
                "{spec}: {e}"
            );
            assert!(e.to_string().starts_with(&format!("bandwidth `{value}`")));
        }
        for (spec, value, says) in [
            ("latency=100", "100", "needs a unit"),
            ("latency=1h", "1h", "needs a unit"),
            ("latency=xms", "xms", "not a number"),
            ("latency=11s", "11s", "at most 10s"),
        ] {
            let e = err(spec);
            assert!(
                matches!(&e, LinkSpecError::Latency { value: v, why } if v == value && why.contains(says)),
                "{spec}: {e}"
            );
        }
    }

    #[test]
    fn buckets_and_lines_are_sized_from_the_link() {
        assert_eq!(link("bandwidth=1gbit").burst_bytes(), MIN_BURST_BYTES);
        // 10 Gbit/s carries 62,500 bytes in 50 µs.
        assert_eq!(link("bandwidth=10gbit").burst_bytes(), 62_500);
        assert_eq!(link("latency=1ms").queue_bytes(), MIN_QUEUE_BYTES);
        // 10 Gbit/s for 10 ms is 12.5 MB in flight.
        assert_eq!(
            link("bandwidth=10gbit,latency=10ms").queue_bytes(),
            25_000_000
        );
    }

    #[test]
    fn no_emulation_leaves_the_stream_as_it_is() {
        let (a, _b) = tokio::io::duplex(16);
        assert!(matches!(
            MaybeEmulated::new(a, None),
            MaybeEmulated::Direct(_)
        ));
    }

    /// Write `data` into `w` in pieces of `piece` bytes, then shut it down (which waits
    /// for a shaped stream's line to empty).
    async fn send_all(mut w: impl AsyncWrite + Unpin, data: &[u8], piece: usize) {
        for p in data.chunks(piece) {
            w.write_all(p).await.expect("write");
        }
        w.shutdown().await.expect("shutdown");
    }

    /// Everything `r` yields until its end, and when the end came.
    async fn receive_all(mut r: impl AsyncRead + Unpin) -> (Instant, Vec<u8>) {
        let mut got = Vec::new();
        r.read_to_end(&mut got).await.expect("read");
        (Instant::now(), got)
    }

    /// Megabytes both ways at once, in writes of odd sizes, arrive whole and in order.
    #[tokio::test]
    async fn data_arrives_intact_and_in_order_both_ways() {
        let (shaped, peer) = pair("bandwidth=400mbit,latency=200us");
        let (out, back) = (pattern(3 << 20, 1), pattern(2 << 20, 7));
        let (shaped_r, shaped_w) = tokio::io::split(shaped);
        let (peer_r, peer_w) = tokio::io::split(peer);
        let (_, (_, at_peer), _, (_, at_shaped)) = tokio::join!(
            send_all(shaped_w, &out, 1_000 + 37),
            receive_all(peer_r),
            send_all(peer_w, &back, 5_000 - 3),
            receive_all(shaped_r),
        );
        assert!(at_peer == out, "the outbound bytes arrive as written");
        assert!(at_shaped == back, "the inbound bytes arrive as written");
    }

    /// Bytes written into the shaped end reach the peer no earlier than the latency after.
    #[tokio::test]
    async fn outbound_bytes_wait_out_the_latency() {
        let latency = Duration::from_millis(30);
        let (mut shaped, mut peer) = pair("latency=30ms");
        for round in 0..3u8 {
            let msg = pattern(100, round);
            let t0 = Instant::now();
            let mut got = vec![0; msg.len()];
            let write = async {
                shaped.write_all(&msg).await.expect("write");
                shaped.flush().await.expect("flush");
                // Keep the connection polled until the bytes are out (as hyper does).
                let mut none = [0u8; 1];
                tokio::select! {
                    _ = shaped.read(&mut none) => panic!("nothing comes back"),
                    _ = tokio::time::sleep(latency * 3) => {}
                }
            };
            let read = async {
                peer.read_exact(&mut got).await.expect("read");
                Instant::now()
            };
            let (_, arrived) = tokio::join!(write, read);
            assert!(arrived - t0 >= latency, "round {round}: {:?}", arrived - t0);
            assert_eq!(got, msg);
        }
    }

    /// Bytes the peer sends are handed to the shaped end's reader no earlier than the
    /// latency after they were sent.
    #[tokio::test]
    async fn inbound_bytes_wait_out_the_latency() {
        let latency = Duration::from_millis(30);
        let (mut shaped, mut peer) = pair("latency=30ms");
        for round in 0..3u8 {
            let msg = pattern(1000, round);
            let t0 = Instant::now();
            peer.write_all(&msg).await.expect("write");
            let mut got = vec![0; msg.len()];
            shaped.read_exact(&mut got).await.expect("read");
            assert!(t0.elapsed() >= latency, "round {round}: {:?}", t0.elapsed());
            assert_eq!(got, msg);
        }
    }

    /// At 1 Mbit/s, 64 KiB take at least (64 KiB - one burst) / bandwidth each way.
    #[tokio::test]
    async fn the_bandwidth_bounds_both_directions() {
        const SIZE: usize = 64 * 1024;
        let l = link("bandwidth=1mbit");
        let least =
            Duration::from_secs_f64((SIZE as u64 - l.burst_bytes()) as f64 * 8.0 / 1_000_000.0);
        let (mut shaped_out, mut peer_in) = pair("bandwidth=1mbit");
        let (mut shaped_in, mut peer_out) = pair("bandwidth=1mbit");
        let (out_msg, in_msg) = (pattern(SIZE, 3), pattern(SIZE, 4));
        let t0 = Instant::now();
        let (_, (out_at, out_got), _, (in_at, in_got)) = tokio::join!(
            send_all(&mut shaped_out, &out_msg, SIZE),
            receive_all(&mut peer_in),
            send_all(&mut peer_out, &in_msg, SIZE),
            receive_all(&mut shaped_in),
        );
        assert!(out_got == out_msg && in_got == in_msg);
        let (out, inn) = (out_at - t0, in_at - t0);
        assert!(out >= least, "outbound took {out:?}, less than {least:?}");
        assert!(inn >= least, "inbound took {inn:?}, less than {least:?}");
    }
}
