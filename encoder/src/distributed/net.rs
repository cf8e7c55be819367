//! The cluster's TCP connections, made here and handed to timely ([`connect_peers`]): each one
//! starts with a mutual challenge-response on a shared secret ([`ClusterSecret`]), and each
//! peer's stream ([`PeerStream`]) records the process it leads to when it fails
//! ([`LostPeer`]), so that a survivor can name the process that died.
//!
//! # Handshake
//!
//! As in timely's own set-up, each pair of processes has one connection, opened by the higher
//! index `c` to the lower `a`. Before timely sees it:
//!
//! ```text
//!   c → a  hello      MAGIC ‖ c ‖ a ‖ P ‖ nonce_c                 (u32 big-endian, 32-byte nonces)
//!   a → c  challenge  MAGIC ‖ a ‖ c ‖ P ‖ nonce_a ‖ tag_a          tag_a = HMAC-SHA256(secret, "acceptor"  ‖ T)
//!   c → a  answer     tag_c                                        tag_c = HMAC-SHA256(secret, "connector" ‖ T)
//!   a → c  accepted   0x01                                         T = nonce_c ‖ nonce_a ‖ c ‖ a ‖ P
//! ```
//!
//! Each side checks the other's tag in constant time (`ring::hmac::verify`) over nonces it
//! did not choose alone, so a recorded handshake cannot be replayed and a peer without the
//! secret cannot answer. A peer that fails (wrong secret, garbage, another host list, silence
//! past [`HANDSHAKE_TIMEOUT`]) is refused: its connection is closed, the refusal is logged
//! with its address, and the process keeps waiting for the right peer until the deadline.
//!
//! Only the start of a connection is authenticated: the job's traffic after the handshake is
//! neither encrypted nor integrity-protected (run it on a private network or a VPN).

use std::io::{self, Read, Write};
use std::net::{IpAddr, Shutdown, SocketAddr, TcpListener, TcpStream, ToSocketAddrs};
use std::path::Path;
use std::sync::{Arc, OnceLock, mpsc};
use std::time::{Duration, Instant};

use ring::hmac;
use ring::rand::{SecureRandom, SystemRandom};
use slag_common::{Error, Result};
use timely::communication::allocator::zero_copy::stream::Stream;

/// First bytes of a hello and a challenge: the protocol and its version.
const MAGIC: &[u8; 8] = b"SLAGCL01";
/// Bytes of each side's nonce.
const NONCE_BYTES: usize = 32;
/// Bytes of an HMAC-SHA256 tag.
const TAG_BYTES: usize = 32;
/// Bytes of a hello: magic, three u32, the connector's nonce.
const HELLO_BYTES: usize = MAGIC.len() + 12 + NONCE_BYTES;
/// Bytes of a challenge: a hello's fields from the acceptor, then its tag.
const CHALLENGE_BYTES: usize = HELLO_BYTES + TAG_BYTES;
/// The acceptor's last byte: the connection is accepted.
const ACCEPTED: u8 = 1;
/// Fewest bytes a cluster secret may have: a captured handshake allows an offline guess of the
/// secret, so it must be long and random, not a word.
pub const MIN_SECRET_BYTES: usize = 16;
/// Longest wait for each step of a handshake (a silent peer is refused after it).
pub const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);
/// Most connections checked at once by one process: past it a new connection is closed at once,
/// so a flood of connections costs a bounded number of threads (each freed within the handshake
/// timeout) and the real peer, which retries, gets in once it ebbs.
const MAX_PENDING_HANDSHAKES: usize = 32;
/// Pause between two attempts to reach a peer.
const RETRY: Duration = Duration::from_millis(500);
/// The HMAC key of a cluster run without a secret (every address on loopback): the handshake
/// still checks the protocol and the process indices, but proves nothing.
const NO_SECRET_KEY: &[u8] = b"slag encode-cluster without a secret: loopback only";

/// The shared secret every process of a cluster holds; its connections start with an HMAC
/// challenge on it. Its bytes never appear in `Debug` or in messages.
#[derive(Clone)]
pub struct ClusterSecret {
    key: hmac::Key,
}

impl std::fmt::Debug for ClusterSecret {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("ClusterSecret(..)")
    }
}

impl ClusterSecret {
    /// The secret `bytes` (at least [`MIN_SECRET_BYTES`]).
    ///
    /// Errors: [`Error::Param`] `cluster_secret` when it is shorter.
    pub fn new(bytes: &[u8]) -> Result<Self> {
        if bytes.len() < MIN_SECRET_BYTES {
            return Err(Error::param(
                "cluster_secret",
                format!("{} bytes", bytes.len()),
                format!("at least {MIN_SECRET_BYTES} random bytes"),
            ));
        }
        Ok(ClusterSecret {
            key: hmac::Key::new(hmac::HMAC_SHA256, bytes),
        })
    }

    /// Reads the secret from `path`: its first line, trimmed, at least [`MIN_SECRET_BYTES`]
    /// long (`head -c 32 /dev/urandom | base64 > FILE`), in a file only its owner may read or
    /// write (`chmod 600 FILE`). Every process of the cluster reads the same secret.
    ///
    /// Errors: [`Error::Param`] `cluster_secret` naming the file's mode when users other than
    /// its owner may read or write it; [`Error::Io`] when it cannot be read; [`Error::Format`]
    /// when it is empty or shorter than [`MIN_SECRET_BYTES`].
    pub fn read(path: &Path) -> Result<Self> {
        if let Some(mode) = slag_common::shards::signature::readable_by_others(path) {
            return Err(Error::param(
                "cluster_secret",
                format!("{} (mode {mode:o})", path.display()),
                "a secret file only its owner may read: chmod 600 it",
            ));
        }
        let text = slag_common::auth::read_token_file(path)?;
        ClusterSecret::new(text.as_bytes()).map_err(|_| {
            Error::format(
                path,
                format!(
                    "the secret is {} bytes; write at least {MIN_SECRET_BYTES} random ones \
                     (head -c 32 /dev/urandom | base64 > FILE) and copy the same file to every \
                     process",
                    text.len()
                ),
            )
        })
    }
}

/// Whether every `host:port` in `addresses` is on loopback (`127.0.0.0/8`, `::1`, `localhost`):
/// then only users of this machine can reach the cluster's ports. Names are not resolved.
pub fn all_loopback(addresses: &[String]) -> bool {
    addresses.iter().all(|a| {
        let host = a.rsplit_once(':').map_or(a.as_str(), |(h, _)| h);
        let host = host.trim_start_matches('[').trim_end_matches(']');
        host.eq_ignore_ascii_case("localhost")
            || host
                .parse::<IpAddr>()
                .is_ok_and(|ip| ip.to_canonical().is_loopback())
    })
}

/// The HMAC key of the handshake: the secret's, or [`NO_SECRET_KEY`]'s without one.
fn handshake_key(secret: Option<&ClusterSecret>) -> hmac::Key {
    match secret {
        Some(s) => s.key.clone(),
        None => hmac::Key::new(hmac::HMAC_SHA256, NO_SECRET_KEY),
    }
}

/// The process whose connection failed first, set once by a [`PeerStream`] (its index in the
/// host list); shared by every peer stream of a process and read by its panic hook.
#[derive(Debug, Default)]
pub struct LostPeer(OnceLock<usize>);

impl LostPeer {
    /// The index of the first process whose connection failed or closed, if any did.
    pub fn get(&self) -> Option<usize> {
        self.0.get().copied()
    }

    fn record(&self, process: usize) {
        let _ = self.0.set(process);
    }
}

/// The connection to one peer process, as timely reads and writes it: a [`TcpStream`] that
/// records its peer's index in [`LostPeer`] when a read or write fails or the peer closes it
/// (a read of 0 bytes), before returning the result unchanged.
///
/// timely also reads 0 bytes once after a peer's clean shutdown; that is recorded too, so
/// [`LostPeer`] is to be read only once a connection has failed (timely panicked).
pub struct PeerStream {
    stream: TcpStream,
    process: usize,
    lost: Arc<LostPeer>,
}

impl PeerStream {
    /// `result` unchanged, after recording this peer as lost when it is a failure
    /// (`WouldBlock` and `Interrupted` are not).
    fn watch<T>(&self, result: io::Result<T>) -> io::Result<T> {
        if let Err(e) = &result
            && !matches!(
                e.kind(),
                io::ErrorKind::WouldBlock | io::ErrorKind::Interrupted
            )
        {
            self.lost.record(self.process);
        }
        result
    }

    /// The index of the peer process in the host list.
    pub fn process(&self) -> usize {
        self.process
    }
}

impl Read for PeerStream {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        let r = self.stream.read(buf);
        if matches!(r, Ok(0)) && !buf.is_empty() {
            self.lost.record(self.process);
        }
        self.watch(r)
    }
}

impl Write for PeerStream {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        let r = self.stream.write(buf);
        if matches!(r, Ok(0)) && !buf.is_empty() {
            self.lost.record(self.process);
        }
        self.watch(r)
    }

    fn flush(&mut self) -> io::Result<()> {
        let r = self.stream.flush();
        self.watch(r)
    }
}

impl Stream for PeerStream {
    fn try_clone(&self) -> io::Result<Self> {
        Ok(PeerStream {
            stream: self.stream.try_clone()?,
            process: self.process,
            lost: Arc::clone(&self.lost),
        })
    }

    fn set_nonblocking(&self, nonblocking: bool) -> io::Result<()> {
        self.stream.set_nonblocking(nonblocking)
    }

    fn shutdown(&self, how: Shutdown) -> io::Result<()> {
        self.stream.shutdown(how)
    }
}

/// Where this process sits and how it proves itself: what both sides of a handshake need.
struct Membership<'a> {
    /// `host:port` of every process.
    addresses: &'a [String],
    /// This process's index.
    me: usize,
    /// The handshake's HMAC key.
    key: hmac::Key,
    /// Longest wait for each handshake step.
    step_timeout: Duration,
    /// When to stop waiting for peers.
    deadline: Instant,
}

/// Connects this process (`me`, listening on `addresses[me]`) to every other process of the
/// cluster, each connection authenticated with `secret` (or the loopback key without one; see
/// the module doc), waiting for them until `deadline`. Returns one stream per process in host
/// list order, `None` at `me`: the layout timely's
/// `initialize_networking_from_sockets` expects. Every stream records a failure in `lost`.
///
/// Refused peers (wrong secret, garbage, another host list) are logged (`warn`, with their
/// address) and waited past; each handshake step waits at most `step_timeout`.
///
/// Errors: [`Error::Network`] on `addresses[me]` when it cannot be listened on, or when some
/// processes had not connected (with the right secret) by `deadline`, naming them.
pub fn connect_peers(
    addresses: &[String],
    me: usize,
    secret: Option<&ClusterSecret>,
    step_timeout: Duration,
    deadline: Instant,
    lost: &Arc<LostPeer>,
) -> Result<Vec<Option<PeerStream>>> {
    let here = &addresses[me];
    let listener = TcpListener::bind(here).map_err(|e| {
        Error::network(
            here.clone(),
            format!(
                "encode-cluster process {me}: cannot listen on {here}: {e}; check that the \
                 port is free and that --process is this machine's line of the host file"
            ),
        )
    })?;
    let m = Membership {
        addresses,
        me,
        key: handshake_key(secret),
        step_timeout,
        deadline,
    };
    let (lower, higher) = std::thread::scope(|s| {
        let connector = s.spawn(|| connect_lower(&m));
        let higher = accept_higher(&listener, &m);
        (connector.join(), higher)
    });
    let lower = lower.map_err(|_| Error::internal("the connecting thread panicked"))?;
    let missing: Vec<usize> = (0..addresses.len())
        .filter(|&p| p != me)
        .filter(|&p| {
            let slot = if p < me {
                &lower[p]
            } else {
                &higher[p - me - 1]
            };
            slot.is_none()
        })
        .collect();
    if !missing.is_empty() {
        return Err(not_connected(&m, &missing));
    }
    let wrap = |(process, stream): (usize, Option<TcpStream>)| {
        stream.map(|stream| PeerStream {
            stream,
            process,
            lost: Arc::clone(lost),
        })
    };
    let streams = lower
        .into_iter()
        .chain(std::iter::once(None))
        .chain(higher)
        .enumerate()
        .map(wrap)
        .collect();
    Ok(streams)
}

/// The error of processes `missing` that had not connected by the deadline.
fn not_connected(m: &Membership<'_>, missing: &[usize]) -> Error {
    let names: Vec<String> = missing
        .iter()
        .map(|&p| format!("{p} ({})", m.addresses[p]))
        .collect();
    Error::network(
        m.addresses[m.me].clone(),
        format!(
            "encode-cluster process {}: process(es) {} did not connect with the cluster secret \
             in time; start every process with the same host file and the same secret file, \
             and check the addresses and firewalls",
            m.me,
            names.join(", ")
        ),
    )
}

/// Connects to every process below this one, retrying each until it answers the handshake or
/// the deadline passes; the streams in process order (`None` where the deadline passed).
fn connect_lower(m: &Membership<'_>) -> Vec<Option<TcpStream>> {
    let mut streams = Vec::with_capacity(m.me);
    for a in 0..m.me {
        let address = &m.addresses[a];
        let stream = loop {
            let remaining = m.deadline.saturating_duration_since(Instant::now());
            if remaining.is_zero() {
                break None;
            }
            match reach(address, remaining.min(m.step_timeout)) {
                Err(e) => tracing::debug!(peer = %address, "process {a} not reachable yet: {e}"),
                Ok(stream) => match connect_handshake(stream, m, a) {
                    Ok(s) => break Some(s),
                    Err(reason) => tracing::warn!(
                        peer = %address,
                        "encode-cluster process {}: refused the connection to process {a} at \
                         {address}: {reason}",
                        m.me
                    ),
                },
            }
            std::thread::sleep(RETRY.min(m.deadline.saturating_duration_since(Instant::now())));
        };
        streams.push(stream);
    }
    streams
}

/// A TCP connection to `address` (its first address that answers within `timeout`).
fn reach(address: &str, timeout: Duration) -> io::Result<TcpStream> {
    let mut last = io::Error::new(io::ErrorKind::NotFound, "the name resolves to no address");
    for a in address.to_socket_addrs()? {
        match TcpStream::connect_timeout(&a, timeout) {
            Ok(s) => return Ok(s),
            Err(e) => last = e,
        }
    }
    Err(last)
}

/// Accepts the processes above this one on `listener` until each has passed the handshake or
/// the deadline passes; the streams in process order (`None` where the deadline passed). Each
/// accepted connection is checked on its own thread, so a silent peer delays no other; at most
/// [`MAX_PENDING_HANDSHAKES`] at once.
fn accept_higher(listener: &TcpListener, m: &Membership<'_>) -> Vec<Option<TcpStream>> {
    let processes = m.addresses.len();
    let mut streams: Vec<Option<TcpStream>> = (m.me + 1..processes).map(|_| None).collect();
    if streams.is_empty() {
        return streams;
    }
    if let Err(e) = listener.set_nonblocking(true) {
        tracing::warn!("cannot poll the cluster's listening socket: {e}");
        return streams;
    }
    let (done, results) = mpsc::channel();
    // Handshake threads started and not yet reported: each reports exactly once.
    let mut pending = 0usize;
    while streams.iter().any(Option::is_none) && Instant::now() < m.deadline {
        // The connections waiting now (a bounded number per pass, so that a flood cannot keep
        // the results below from being read), each checked on its own thread or closed at once.
        for _ in 0..2 * MAX_PENDING_HANDSHAKES {
            match listener.accept() {
                Ok((_, peer)) if pending >= MAX_PENDING_HANDSHAKES => tracing::warn!(
                    peer = %peer,
                    "encode-cluster process {}: refused a connection from {peer}: \
                     {MAX_PENDING_HANDSHAKES} others are being checked",
                    m.me
                ),
                Ok((stream, peer)) => {
                    pending += usize::from(spawn_accept_handshake(stream, peer, m, done.clone()));
                }
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => break,
                Err(e) => {
                    tracing::debug!("accepting a cluster connection failed: {e}");
                    break;
                }
            }
        }
        let Ok((peer, outcome)) = results.recv_timeout(Duration::from_millis(20)) else {
            continue;
        };
        pending -= 1;
        match outcome {
            Ok((c, stream)) => {
                if streams[c - m.me - 1].replace(stream).is_some() {
                    tracing::warn!(
                        peer = %peer,
                        "process {c} connected again; the new connection replaces the old"
                    );
                }
            }
            Err(reason) => tracing::warn!(
                peer = %peer,
                "encode-cluster process {}: refused a connection from {peer}: {reason}",
                m.me
            ),
        }
    }
    streams
}

/// What an accepting handshake thread reports: the peer's address, then its process index and
/// stream or the reason it was refused.
type AcceptOutcome = (SocketAddr, std::result::Result<(usize, TcpStream), String>);

/// Runs [`accept_handshake`] on `stream` on a new thread, reporting to `done`; whether the
/// thread started (else the connection is closed, logged).
fn spawn_accept_handshake(
    stream: TcpStream,
    peer: SocketAddr,
    m: &Membership<'_>,
    done: mpsc::Sender<AcceptOutcome>,
) -> bool {
    let (me, processes, key, step) = (m.me, m.addresses.len(), m.key.clone(), m.step_timeout);
    let spawned = std::thread::Builder::new()
        .name("slag:cluster-handshake".into())
        .spawn(move || {
            let outcome = accept_handshake(stream, me, processes, &key, step);
            let _ = done.send((peer, outcome));
        });
    if let Err(e) = &spawned {
        tracing::warn!(peer = %peer, "refused a connection: no thread to check it on: {e}");
    }
    spawned.is_ok()
}

/// The fields a hello and a challenge share: sender, receiver, processes, nonce.
struct Greeting {
    from: usize,
    to: usize,
    processes: usize,
    nonce: [u8; NONCE_BYTES],
}

impl Greeting {
    fn encode(&self) -> [u8; HELLO_BYTES] {
        let mut b = [0u8; HELLO_BYTES];
        b[..8].copy_from_slice(MAGIC);
        for (i, v) in [self.from, self.to, self.processes].into_iter().enumerate() {
            b[8 + 4 * i..12 + 4 * i].copy_from_slice(&(v as u32).to_be_bytes());
        }
        b[20..].copy_from_slice(&self.nonce);
        b
    }

    /// The greeting in `b` (at least [`HELLO_BYTES`]).
    ///
    /// Errors: the reason, when `b` does not start with [`MAGIC`].
    fn decode(b: &[u8]) -> std::result::Result<Self, String> {
        if &b[..8] != MAGIC {
            return Err("not a slag encode-cluster peer (no cluster greeting)".into());
        }
        let field = |i: usize| {
            let mut v = [0u8; 4];
            v.copy_from_slice(&b[8 + 4 * i..12 + 4 * i]);
            u32::from_be_bytes(v) as usize
        };
        let mut nonce = [0u8; NONCE_BYTES];
        nonce.copy_from_slice(&b[20..HELLO_BYTES]);
        Ok(Greeting {
            from: field(0),
            to: field(1),
            processes: field(2),
            nonce,
        })
    }

    /// Refuses a greeting not from `from` to `to` in a cluster of `processes`.
    fn expect(
        &self,
        from: std::ops::Range<usize>,
        to: usize,
        processes: usize,
    ) -> std::result::Result<(), String> {
        if from.contains(&self.from) && self.to == to && self.processes == processes {
            return Ok(());
        }
        Err(format!(
            "it says it is process {} of {} talking to process {}, but this is process {to} of \
             {processes}: the processes were started with different host files or --process",
            self.from, self.processes, self.to
        ))
    }
}

/// A fresh random nonce.
fn nonce() -> std::result::Result<[u8; NONCE_BYTES], String> {
    let mut n = [0u8; NONCE_BYTES];
    SystemRandom::new()
        .fill(&mut n)
        .map_err(|_| "the system has no random numbers for a nonce".to_string())?;
    Ok(n)
}

/// The bytes a tag signs: `role ‖ nonce_c ‖ nonce_a ‖ c ‖ a ‖ P`.
fn transcript(role: &[u8], hello: &Greeting, challenge: &Greeting) -> Vec<u8> {
    let mut t = Vec::with_capacity(role.len() + 2 * NONCE_BYTES + 12);
    t.extend_from_slice(role);
    t.extend_from_slice(&hello.nonce);
    t.extend_from_slice(&challenge.nonce);
    for v in [hello.from, challenge.from, hello.processes] {
        t.extend_from_slice(&(v as u32).to_be_bytes());
    }
    t
}

const ACCEPTOR: &[u8] = b"slag-cluster acceptor";
const CONNECTOR: &[u8] = b"slag-cluster connector";

/// Sets the handshake's timeouts on `stream` (`None` clears them for timely).
fn set_timeouts(stream: &TcpStream, t: Option<Duration>) -> std::result::Result<(), String> {
    stream
        .set_nonblocking(false)
        .and_then(|()| stream.set_read_timeout(t))
        .and_then(|()| stream.set_write_timeout(t))
        .and_then(|()| stream.set_nodelay(true))
        .map_err(|e| format!("cannot set up the connection: {e}"))
}

/// The reason a handshake read or write of `what` failed.
fn io_reason(what: &str, e: &io::Error) -> String {
    match e.kind() {
        io::ErrorKind::UnexpectedEof => format!("it closed the connection before its {what}"),
        io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut => {
            format!("no {what} within the handshake timeout")
        }
        _ => format!("{what}: {e}"),
    }
}

/// The acceptor's side of the handshake (module doc) with process `me` of `processes` on
/// `stream`: the connecting process's index and the stream, ready for timely.
///
/// Errors: the reason the peer is refused (it sent no hello, another host list, a tag that does
/// not prove the secret, silence past `step`).
fn accept_handshake(
    mut stream: TcpStream,
    me: usize,
    processes: usize,
    key: &hmac::Key,
    step: Duration,
) -> std::result::Result<(usize, TcpStream), String> {
    set_timeouts(&stream, Some(step))?;
    let mut b = [0u8; HELLO_BYTES];
    stream
        .read_exact(&mut b)
        .map_err(|e| io_reason("hello", &e))?;
    let hello = Greeting::decode(&b)?;
    hello.expect(me + 1..processes, me, processes)?;
    let challenge = Greeting {
        from: me,
        to: hello.from,
        processes,
        nonce: nonce()?,
    };
    let tag = hmac::sign(key, &transcript(ACCEPTOR, &hello, &challenge));
    let mut out = challenge.encode().to_vec();
    out.extend_from_slice(tag.as_ref());
    stream
        .write_all(&out)
        .map_err(|e| io_reason("challenge", &e))?;
    let mut answer = [0u8; TAG_BYTES];
    stream.read_exact(&mut answer).map_err(|e| match e.kind() {
        // What a connector does when this process's tag does not prove its secret.
        io::ErrorKind::UnexpectedEof => format!(
            "process {} closed the connection before its answer: it holds another cluster \
             secret (or none)",
            hello.from
        ),
        _ => io_reason("answer", &e),
    })?;
    hmac::verify(key, &transcript(CONNECTOR, &hello, &challenge), &answer).map_err(|_| {
        format!(
            "process {} failed the challenge: it holds another cluster secret (or none)",
            hello.from
        )
    })?;
    stream
        .write_all(&[ACCEPTED])
        .map_err(|e| io_reason("acceptance", &e))?;
    set_timeouts(&stream, None)?;
    Ok((hello.from, stream))
}

/// The connector's side of the handshake (module doc) from process `m.me` to process `a`.
///
/// Errors: the reason the connection is given up (the peer sent no challenge, another host
/// list, a tag that does not prove the secret, it refused this process, silence).
fn connect_handshake(
    mut stream: TcpStream,
    m: &Membership<'_>,
    a: usize,
) -> std::result::Result<TcpStream, String> {
    let processes = m.addresses.len();
    set_timeouts(&stream, Some(m.step_timeout))?;
    let hello = Greeting {
        from: m.me,
        to: a,
        processes,
        nonce: nonce()?,
    };
    stream
        .write_all(&hello.encode())
        .map_err(|e| io_reason("hello", &e))?;
    let mut b = [0u8; CHALLENGE_BYTES];
    stream
        .read_exact(&mut b)
        .map_err(|e| io_reason("challenge", &e))?;
    let challenge = Greeting::decode(&b)?;
    challenge.expect(a..a + 1, m.me, processes)?;
    let tag = &b[HELLO_BYTES..];
    hmac::verify(&m.key, &transcript(ACCEPTOR, &hello, &challenge), tag).map_err(|_| {
        format!("process {a} failed the challenge: it holds another cluster secret (or none)")
    })?;
    let answer = hmac::sign(&m.key, &transcript(CONNECTOR, &hello, &challenge));
    stream
        .write_all(answer.as_ref())
        .map_err(|e| io_reason("answer", &e))?;
    let mut accepted = [0u8; 1];
    stream
        .read_exact(&mut accepted)
        .map_err(|e| io_reason("acceptance", &e))?;
    if accepted[0] != ACCEPTED {
        return Err(format!("process {a} sent no acceptance"));
    }
    set_timeouts(&stream, None)?;
    Ok(stream)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    const STEP: Duration = Duration::from_secs(2);

    fn secret(s: &str) -> ClusterSecret {
        ClusterSecret::new(s.as_bytes()).unwrap()
    }

    /// A connected loopback pair: (connecting end, accepted end).
    fn pair() -> (TcpStream, TcpStream) {
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        let c = TcpStream::connect(l.local_addr().unwrap()).unwrap();
        (c, l.accept().unwrap().0)
    }

    /// Both sides of one handshake between process 1 (connecting, `c_secret`) and process 0
    /// (accepting, `a_secret`) of two, each bounded by `STEP` per step.
    fn handshake(
        c_secret: &ClusterSecret,
        a_secret: &ClusterSecret,
    ) -> (
        std::result::Result<TcpStream, String>,
        std::result::Result<(usize, TcpStream), String>,
    ) {
        let (c, a) = pair();
        let addresses = vec!["127.0.0.1:1".to_string(), "127.0.0.1:2".to_string()];
        let m = Membership {
            addresses: &addresses,
            me: 1,
            key: handshake_key(Some(c_secret)),
            step_timeout: STEP,
            deadline: Instant::now() + STEP,
        };
        let key = handshake_key(Some(a_secret));
        std::thread::scope(|s| {
            let acceptor = s.spawn(|| accept_handshake(a, 0, 2, &key, STEP));
            let connector = connect_handshake(c, &m, 0);
            (connector, acceptor.join().unwrap())
        })
    }

    #[test]
    fn the_right_secret_passes_both_ways_and_leaves_a_clean_stream() {
        let t0 = Instant::now();
        let (c, a) = handshake(&secret("0123456789abcdef"), &secret("0123456789abcdef"));
        let (mut c, (index, mut a)) = (c.unwrap(), a.unwrap());
        assert_eq!(index, 1, "the acceptor learns the connecting process");
        // Nothing of the handshake is left on either stream, and the timeouts are cleared.
        c.write_all(b"timely").unwrap();
        let mut got = [0u8; 6];
        a.read_exact(&mut got).unwrap();
        assert_eq!(&got, b"timely");
        a.write_all(b"back").unwrap();
        let mut got = [0u8; 4];
        c.read_exact(&mut got).unwrap();
        assert_eq!(&got, b"back");
        assert_eq!(a.read_timeout().unwrap(), None);
        assert_eq!(c.read_timeout().unwrap(), None);
        assert!(t0.elapsed() < STEP);
    }

    #[test]
    fn a_wrong_secret_fails_on_both_sides() {
        let (c, a) = handshake(&secret("0123456789abcdef"), &secret("0123456789abcdeX"));
        let c = c.unwrap_err();
        assert!(c.contains("process 0 failed the challenge"), "{c}");
        // The connector gave up before answering: the acceptor sees no valid answer.
        let a = a.unwrap_err();
        assert!(
            a.contains("process 1 closed the connection before its answer"),
            "{a}"
        );
    }

    #[test]
    fn a_connector_that_answers_without_the_secret_is_refused() {
        // A peer that reads the challenge and sends a made-up answer.
        let (mut c, a) = pair();
        let key = handshake_key(Some(&secret("0123456789abcdef")));
        let acceptor = std::thread::spawn(move || accept_handshake(a, 0, 2, &key, STEP));
        let hello = Greeting {
            from: 1,
            to: 0,
            processes: 2,
            nonce: [7; NONCE_BYTES],
        };
        c.write_all(&hello.encode()).unwrap();
        let mut b = [0u8; CHALLENGE_BYTES];
        c.read_exact(&mut b).unwrap();
        c.write_all(&b[HELLO_BYTES..]).unwrap(); // its own tag reflected back
        let e = acceptor.join().unwrap().unwrap_err();
        assert!(e.contains("process 1 failed the challenge"), "{e}");
        // Refused: closed, never accepted.
        let mut rest = Vec::new();
        assert_eq!(c.read_to_end(&mut rest).unwrap_or(0), 0);
    }

    #[test]
    fn garbage_and_silence_are_refused_without_hanging() {
        let key = handshake_key(Some(&secret("0123456789abcdef")));
        // Garbage to an acceptor (an HTTP request, a port scanner).
        let (mut c, a) = pair();
        c.write_all(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n-------------------------")
            .unwrap();
        let e = accept_handshake(a, 0, 2, &key, STEP).unwrap_err();
        assert!(e.contains("not a slag encode-cluster peer"), "{e}");
        // Too few bytes, then closed.
        let (mut c, a) = pair();
        c.write_all(b"SLAG").unwrap();
        drop(c);
        let e = accept_handshake(a, 0, 2, &key, STEP).unwrap_err();
        assert!(e.contains("closed the connection before its hello"), "{e}");
        // Silence: refused after the step timeout, not waited on forever.
        let (_c, a) = pair();
        let t0 = Instant::now();
        let e = accept_handshake(a, 0, 2, &key, Duration::from_millis(300)).unwrap_err();
        assert!(e.contains("no hello within"), "{e}");
        assert!(t0.elapsed() < STEP);
        // Garbage from a server the connector reached.
        let (c, mut a) = pair();
        let server = std::thread::spawn(move || {
            a.write_all(&[0xAB; CHALLENGE_BYTES]).unwrap();
            a
        });
        let addresses = vec!["127.0.0.1:1".to_string(), "127.0.0.1:2".to_string()];
        let m = Membership {
            addresses: &addresses,
            me: 1,
            key,
            step_timeout: STEP,
            deadline: Instant::now() + STEP,
        };
        let e = connect_handshake(c, &m, 0).unwrap_err();
        assert!(e.contains("not a slag encode-cluster peer"), "{e}");
        drop(server.join().unwrap());
    }

    #[test]
    fn a_peer_with_another_host_list_is_refused() {
        let key = handshake_key(None);
        let (mut c, a) = pair();
        let hello = Greeting {
            from: 1,
            to: 0,
            processes: 3,
            nonce: [1; NONCE_BYTES],
        };
        c.write_all(&hello.encode()).unwrap();
        let e = accept_handshake(a, 0, 2, &key, STEP).unwrap_err();
        assert!(e.contains("different host files"), "{e}");
    }

    /// Free loopback addresses for `n` processes.
    fn loopback_hosts(n: usize) -> Vec<String> {
        let ls: Vec<_> = (0..n)
            .map(|_| TcpListener::bind("127.0.0.1:0").unwrap())
            .collect();
        ls.iter()
            .map(|l| l.local_addr().unwrap().to_string())
            .collect()
    }

    #[test]
    fn three_processes_connect_past_an_intruder_and_name_a_lost_peer() {
        let hosts = loopback_hosts(3);
        let s = secret("a secret of enough bytes");
        let deadline = Instant::now() + Duration::from_secs(20);
        let lost: Vec<Arc<LostPeer>> = (0..3).map(|_| Arc::default()).collect();
        let streams = std::thread::scope(|scope| {
            let spawn = |p: usize| {
                let (hosts, s, lost) = (&hosts, &s, &lost[p]);
                scope.spawn(move || connect_peers(hosts, p, Some(s), STEP, deadline, lost))
            };
            // Processes 0 and 1 first: process 0 listens until process 2 is in, so the intruder
            // below always finds it listening, however the threads are scheduled.
            let mut handles: Vec<_> = (0..2).map(spawn).collect();
            // An intruder with another secret, posing as process 2 to process 0; it is refused
            // and the real process 2, started after it, still gets in.
            let intruder = ClusterSecret::new(b"not the cluster's secret").unwrap();
            let m = Membership {
                addresses: &hosts,
                me: 2,
                key: handshake_key(Some(&intruder)),
                step_timeout: STEP,
                deadline,
            };
            let c = loop {
                if let Ok(c) = TcpStream::connect(&hosts[0]) {
                    break c;
                }
                assert!(Instant::now() < deadline, "process 0 never listened");
                std::thread::sleep(Duration::from_millis(10));
            };
            assert!(connect_handshake(c, &m, 0).is_err());
            handles.push(spawn(2));
            handles
                .into_iter()
                .map(|h| h.join().unwrap().unwrap())
                .collect::<Vec<_>>()
        });
        for (p, row) in streams.iter().enumerate() {
            let peers: Vec<Option<usize>> = row
                .iter()
                .map(|s| s.as_ref().map(PeerStream::process))
                .collect();
            let expected: Vec<Option<usize>> = (0..3).map(|q| (q != p).then_some(q)).collect();
            assert_eq!(peers, expected, "process {p}");
        }
        // Process 1 dies: process 0's stream to it reads EOF and records it.
        let mut streams = streams;
        drop(std::mem::take(&mut streams[1]));
        let mut to_1 = streams[0][1].take().unwrap();
        let mut b = [0u8; 8];
        assert_eq!(to_1.read(&mut b).unwrap(), 0);
        assert_eq!(lost[0].get(), Some(1));
        assert_eq!(lost[2].get(), None);
    }

    #[test]
    fn a_flood_of_silent_connections_does_not_keep_the_real_peer_out() {
        let hosts = loopback_hosts(2);
        let step = Duration::from_millis(300);
        let deadline = Instant::now() + Duration::from_secs(20);
        let s = secret("0123456789abcdef");
        std::thread::scope(|scope| {
            let p0 =
                scope.spawn(|| connect_peers(&hosts, 0, Some(&s), step, deadline, &Arc::default()));
            // Twice as many silent connections as are checked at once, held open.
            let mut flood = Vec::new();
            while flood.len() < 2 * MAX_PENDING_HANDSHAKES {
                match TcpStream::connect(&hosts[0]) {
                    Ok(c) => flood.push(c),
                    Err(_) => std::thread::sleep(Duration::from_millis(10)),
                }
            }
            let p1 = connect_peers(&hosts, 1, Some(&s), step, deadline, &Arc::default()).unwrap();
            assert_eq!(p1[0].as_ref().map(PeerStream::process), Some(0));
            let p0 = p0.join().unwrap().unwrap();
            assert_eq!(p0[1].as_ref().map(PeerStream::process), Some(1));
            drop(flood);
        });
    }

    #[test]
    fn a_missing_or_wrong_secret_peer_times_out_with_its_name() {
        let hosts = loopback_hosts(2);
        let deadline = Instant::now() + Duration::from_millis(1500);
        let (a, b) = (secret("0123456789abcdef"), secret("fedcba9876543210"));
        let (r0, r1) = std::thread::scope(|scope| {
            let h = scope.spawn(|| {
                connect_peers(&hosts, 1, Some(&b), STEP, deadline, &Arc::default()).map(|_| ())
            });
            let r0 =
                connect_peers(&hosts, 0, Some(&a), STEP, deadline, &Arc::default()).map(|_| ());
            (r0, h.join().unwrap())
        });
        for (r, other) in [(r0, 1), (r1, 0)] {
            let e = r.unwrap_err().to_string();
            assert!(
                e.contains(&format!("process(es) {other} ({})", hosts[other])),
                "{e}"
            );
        }
    }

    #[test]
    fn secrets_are_read_from_private_files_only() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("secret");
        std::fs::write(&f, "c2xhZyBjbHVzdGVyIHNlY3JldCBvZiAzMiBieXRlcw==\n").unwrap();
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            std::fs::set_permissions(&f, std::fs::Permissions::from_mode(0o644)).unwrap();
            let e = ClusterSecret::read(&f).unwrap_err();
            assert!(
                matches!(
                    &e,
                    Error::Param {
                        name: "cluster_secret",
                        ..
                    }
                ) && e.to_string().contains("mode 644"),
                "{e}"
            );
            std::fs::set_permissions(&f, std::fs::Permissions::from_mode(0o600)).unwrap();
        }
        ClusterSecret::read(&f).unwrap();
        for short in ["\n", "  short  \n"] {
            std::fs::write(&f, short).unwrap();
            let e = ClusterSecret::read(&f).unwrap_err();
            assert!(matches!(e, Error::Format { .. }), "{e}");
        }
        assert!(matches!(
            ClusterSecret::read(&dir.path().join("absent")),
            Err(Error::Io { .. })
        ));
        assert_eq!(
            format!("{:?}", secret("0123456789abcdef")),
            "ClusterSecret(..)"
        );
    }

    #[test]
    fn only_loopback_addresses_count_as_loopback() {
        let v = |a: &[&str]| all_loopback(&a.iter().map(|s| s.to_string()).collect::<Vec<_>>());
        assert!(v(&[
            "127.0.0.1:4000",
            "127.9.0.1:1",
            "[::1]:4000",
            "localhost:4001"
        ]));
        for off in ["10.0.0.2:4000", "0.0.0.0:4000", "node2:4000", "[::]:4000"] {
            assert!(!v(&["127.0.0.1:4000", off]), "{off}");
        }
    }
}
