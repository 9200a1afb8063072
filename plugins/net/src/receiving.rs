//! What a server holds of messages while they arrive, across all its connections.
//!
//! Each connection bounds its own message (16 MiB), and a server its connections (4 096 by
//! default), but 4 096 connections each in the middle of a 16 MiB message are 64 GiB: a
//! peer that opens many connections and sends large messages slowly, or many peers sending
//! large messages at once, would grow the process until the system killed it. A server's
//! [`Receiving`] bounds the sum: a message that would take it over [`RECEIVING_BYTES`] is
//! refused (an HTTP request answered 503, a gRPC call `RESOURCE_EXHAUSTED`, a TCP
//! connection closed with its frame counted as received truncated), and the sender may try
//! again. A message of up to [`UNCOUNTED`] bytes holds nothing of the budget, so small
//! messages are never refused for it.
//!
//! Clients read the answers to their own calls with the same reader, outside any budget:
//! [`collect_within`], and [`collect_with_trailers`] for gRPC's.

use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;

use aimrt_plugin_api::RateLimit;
use bytes::Bytes;
use http_body_util::BodyExt;
use hyper::HeaderMap;

/// Bytes of messages a server holds while they arrive, across its connections, at most:
/// sixteen messages of the largest size (16 MiB) at once.
pub const RECEIVING_BYTES: usize = 256 << 20;

/// Bytes of a message that do not count against [`RECEIVING_BYTES`].
pub const UNCOUNTED: usize = 64 << 10;

/// One server's budget of bytes held by messages that are arriving, and the count of the
/// messages it refused.
#[derive(Debug)]
pub struct Receiving {
    held: AtomicUsize,
    limit: usize,
    /// The server, as its log lines name it (`net_plugin tcp`).
    who: &'static str,
    refused: AtomicU64,
    alarm: RateLimit,
}

/// A message would take its server over its budget.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("{held} bytes of messages are arriving on this server's connections, and {wanted} more would pass its limit of {limit}")]
pub struct Full {
    /// What the messages held then (this one's part included).
    pub held: usize,
    /// What this message asked for in addition to what it held.
    pub wanted: usize,
    /// The budget.
    pub limit: usize,
}

impl Receiving {
    /// A budget of `limit` bytes for the server `who` names in its log lines.
    pub fn new(limit: usize, who: &'static str) -> Arc<Receiving> {
        Arc::new(Receiving {
            held: AtomicUsize::new(0),
            limit,
            who,
            refused: AtomicU64::new(0),
            alarm: RateLimit::from_millis(1000),
        })
    }

    /// The bytes held now.
    pub fn held(&self) -> usize {
        self.held.load(Ordering::Relaxed)
    }

    /// A message was refused for the budget: counted, and `what` (which message, and the
    /// [`Full`] it met) said at most once a second.
    pub fn refuse(&self, what: std::fmt::Arguments<'_>) {
        self.refused.fetch_add(1, Ordering::Relaxed);
        if let Some(held) = self.alarm.admit() {
            tracing::warn!(target: "aimrt", "{}: {what} ({held} more such lines held back since the last)", self.who);
        }
    }

    /// The messages refused so far.
    pub fn refused(&self) -> u64 {
        self.refused.load(Ordering::Relaxed)
    }

    /// The end of the server's shutdown line: `, N refused as they arrived (…)`, or
    /// nothing when none was.
    ///
    /// ```
    /// use aimrt_net::receiving::Receiving;
    /// let budget = Receiving::new(1 << 20, "a server");
    /// assert_eq!(budget.refused_part(), "");
    /// budget.refuse(format_args!("a message was refused"));
    /// assert_eq!(
    ///     budget.refused_part(),
    ///     ", 1 refused as they arrived (the server's connections held 1048576 bytes of messages arriving)"
    /// );
    /// ```
    pub fn refused_part(&self) -> String {
        match self.refused() {
            0 => String::new(),
            n => format!(
                ", {n} refused as they arrived (the server's connections held {} bytes of messages arriving)",
                self.limit
            ),
        }
    }
}

/// What one message (or one connection's buffer) holds of a server's budget; given back
/// when dropped.
///
/// ```
/// use aimrt_net::receiving::{Claim, Receiving, UNCOUNTED};
/// let budget = Receiving::new(1 << 20, "a server");
/// let mut a = Claim::new(&budget);
/// a.hold(UNCOUNTED).unwrap(); // small: holds nothing
/// assert_eq!(budget.held(), 0);
/// a.hold(UNCOUNTED + 1000).unwrap();
/// assert_eq!(budget.held(), 1000);
/// let mut b = Claim::new(&budget);
/// let full = b.hold(UNCOUNTED + (1 << 20)).unwrap_err();
/// assert_eq!((full.held, full.wanted), (1000, 1 << 20));
/// drop(a);
/// assert_eq!(budget.held(), 0);
/// ```
#[derive(Debug)]
pub struct Claim<'a> {
    of: &'a Receiving,
    bytes: usize,
}

impl<'a> Claim<'a> {
    /// A claim on `of` holding nothing yet (it borrows the budget: a message's claim lives
    /// no longer than its server's handling of it).
    pub fn new(of: &'a Receiving) -> Claim<'a> {
        Claim { of, bytes: 0 }
    }

    /// The budget it holds of.
    pub fn budget(&self) -> &'a Receiving {
        self.of
    }

    /// Holds what a message of `size` bytes needs (less, and back, when it shrank); `Err`
    /// when more would take the server over its budget, holding what it held before.
    pub fn hold(&mut self, size: usize) -> Result<(), Full> {
        let want = size.saturating_sub(UNCOUNTED);
        if want <= self.bytes {
            if want < self.bytes {
                self.of.held.fetch_sub(self.bytes - want, Ordering::Relaxed);
                self.bytes = want;
            }
            return Ok(());
        }
        let more = want - self.bytes;
        let limit = self.of.limit;
        self.of
            .held
            .fetch_update(Ordering::Relaxed, Ordering::Relaxed, |held| {
                held.checked_add(more).filter(|&n| n <= limit)
            })
            .map_err(|held| Full {
                held,
                wanted: more,
                limit,
            })?;
        self.bytes = want;
        Ok(())
    }

    /// [`hold`](Claim::hold) for a message of `size` bytes, unless it holds more already
    /// (a declared length held before the bytes arrived).
    pub fn grow_to(&mut self, size: usize) -> Result<(), Full> {
        if size.saturating_sub(UNCOUNTED) <= self.bytes {
            return Ok(());
        }
        self.hold(size)
    }
}

impl Drop for Claim<'_> {
    fn drop(&mut self) {
        self.of.held.fetch_sub(self.bytes, Ordering::Relaxed);
    }
}

/// Why [`collect`] did not read a whole body.
#[derive(Debug, thiserror::Error)]
pub enum BodyError {
    /// The body is longer than the limit it was read with.
    #[error("the body is larger than the limit of {0} bytes")]
    TooLarge(usize),
    /// The server holds too much of other messages now.
    #[error(transparent)]
    Full(#[from] Full),
    /// The body could not be read (the connection broke, a malformed chunk).
    #[error("{0}")]
    Read(Box<dyn std::error::Error + Send + Sync>),
}

/// Reads `body` whole, at most `limit` bytes, holding its bytes in `claim` as they arrive
/// (beyond what `claim` holds already); a body of one chunk is returned without a copy.
pub fn collect<'c, 'b, B>(
    body: B,
    limit: usize,
    claim: &'c mut Claim<'b>,
) -> impl std::future::Future<Output = Result<Bytes, BodyError>> + use<'c, 'b, B>
where
    B: hyper::body::Body<Data = Bytes> + Unpin,
    B::Error: Into<Box<dyn std::error::Error + Send + Sync>>,
{
    // `gather`'s own future, not one that awaits it: one state machine a body.
    gather(body, limit, |len| claim.grow_to(len), |_| ())
}

/// Reads `body` whole, at most `limit` bytes, in no budget: for what a client reads of
/// the answers to its own calls (docs/decisions.md). A body of one chunk is returned
/// without a copy.
///
/// ```
/// # tokio::runtime::Builder::new_current_thread().build().unwrap().block_on(async {
/// use aimrt_net::receiving::{collect_within, BodyError};
/// use http_body_util::Full;
/// let body = Full::new(bytes::Bytes::from_static(b"an answer"));
/// assert_eq!(collect_within(body, 100).await.unwrap(), "an answer");
/// let long = Full::new(bytes::Bytes::from_static(b"an answer"));
/// assert!(matches!(collect_within(long, 4).await, Err(BodyError::TooLarge(4))));
/// # });
/// ```
pub fn collect_within<B>(
    body: B,
    limit: usize,
) -> impl std::future::Future<Output = Result<Bytes, BodyError>>
where
    B: hyper::body::Body<Data = Bytes> + Unpin,
    B::Error: Into<Box<dyn std::error::Error + Send + Sync>>,
{
    gather(body, limit, |_| Ok(()), |_| ())
}

/// [`collect_within`], keeping the body's trailers in `trailers` (a gRPC answer's
/// status is there).
///
/// ```
/// # tokio::runtime::Builder::new_current_thread().build().unwrap().block_on(async {
/// use aimrt_net::receiving::collect_with_trailers;
/// use http_body_util::{BodyExt, Full};
/// let mut status = hyper::HeaderMap::new();
/// status.insert("grpc-status", "0".parse().unwrap());
/// let trailers = std::future::ready(Some(Ok(status)));
/// let body = Full::new(bytes::Bytes::from_static(b"an answer")).with_trailers(trailers);
/// let mut trailers = None;
/// let read = collect_with_trailers(body, 100, &mut trailers).await.unwrap();
/// assert_eq!(read, "an answer");
/// assert_eq!(trailers.unwrap()["grpc-status"], "0");
/// # });
/// ```
pub fn collect_with_trailers<'t, B>(
    body: B,
    limit: usize,
    trailers: &'t mut Option<HeaderMap>,
) -> impl std::future::Future<Output = Result<Bytes, BodyError>> + use<'t, B>
where
    B: hyper::body::Body<Data = Bytes> + Unpin,
    B::Error: Into<Box<dyn std::error::Error + Send + Sync>>,
{
    gather(body, limit, |_| Ok(()), |t| *trailers = Some(t))
}

/// Reads `body` whole, at most `limit` bytes (a body whose declared length is larger is
/// refused before it is read), telling `hold` the length read so far at each chunk (an
/// `Err` from `hold` ends the read) and `keep` the trailers.
async fn gather<B>(
    mut body: B,
    limit: usize,
    mut hold: impl FnMut(usize) -> Result<(), Full>,
    mut keep: impl FnMut(HeaderMap),
) -> Result<Bytes, BodyError>
where
    B: hyper::body::Body<Data = Bytes> + Unpin,
    B::Error: Into<Box<dyn std::error::Error + Send + Sync>>,
{
    // A declared length over the limit is refused before a byte is read.
    if usize::try_from(body.size_hint().lower()).map_or(true, |n| n > limit) {
        return Err(BodyError::TooLarge(limit));
    }
    // The first chunk on its own: most bodies are one, and then nothing is allocated.
    let mut first: Option<Bytes> = None;
    let mut rest: Vec<Bytes> = Vec::new();
    let mut len = 0;
    while let Some(frame) = body.frame().await {
        let frame = frame.map_err(|e| BodyError::Read(e.into()))?;
        let data = match frame.into_data() {
            Ok(data) => data,
            Err(frame) => {
                if let Ok(trailers) = frame.into_trailers() {
                    keep(trailers);
                }
                continue;
            }
        };
        if data.is_empty() {
            continue;
        }
        len += data.len();
        if len > limit {
            return Err(BodyError::TooLarge(limit));
        }
        hold(len)?;
        if first.is_none() {
            first = Some(data);
        } else {
            rest.push(data);
        }
    }
    let Some(first) = first else {
        return Ok(Bytes::new());
    };
    if rest.is_empty() {
        return Ok(first);
    }
    let mut whole = Vec::with_capacity(len);
    for c in std::iter::once(&first).chain(&rest) {
        whole.extend_from_slice(c);
    }
    Ok(Bytes::from(whole))
}

#[cfg(test)]
mod tests {
    use super::*;
    use http_body_util::Full as FullBody;
    use std::collections::VecDeque;

    /// A body of chunks, as they would arrive.
    struct Chunks(VecDeque<Bytes>);

    impl hyper::body::Body for Chunks {
        type Data = Bytes;
        type Error = std::io::Error;
        fn poll_frame(
            mut self: std::pin::Pin<&mut Self>,
            _: &mut std::task::Context<'_>,
        ) -> std::task::Poll<Option<Result<hyper::body::Frame<Bytes>, std::io::Error>>> {
            std::task::Poll::Ready(self.0.pop_front().map(|c| Ok(hyper::body::Frame::data(c))))
        }
    }

    fn body(chunks: Vec<Vec<u8>>) -> Chunks {
        Chunks(chunks.into_iter().map(Bytes::from).collect())
    }

    fn block_on<F: std::future::Future>(f: F) -> F::Output {
        tokio::runtime::Builder::new_current_thread()
            .build()
            .unwrap()
            .block_on(f)
    }

    /// Bodies are read whole within the limit and the budget, one chunk without a copy;
    /// one that would pass either is refused, and what it held is given back.
    #[test]
    fn a_body_is_read_within_its_limit_and_the_servers_budget() {
        let budget = Receiving::new(1 << 20, "a server");
        let mut claim = Claim::new(&budget);
        let one = Bytes::from(vec![7u8; 100]);
        let got = block_on(collect(FullBody::new(one.clone()), 1000, &mut claim)).unwrap();
        assert_eq!(got.as_ptr(), one.as_ptr(), "one chunk is not copied");
        let none = block_on(collect(body(vec![vec![], vec![]]), 1000, &mut claim)).unwrap();
        assert!(none.is_empty(), "empty chunks make an empty body");
        let chunks = vec![vec![1u8; 60_000], vec![2u8; 60_000], vec![3u8; 10]];
        let got = block_on(collect(body(chunks), 1 << 20, &mut claim)).unwrap();
        assert_eq!(got.len(), 120_010);
        assert_eq!((got[0], got[60_000], got[120_009]), (1, 2, 3));
        assert_eq!(budget.held(), 120_010 - UNCOUNTED, "held while it is kept");
        drop(claim);
        assert_eq!(budget.held(), 0);
        // A declared length held first is not given back as the first bytes arrive.
        let mut claim = Claim::new(&budget);
        claim.hold(UNCOUNTED + 500_000).unwrap();
        let got = block_on(collect(body(vec![vec![0; 100_000]]), 1 << 20, &mut claim)).unwrap();
        assert_eq!((got.len(), budget.held()), (100_000, 500_000));
        drop(claim);

        let mut claim = Claim::new(&budget);
        let too_large = block_on(collect(
            body(vec![vec![0; 600], vec![0; 600]]),
            1000,
            &mut claim,
        ));
        assert!(
            matches!(too_large, Err(BodyError::TooLarge(1000))),
            "{too_large:?}"
        );

        // Another message holds most of the budget: a large body is refused part way.
        let mut other = Claim::new(&budget);
        other.hold(UNCOUNTED + 900_000).unwrap();
        let mut claim = Claim::new(&budget);
        let chunks = vec![vec![0u8; 100_000]; 3];
        let full = block_on(collect(body(chunks), 16 << 20, &mut claim)).unwrap_err();
        let BodyError::Full(full) = full else {
            panic!("{full:?}")
        };
        // The first two chunks held 200 000 bytes, less what counts for nothing.
        let own = 200_000 - UNCOUNTED;
        assert_eq!(
            (full.held, full.wanted, full.limit),
            (900_000 + own, 100_000, 1 << 20)
        );
        let said = format!("{} bytes of messages are arriving on this server's connections, and 100000 more would pass its limit of 1048576", 900_000 + own);
        assert_eq!(full.to_string(), said);
        drop(claim);
        assert_eq!(
            budget.held(),
            900_000,
            "the refused body gave back what it held"
        );
        // Small bodies pass however full the budget is.
        other.hold(UNCOUNTED + (1 << 20)).unwrap();
        let mut claim = Claim::new(&budget);
        let small = block_on(collect(body(vec![vec![0; UNCOUNTED]]), 1 << 20, &mut claim));
        assert_eq!(small.unwrap().len(), UNCOUNTED);
        other.hold(0).unwrap();
        assert_eq!(budget.held(), 0, "a claim that shrinks gives back");
    }
}
