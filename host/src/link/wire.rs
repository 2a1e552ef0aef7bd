use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use deform_shared::frame::{self, Feed, FrameAccumulator, DELIMITER};
use deform_shared::protocol::{Envelope, ErrorCode, Request, Response, MAX_FRAME_LEN, UNKNOWN_SEQ};
use serialport::SerialPort;

use super::{open_serial, LinkError, Port};

/// How long a request waits for its answer unless told otherwise.
pub const DEFAULT_REQUEST_TIMEOUT: Duration = Duration::from_secs(10);

/// Bytes asked of the port per read.
const READ_CHUNK: usize = 256;

/// Which answers an exchange takes as its own.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Exchange {
    /// Mid-session the line is clean: the answer with our sequence number is ours, and a
    /// complaint about an unreadable frame ([`UNKNOWN_SEQ`]) is about our request, so it fails
    /// the request rather than leave it waiting for an answer that will never come.
    Request,
    /// While handshaking, the line may still carry noise and a previous session's answers (and
    /// our own flushing delimiter may end a partial frame, which the target then complains
    /// about). Only a `Hello` or a version complaint with our sequence number is ours;
    /// everything else is skipped.
    Handshake,
}

/// Counters of what a [`Link`] saw, for diagnostics and tests.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LinkStats {
    /// Requests sent.
    pub requests: u64,
    /// Frames from the target that did not decode (line noise, truncated or overlong frames).
    pub corrupt_frames: u64,
    /// Well-formed answers that were not for the waiting request (late answers to earlier
    /// requests, a previous session's, or complaints about noise).
    pub stale_answers: u64,
}

/// One request at a time to a target, over any [`Port`].
///
/// Every request travels in an [`Envelope`] with a fresh sequence number, and only the answer
/// carrying that number is taken: anything else on the line is counted and skipped, so late or
/// duplicated answers can never be mistaken for the current one. The very first frame of a link
/// is preceded by a lone delimiter, which ends whatever partial frame the target may hold (its
/// receive buffer may contain noise from before the port was opened).
pub struct Link<P: Port = Box<dyn SerialPort>> {
    port: P,
    frames: FrameAccumulator<MAX_FRAME_LEN>,
    /// Bytes read from the port but not yet fed to `frames`: they may hold the start of the
    /// next answer, so they outlive a request.
    inbox: Vec<u8>,
    inbox_read: usize,
    next_seq: u16,
    flushed: bool,
    timeout: Duration,
    stats: LinkStats,
}

impl Link<Box<dyn SerialPort>> {
    /// Opens a serial port (or a QEMU pty); see [`open_serial`].
    pub fn open(path: &str) -> Result<Self, LinkError> {
        Ok(Link::new(open_serial(path)?))
    }
}

impl<P: Port> Link<P> {
    /// A link over `port` with [`DEFAULT_REQUEST_TIMEOUT`].
    pub fn new(port: P) -> Self {
        Link {
            port,
            frames: FrameAccumulator::new(),
            inbox: Vec::with_capacity(READ_CHUNK),
            inbox_read: 0,
            next_seq: initial_seq(),
            flushed: false,
            timeout: DEFAULT_REQUEST_TIMEOUT,
            stats: LinkStats::default(),
        }
    }

    /// Sets how long [`request`](Self::request) waits for an answer.
    pub fn with_timeout(mut self, timeout: Duration) -> Self {
        self.timeout = timeout;
        self
    }

    pub fn set_timeout(&mut self, timeout: Duration) {
        self.timeout = timeout;
    }

    pub fn timeout(&self) -> Duration {
        self.timeout
    }

    pub fn stats(&self) -> LinkStats {
        self.stats
    }

    /// Sends `request` and waits for its answer within the link's timeout. An `Error` answer
    /// becomes [`LinkError::Target`].
    pub fn request(&mut self, request: &Request) -> Result<Response, LinkError> {
        self.request_within(request, self.timeout)
    }

    /// Like [`request`](Self::request) with its own deadline (a long solve needs more).
    pub fn request_within(
        &mut self,
        request: &Request,
        timeout: Duration,
    ) -> Result<Response, LinkError> {
        self.exchange(request, timeout, Exchange::Request)
    }

    /// Writes bytes as they are, outside any frame: for tests that put noise on the line.
    pub fn send_raw(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        self.port.set_timeout(self.timeout)?;
        self.port.write_all(bytes)?;
        self.port.flush()?;
        Ok(())
    }

    pub fn port_mut(&mut self) -> &mut P {
        &mut self.port
    }

    pub(crate) fn exchange(
        &mut self,
        request: &Request,
        timeout: Duration,
        kind: Exchange,
    ) -> Result<Response, LinkError> {
        let name = request_name(request);
        let seq = self.take_seq();
        let mut out = [0u8; MAX_FRAME_LEN + 1];
        let start = if self.flushed { 0 } else { 1 };
        out[0] = DELIMITER;
        let len = frame::encode(&Envelope { seq, body: request }, &mut out[start..]).map_err(
            |source| LinkError::Encode {
                request: name,
                source,
            },
        )?;
        // A target that is slow to drain its input may hold up our write, but not forever.
        self.port.set_timeout(timeout)?;
        self.port.write_all(&out[..start + len])?;
        self.port.flush()?;
        self.flushed = true;
        self.stats.requests += 1;

        let deadline = Instant::now() + timeout;
        loop {
            let Some(answer) = self.receive(deadline)? else {
                return Err(LinkError::Timeout {
                    request: name,
                    after: timeout,
                });
            };
            let ours = answer.seq == seq
                && (kind == Exchange::Request || is_handshake_answer(&answer.body));
            if ours {
                return match answer.body {
                    Response::Error(code) => Err(LinkError::Target {
                        request: name,
                        code,
                    }),
                    body => Ok(body),
                };
            }
            if answer.seq == UNKNOWN_SEQ && kind == Exchange::Request {
                if let Response::Error(code @ ErrorCode::Frame(_)) = answer.body {
                    return Err(LinkError::Target {
                        request: name,
                        code,
                    });
                }
            }
            self.stats.stale_answers += 1;
        }
    }

    fn take_seq(&mut self) -> u16 {
        let seq = self.next_seq;
        self.next_seq = match seq.wrapping_add(1) {
            UNKNOWN_SEQ => 0,
            next => next,
        };
        seq
    }

    /// The next well-formed answer, or `None` once `deadline` passes. Corrupt frames are
    /// counted and skipped.
    fn receive(&mut self, deadline: Instant) -> Result<Option<Envelope<Response>>, LinkError> {
        loop {
            while let Some(&byte) = self.inbox.get(self.inbox_read) {
                self.inbox_read += 1;
                match self.frames.feed(byte) {
                    Feed::Pending => {}
                    Feed::Overflow => self.stats.corrupt_frames += 1,
                    Feed::Frame(body) => match frame::decode::<Envelope<Response>>(body) {
                        Ok(answer) => return Ok(Some(answer)),
                        Err(_) => self.stats.corrupt_frames += 1,
                    },
                }
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Ok(None);
            }
            self.port.set_timeout(left)?;
            let mut buf = [0u8; READ_CHUNK];
            match self.port.read(&mut buf) {
                Ok(0) => {
                    return Err(LinkError::Io(std::io::Error::new(
                        std::io::ErrorKind::UnexpectedEof,
                        "the target closed the connection",
                    )))
                }
                Ok(n) => {
                    self.inbox.clear();
                    self.inbox.extend_from_slice(&buf[..n]);
                    self.inbox_read = 0;
                }
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::TimedOut
                            | std::io::ErrorKind::WouldBlock
                            | std::io::ErrorKind::Interrupted
                    ) => {}
                Err(e) => return Err(e.into()),
            }
        }
    }
}

fn is_handshake_answer(body: &Response) -> bool {
    matches!(
        body,
        Response::Hello(_) | Response::Error(ErrorCode::VersionMismatch { .. })
    )
}

/// A starting sequence number that differs between runs, so that answers still in flight from
/// a previous host process cannot match this one's first requests.
fn initial_seq() -> u16 {
    let nanos = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.subsec_nanos())
        .unwrap_or(0);
    let mixed = nanos ^ std::process::id().rotate_left(16);
    match (mixed ^ (mixed >> 16)) as u16 {
        UNKNOWN_SEQ => 0,
        seq => seq,
    }
}

/// The request's variant name, for messages.
pub fn request_name(request: &Request) -> &'static str {
    match request {
        Request::Hello { .. } => "Hello",
        Request::BeginMatrix { .. } => "BeginMatrix",
        Request::Tile(_) => "Tile",
        Request::Words { .. } => "Words",
        Request::EndMatrix { .. } => "EndMatrix",
        Request::BeginVector { .. } => "BeginVector",
        Request::VectorData { .. } => "VectorData",
        Request::Solve(_) => "Solve",
        Request::ReadSolution { .. } => "ReadSolution",
        Request::BeginUpdate { .. } => "BeginUpdate",
        Request::UpdateValues { .. } => "UpdateValues",
        Request::EndUpdate { .. } => "EndUpdate",
    }
}

#[cfg(test)]
mod tests {
    use std::io::{Read, Write};
    use std::os::unix::net::UnixStream;
    use std::thread;

    use deform_shared::frame::FrameError;
    use deform_shared::protocol::{SessionStep, PROTOCOL_VERSION};

    use super::*;
    use crate::link::fake_target::{answer_frame, serve, Received};

    const HELLO: Request = Request::Hello {
        protocol_version: PROTOCOL_VERSION,
    };

    fn quick_link(stream: UnixStream) -> Link<UnixStream> {
        Link::new(stream).with_timeout(Duration::from_secs(5))
    }

    #[test]
    fn the_first_frame_is_preceded_by_a_flushing_delimiter_and_later_ones_are_not() {
        let (host, mut target) = UnixStream::pair().unwrap();
        let mut link = quick_link(host);
        let peer = thread::spawn(move || {
            let mut raw = Vec::new();
            let mut acc = FrameAccumulator::<MAX_FRAME_LEN>::new();
            let mut answered = 0;
            let mut byte = [0u8];
            while answered < 2 {
                target.read_exact(&mut byte).unwrap();
                raw.push(byte[0]);
                if let Feed::Frame(body) = acc.feed(byte[0]) {
                    let req: Envelope<Request> = frame::decode(body).unwrap();
                    target
                        .write_all(&answer_frame(req.seq, Response::Ack))
                        .unwrap();
                    answered += 1;
                }
            }
            raw
        });
        assert_eq!(
            link.request(&Request::EndMatrix { crc32: 1 }).unwrap(),
            Response::Ack
        );
        assert_eq!(
            link.request(&Request::EndMatrix { crc32: 2 }).unwrap(),
            Response::Ack
        );
        let raw = peer.join().unwrap();
        assert_eq!(
            raw[0], DELIMITER,
            "the session must open with a lone delimiter"
        );
        assert_ne!(raw[1], DELIMITER);
        let delimiters = raw.iter().filter(|&&b| b == DELIMITER).count();
        assert_eq!(
            delimiters, 3,
            "one flush, then one delimiter per frame: {raw:?}"
        );
    }

    #[test]
    fn noise_and_stale_answers_before_the_answer_are_skipped() {
        let (host, target) = UnixStream::pair().unwrap();
        let mut link = quick_link(host);
        serve(target, |received| match received {
            Received::Request(req) => {
                let mut out = vec![0x13, 0x37, 0xFF, 0x00]; // a short garbage frame
                out.extend(std::iter::repeat_n(0xAA, 2 * MAX_FRAME_LEN)); // an overlong one
                out.push(0x00);
                let mut corrupted = answer_frame(req.seq, Response::Ack);
                corrupted[2] ^= 0x10;
                out.extend(corrupted);
                out.extend(answer_frame(req.seq.wrapping_sub(1), Response::Ack)); // stale
                out.extend(answer_frame(
                    req.seq,
                    Response::Hello(crate::link::fake_target::info()),
                ));
                out
            }
            Received::Unreadable(_) => Vec::new(),
        });
        let answer = link.request(&HELLO).unwrap();
        assert!(matches!(answer, Response::Hello(_)), "{answer:?}");
        let stats = link.stats();
        assert_eq!(stats.corrupt_frames, 3, "{stats:?}");
        assert_eq!(stats.stale_answers, 1, "{stats:?}");
    }

    #[test]
    fn a_silent_target_times_out_naming_the_request() {
        let (host, target) = UnixStream::pair().unwrap();
        let mut link = Link::new(host);
        serve(target, |_| Vec::new());
        let started = Instant::now();
        let err = link
            .request_within(
                &Request::ReadSolution {
                    direction: 0,
                    offset: 0,
                },
                Duration::from_millis(150),
            )
            .unwrap_err();
        let waited = started.elapsed();
        assert!(
            matches!(
                err,
                LinkError::Timeout {
                    request: "ReadSolution",
                    ..
                }
            ),
            "{err:?}"
        );
        assert!(err.to_string().contains("ReadSolution"), "{err}");
        assert!(
            waited >= Duration::from_millis(150) && waited < Duration::from_secs(2),
            "{waited:?}"
        );
    }

    #[test]
    fn a_target_that_streams_noise_forever_still_times_out() {
        let (host, mut target) = UnixStream::pair().unwrap();
        let mut link = Link::new(host);
        thread::spawn(move || {
            let noise = [0x55u8; 64];
            while target.write_all(&noise).is_ok() {
                thread::sleep(Duration::from_millis(1));
            }
        });
        let started = Instant::now();
        let err = link
            .request_within(&HELLO, Duration::from_millis(200))
            .unwrap_err();
        assert!(
            matches!(
                err,
                LinkError::Timeout {
                    request: "Hello",
                    ..
                }
            ),
            "{err:?}"
        );
        assert!(started.elapsed() < Duration::from_secs(2));
    }

    #[test]
    fn an_unreadable_frame_complaint_is_an_error_mid_session() {
        let (host, target) = UnixStream::pair().unwrap();
        let mut link = quick_link(host);
        serve(target, |_| {
            answer_frame(
                UNKNOWN_SEQ,
                Response::Error(ErrorCode::Frame(FrameError::Crc)),
            )
        });
        let err = link.request(&Request::EndMatrix { crc32: 0 }).unwrap_err();
        assert_eq!(
            err.target_code(),
            Some(ErrorCode::Frame(FrameError::Crc)),
            "{err:?}"
        );
        assert!(err.to_string().contains("EndMatrix"), "{err}");
    }

    #[test]
    fn error_answers_carry_the_targets_code() {
        let (host, target) = UnixStream::pair().unwrap();
        let mut link = quick_link(host);
        let code = ErrorCode::OutOfOrder(SessionStep::NoMatrix);
        serve(target, move |received| match received {
            Received::Request(req) => answer_frame(req.seq, Response::Error(code)),
            Received::Unreadable(_) => Vec::new(),
        });
        let err = link
            .request(&Request::ReadSolution {
                direction: 0,
                offset: 0,
            })
            .unwrap_err();
        assert_eq!(err.target_code(), Some(code));
        assert!(err.to_string().contains("no matrix is loaded"), "{err}");
    }

    #[test]
    fn a_closed_connection_is_an_io_error_not_a_hang() {
        let (host, target) = UnixStream::pair().unwrap();
        drop(target);
        let mut link = quick_link(host);
        let err = link.request(&HELLO).unwrap_err();
        assert!(matches!(err, LinkError::Io(_)), "{err:?}");
    }

    #[test]
    fn sequence_numbers_never_use_the_unknown_marker() {
        let (host, _target) = UnixStream::pair().unwrap();
        let mut link = quick_link(host);
        link.next_seq = UNKNOWN_SEQ - 1;
        assert_eq!(link.take_seq(), UNKNOWN_SEQ - 1);
        assert_eq!(link.take_seq(), 0);
    }
}
