//! The host's end of the reliable transport ([`deform_shared::transport`], `docs/PROTOCOL.md`):
//! numbered request frames, up to [`WINDOW`] of them in flight, replies matched by number and
//! delivered in order, retransmission on NAK or timeout (with exponential back-off), and
//! bounded waiting everywhere.
//!
//! The host owns every timer. A request's frame is sent again when the target NAKs it, when the
//! target shows it handled the request but its reply was lost (a later reply, or a NAK naming a
//! later number), or when no reply came within the retransmit timeout: the smoothed time the
//! target takes per request plus four times its variation (RFC 6298; at least 20 ms, at most
//! [`LinkConfig::retransmit`]). The timeout doubles (up to 8× [`LinkConfig::retransmit`]) only
//! while the line shows no *damage*: with no NAK and no corrupt frame since the frame went out,
//! the target is slow (or absent) and resending sooner would only load it; with damage, the line
//! is noisy, the target there, and waiting longer would only lose time.
//!
//! The deadline follows **progress**: a run fails with [`LinkError::Timeout`] only once nothing
//! has been acknowledged for [`Link::timeout`] (no reply, no `Ack`, no NAK naming a later number),
//! or once one frame went [`LinkConfig::retries`] retransmissions without a sign of damage;
//! a long-running request (`Solve`) that the target acknowledged may wait its own, longer,
//! deadline. So a noisy line that keeps moving is never given up on, however many frames it
//! damages, while a dead one fails within the timeout; a passed deadline first reads what the
//! line already holds, since the time may have gone on this side while replies waited, and time
//! this side could not watch the line (a wait that ended far later than asked, a write held up
//! for over a second) moves the deadlines rather than counting as the target's silence. Nothing
//! here can block longer than those bounds: every read and write on the port is bounded by the
//! time left.

use std::collections::VecDeque;
use std::io::ErrorKind;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use deform_shared::frame::{self, DELIMITER};
use deform_shared::protocol::{Envelope, ErrorCode, Request, Response, MAX_FRAME_LEN};
use deform_shared::transport::{Uplink, WINDOW};
use serialport::SerialPort;

use super::adapt::{Adaptive, ChunkSize};
use super::{open_serial, FrameEvent, FrameReader, LinkError, Port};

/// How long the link may go without progress (nothing acknowledged) before it fails, unless told
/// otherwise.
pub const DEFAULT_REQUEST_TIMEOUT: Duration = Duration::from_secs(10);

/// The least retransmit timeout, however fast the target answers.
const MIN_RETRANSMIT: Duration = Duration::from_millis(20);

/// How long a step of this side (a wait for the line that ended later than asked, one write)
/// may take before the link takes it that this side was held (see [`held_past`]). A loaded
/// machine wakes a poll late by milliseconds, rarely by a few hundred.
const HELD: Duration = Duration::from_secs(1);

/// How long this side was held, if a wait for the line that was to end at `wake` ended more
/// than [`HELD`] after it (else zero): a suspended laptop, a stopped process, or a stalled
/// virtual machine, which stops a QEMU target with it. That time says nothing about the
/// target, so the link's deadlines move by it rather than failing a run whose target had no
/// time to answer: a passed deadline only gets a few milliseconds of reading, too little for a
/// target that has to handle the frame sent again after the stop. A write held up longer than
/// [`HELD`] moves them the same way ([`Link::write`]): whatever held it, the host could not
/// watch the line meanwhile, and a port that never drains still fails, when the write's own
/// timeout runs out ([`LinkError::WriteStalled`]).
fn held_past(wake: Instant) -> Duration {
    let late = Instant::now().saturating_duration_since(wake);
    if late > HELD {
        late
    } else {
        Duration::ZERO
    }
}

/// Retransmission settings.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LinkConfig {
    /// The longest a frame waits for its reply (or an ACK) before it is sent again, and the
    /// wait until the link has measured how fast the target answers (it then waits that time
    /// plus four times its variation, at least 20 ms, at most this); doubled after every
    /// retransmission of the same frame with no sign of a damaged line (no NAK, no corrupt frame)
    /// since it went out, up to 8× this.
    pub retransmit: Duration,
    /// Retransmissions of one frame in a row with no sign of a damaged line between them before
    /// the request fails: a target that is not there (or hangs), rather than a noisy line.
    pub retries: u32,
    /// Requests in flight (1 ..= [`WINDOW`]).
    pub window: u16,
}

impl Default for LinkConfig {
    /// 250 ms is ~25 round trips of a full frame through a QEMU pty and far more than a
    /// 115200-baud line needs for one. 16 undamaged retries with the doubling take longer than
    /// [`DEFAULT_REQUEST_TIMEOUT`], which therefore decides by default.
    fn default() -> Self {
        LinkConfig {
            retransmit: Duration::from_millis(250),
            retries: 16,
            window: WINDOW,
        }
    }
}

/// Counters of what a [`Link`] saw, for diagnostics, reports and tests.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LinkStats {
    /// Requests sent (each counted once, however often its frame went out).
    pub requests: u64,
    /// Frames sent again (after a NAK or a timeout).
    pub retransmits: u64,
    /// Of those, sent because of a timeout.
    pub timeouts: u64,
    /// NAKs received.
    pub naks: u64,
    /// Frames from the target that did not decode (line noise, truncated or overlong frames).
    pub corrupt_frames: u64,
    /// Of those, frames whose CRC was right but whose contents did not decode: a target that
    /// speaks another protocol version.
    pub undecodable: u64,
    /// Well-formed replies that were not awaited (duplicates, a previous session's).
    pub stale_answers: u64,
    /// Bytes written to the port, retransmissions included.
    pub bytes_sent: u64,
    /// Of those, bytes of retransmitted frames.
    pub bytes_resent: u64,
    /// Bytes read from the port.
    pub bytes_received: u64,
    /// Of those, bytes of the frames that a prompt, clean line carries: each reply,
    /// acknowledgement and notice once. The rest is what a loaded host or a noisy line added:
    /// noise, corrupt frames, NAKs, and the duplicate replies and repeated acknowledgements
    /// that retransmissions draw.
    pub bytes_received_clean: u64,
    /// Notices (firmware logs) received, and how many the numbering says were lost.
    pub notices: u64,
    pub notices_lost: u64,
}

/// A request in flight.
struct InFlight {
    seq: u16,
    request: Request,
    frame: Vec<u8>,
    last_sent: Instant,
    /// When the retransmit timer started: the last send, or the moment the request became the
    /// oldest without a reply, whichever is later.
    timer: Instant,
    retries: u32,
    /// When the target acknowledged a long-running request.
    accepted: Option<Instant>,
    reply: Option<Response>,
    /// Whether a NAK already reported this send of it as damaged (see [`Adaptive`]).
    damage_counted: bool,
    /// Whether the target has shown it handled the request (a later reply, or a NAK naming a
    /// later number) though its reply has not arrived.
    handled: bool,
    /// Retransmissions in a row with no sign of damage since the send before: the back-off's
    /// exponent.
    quiet: u32,
    /// [`Link::damage_seen`] at the last send, to tell a slow target from a noisy line.
    damage_at_send: u64,
}

impl InFlight {
    /// A request just sent for the first time.
    fn new(seq: u16, request: Request, frame: Vec<u8>, damage_at_send: u64) -> Self {
        let now = Instant::now();
        InFlight {
            seq,
            request,
            frame,
            last_sent: now,
            timer: now,
            retries: 0,
            accepted: None,
            reply: None,
            damage_counted: false,
            handled: false,
            quiet: 0,
            damage_at_send,
        }
    }
}

/// How one [`Link::run`] stands: the requests in flight, in the order sent, and why it ends.
struct Run {
    window: VecDeque<InFlight>,
    /// The first error of the run; no new request is sent after it.
    failure: Option<LinkError>,
    /// The requests' iterator has ended.
    exhausted: bool,
    /// When the target last acknowledged anything new: the deadlines count from here.
    progress: Instant,
}

impl Run {
    fn new() -> Self {
        Run {
            window: VecDeque::new(),
            failure: None,
            exhausted: false,
            progress: Instant::now(),
        }
    }

    fn oldest_unanswered(&self) -> Option<&InFlight> {
        self.window.iter().find(|e| e.reply.is_none())
    }

    /// Hands the replies that are in order to `on_reply` (a target's error reply fails the
    /// run); after a failure the rest are only taken off the window.
    fn deliver(&mut self, on_reply: &mut impl FnMut(&Request, Response) -> Result<(), LinkError>) {
        while self.window.front().is_some_and(|f| f.reply.is_some()) {
            let Some(done) = self.window.pop_front() else {
                break;
            };
            let Some(reply) = done.reply else { break };
            if self.failure.is_some() {
                continue;
            }
            let result = match reply {
                Response::Error(code) => Err(LinkError::Target {
                    request: done.request.name(),
                    code,
                }),
                reply => on_reply(&done.request, reply),
            };
            if let Err(e) = result {
                self.failure = Some(e);
            }
        }
    }

    /// Moves the deadlines on by the time the host was held up and could not watch the line.
    fn postpone(&mut self, held: Duration) {
        if held.is_zero() {
            return;
        }
        self.progress += held;
        for at in self.window.iter_mut().filter_map(|e| e.accepted.as_mut()) {
            *at += held;
        }
    }
}

/// Something the target says besides replies, handed to the notice handler.
pub type NoticeHandler = Box<dyn FnMut(u16, Response) + Send>;

/// The transport to a target, over any [`Port`].
pub struct Link<P: Port = Box<dyn SerialPort>> {
    port: P,
    /// Frames from the port, at most one frame long.
    reader: FrameReader<MAX_FRAME_LEN>,
    next_seq: u16,
    flushed: bool,
    timeout: Duration,
    config: LinkConfig,
    stats: LinkStats,
    last_notice: Option<u16>,
    notice_handler: Option<NoticeHandler>,
    /// Smoothed service time: from the moment a request became the oldest without a reply to
    /// its reply, for requests answered at the first send.
    srtt: Option<Duration>,
    /// Its smoothed variation.
    rttvar: Duration,
    /// Chunk size and window, adapted to the line (see [`super::adapt`]).
    adapt: Adaptive,
    /// Time this side was held (see [`held_past`]) since the run loop last moved its deadlines
    /// by it.
    held: Duration,
}

impl Link<Box<dyn SerialPort>> {
    /// Opens a serial port (or a QEMU pty); see [`open_serial`].
    pub fn open(path: &str) -> Result<Self, LinkError> {
        Ok(Link::new(open_serial(path)?))
    }
}

impl<P: Port> Link<P> {
    /// A link over `port` with [`DEFAULT_REQUEST_TIMEOUT`] and the default [`LinkConfig`].
    pub fn new(port: P) -> Self {
        Link {
            port,
            reader: FrameReader::default(),
            next_seq: initial_seq(),
            flushed: false,
            timeout: DEFAULT_REQUEST_TIMEOUT,
            config: LinkConfig::default(),
            stats: LinkStats::default(),
            last_notice: None,
            notice_handler: None,
            srtt: None,
            rttvar: Duration::ZERO,
            adapt: Adaptive::new(WINDOW),
            held: Duration::ZERO,
        }
    }

    /// Turns the adaptation off: every chunk `chunk` elements, the whole window, whatever the
    /// line does (for tests that count requests, and for comparisons).
    pub fn with_fixed_chunk(mut self, chunk: usize) -> Self {
        self.adapt = Adaptive::fixed(chunk, self.config.window);
        self
    }

    /// Sets how long a request may wait for its reply, retransmissions included.
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

    pub fn config(&self) -> LinkConfig {
        self.config
    }

    pub fn set_config(&mut self, config: LinkConfig) {
        self.config = LinkConfig {
            window: config.window.clamp(1, WINDOW),
            ..config
        };
        self.adapt.set_max_window(self.config.window);
    }

    /// The chunk size the link has adapted to, for request generators to read as they go.
    pub fn chunk_size(&self) -> ChunkSize {
        self.adapt.chunk_handle()
    }

    /// The adaptation's state: chunk, window, estimated byte-error rate.
    pub fn adaptive(&self) -> &Adaptive {
        &self.adapt
    }

    pub fn stats(&self) -> LinkStats {
        self.stats
    }

    /// Where unsolicited messages (firmware logs in `Response::Log`) go, with their notice
    /// number. Without a handler they are counted and dropped.
    pub fn set_notice_handler(&mut self, handler: NoticeHandler) {
        self.notice_handler = Some(handler);
    }

    /// Sends `request` and waits for its reply. An `Error` reply becomes [`LinkError::Target`].
    pub fn request(&mut self, request: &Request) -> Result<Response, LinkError> {
        self.request_within(request, self.timeout)
    }

    /// Like [`request`](Self::request); a long-running request (`Solve`) that the target
    /// acknowledged may take up to `timeout` (other requests are bounded by the link's own
    /// timeout, since their frames may need resending).
    pub fn request_within(
        &mut self,
        request: &Request,
        timeout: Duration,
    ) -> Result<Response, LinkError> {
        let mut answer = None;
        self.run_within(std::iter::once(request.clone()), timeout, |_, response| {
            answer = Some(response);
            Ok(())
        })?;
        answer.ok_or(LinkError::Timeout {
            request: request.name(),
            after: timeout,
            retries: 0,
        })
    }

    /// Sends `requests` with up to [`LinkConfig::window`] in flight and hands every reply, in
    /// request order, to `on_reply`. Stops at the first `Error` reply (as
    /// [`LinkError::Target`]) or the first error `on_reply` returns, but only after the replies
    /// to the requests already in flight have arrived, so that the target and the host agree on
    /// the sequence numbers afterwards.
    pub fn run(
        &mut self,
        requests: impl Iterator<Item = Request>,
        on_reply: impl FnMut(&Request, Response) -> Result<(), LinkError>,
    ) -> Result<(), LinkError> {
        self.run_within(requests, self.timeout, on_reply)
    }

    fn run_within(
        &mut self,
        mut requests: impl Iterator<Item = Request>,
        long_timeout: Duration,
        mut on_reply: impl FnMut(&Request, Response) -> Result<(), LinkError>,
    ) -> Result<(), LinkError> {
        let mut run = Run::new();
        self.held = Duration::ZERO;
        loop {
            self.fill_window(&mut run, &mut requests)?;
            run.deliver(&mut on_reply);
            if run.window.is_empty() {
                match run.failure.take() {
                    Some(e) => return Err(e),
                    None if run.exhausted => return Ok(()),
                    None => continue,
                }
            }
            self.await_frame(&mut run, long_timeout)?;
            self.retransmit_if_due(&mut run)?;
        }
    }

    /// Sends new requests until the window is full, unless a failure stops new requests.
    fn fill_window(
        &mut self,
        run: &mut Run,
        requests: &mut impl Iterator<Item = Request>,
    ) -> Result<(), LinkError> {
        while !run.exhausted
            && run.failure.is_none()
            && run.window.len() < usize::from(self.adapt.window())
        {
            let Some(request) = requests.next() else {
                run.exhausted = true;
                break;
            };
            let seq = self.take_seq();
            let frame = self.encode(seq, &request)?;
            self.write(&frame)?;
            self.stats.requests += 1;
            let damage_at_send = self.damage_seen();
            run.window
                .push_back(InFlight::new(seq, request, frame, damage_at_send));
        }
        Ok(())
    }

    /// Waits for the next frame until the retransmission or a deadline is due, and takes it
    /// in. Fails with the timeout of a request whose deadline passed only if nothing came in
    /// and no write held the host up meanwhile.
    fn await_frame(&mut self, run: &mut Run, long_timeout: Duration) -> Result<(), LinkError> {
        let (wake, expired) = self.next_wake(run, long_timeout);
        let (corrupt, received) = (self.stats.corrupt_frames, self.stats.bytes_received);
        let frame = self.receive(wake)?;
        self.held += held_past(wake);
        let progressed = match frame {
            None => false,
            Some((up, bytes)) => {
                let (progressed, repeat) = self.on_frame(up, &mut run.window)?;
                if !repeat {
                    self.stats.bytes_received_clean += bytes as u64;
                }
                progressed
            }
        };
        let held = std::mem::take(&mut self.held);
        run.postpone(held);
        if progressed {
            run.progress = Instant::now();
        } else if let Some(timeout) = expired.filter(|_| held.is_zero()) {
            return Err(timeout);
        }
        // What the line did, for the chunk and window (see `adapt`).
        self.adapt
            .traffic((self.stats.bytes_received - received) as usize);
        for _ in corrupt..self.stats.corrupt_frames {
            self.adapt.damage();
        }
        Ok(())
    }

    /// When to stop waiting for a frame, and the timeout of the first request whose deadline
    /// has passed, if one has.
    ///
    /// A deadline that passed fails the run only if the line has nothing waiting either: the
    /// time may have gone on this side (a write held up by a slow target, a loaded machine)
    /// while the replies sat unread, so an expired run still reads for a few milliseconds.
    fn next_wake(&self, run: &Run, long_timeout: Duration) -> (Instant, Option<LinkError>) {
        let now = Instant::now();
        let mut wake = now + self.timeout;
        let mut expired = None;
        for entry in run.window.iter().filter(|e| e.reply.is_none()) {
            let deadline = self.deadline(entry, run.progress, long_timeout);
            if now >= deadline && expired.is_none() {
                expired = Some(LinkError::Timeout {
                    request: entry.request.name(),
                    after: now - entry.accepted.unwrap_or(run.progress),
                    retries: entry.retries,
                });
            }
            wake = wake.min(deadline);
        }
        // Only the oldest request without a reply runs a retransmit timer: the target handles
        // requests in order, so the later ones are held behind it (or were lost, which the
        // target NAKs once it gets past the gap).
        if let Some(oldest) = run.oldest_unanswered() {
            wake = wake.min(oldest.timer + self.backoff(oldest));
        }
        if expired.is_some() {
            wake = wake.max(now + Duration::from_millis(5));
        }
        (wake, expired)
    }

    /// Sends the oldest request without a reply again if its retransmit timer ran out, or
    /// gives up on it after `retries` quiet retransmissions of a request never accepted.
    fn retransmit_if_due(&mut self, run: &mut Run) -> Result<(), LinkError> {
        let now = Instant::now();
        let damage = self.damage_seen();
        let Some(entry) = run.window.iter_mut().find(|e| e.reply.is_none()) else {
            return Ok(());
        };
        if now < entry.timer + self.backoff(entry) {
            return Ok(());
        }
        // No damage since the last send: back off (a slow or absent target); damage: the line
        // is noisy, the target there, and waiting longer only loses time.
        if damage == entry.damage_at_send {
            entry.quiet += 1;
        } else {
            entry.quiet = 0;
        }
        if entry.accepted.is_none() && entry.quiet > self.config.retries {
            return Err(LinkError::Timeout {
                request: entry.request.name(),
                after: now - run.progress,
                retries: entry.retries,
            });
        }
        self.stats.timeouts += 1;
        self.retransmit(entry)
    }

    /// When a request without reply fails: [`Link::timeout`] after the last progress, or for a
    /// long-running request the target acknowledged, `long_timeout` after its `Ack`.
    fn deadline(&self, entry: &InFlight, progress: Instant, long_timeout: Duration) -> Instant {
        match entry.accepted {
            Some(at) => at + long_timeout,
            None => progress + self.timeout,
        }
    }

    /// The retransmit timeout for an entry's next retransmission.
    fn backoff(&self, entry: &InFlight) -> Duration {
        // Doubling from the adaptive base, while the line shows no damage, up to 8× the configured
        // timeout: a target that is merely slow (a long CRC check, a loaded host) is not flooded
        // with resends; the deadline still bounds the wait.
        let rto = (self.base_rto() * (1u32 << entry.quiet.min(10))).min(self.config.retransmit * 8);
        if entry.accepted.is_some() {
            // The target is working on it; resend only to recover a lost reply.
            rto.max(Duration::from_secs(1))
        } else {
            rto
        }
    }

    fn retransmit(&mut self, entry: &mut InFlight) -> Result<(), LinkError> {
        self.write(&entry.frame)?;
        self.stats.bytes_resent += entry.frame.len() as u64;
        entry.damage_at_send = self.damage_seen();
        entry.last_sent = Instant::now();
        entry.timer = entry.last_sent;
        entry.damage_counted = false;
        if entry.accepted.is_none() {
            entry.retries += 1;
        }
        self.stats.retransmits += 1;
        Ok(())
    }

    /// Takes one frame from the target: whether it acknowledged anything new (progress), and
    /// whether it was a repeat that a prompt, clean line would not have carried.
    fn on_frame(
        &mut self,
        up: Uplink,
        window: &mut VecDeque<InFlight>,
    ) -> Result<(bool, bool), LinkError> {
        let stale = self.stats.stale_answers;
        let progressed = match up {
            Uplink::Reply { seq, body } => self.on_reply(seq, body, window)?,
            Uplink::Ack { seq } => match window.iter_mut().find(|e| e.seq == seq) {
                Some(entry) if entry.accepted.is_none() => {
                    entry.accepted = Some(Instant::now());
                    true
                }
                // Accepted before, or no longer awaited: the answer to a retransmission.
                _ => return Ok((false, true)),
            },
            Uplink::Nak { expected } => return Ok((self.on_nak(expected, window)?, true)),
            Uplink::NotSynced { seq } => {
                if window.iter().any(|e| e.seq == seq) {
                    return Err(LinkError::TargetReset);
                }
                self.stats.stale_answers += 1;
                false
            }
            Uplink::Notice { seq, body } => {
                self.on_notice(seq, body);
                false
            }
            Uplink::Panic { message } => {
                return Err(LinkError::TargetPanicked {
                    message: message.to_string(),
                })
            }
        };
        Ok((progressed, self.stats.stale_answers > stale))
    }

    /// A reply: delivered to its request, and an acknowledgement of every request before it.
    fn on_reply(
        &mut self,
        seq: u16,
        body: Response,
        window: &mut VecDeque<InFlight>,
    ) -> Result<bool, LinkError> {
        // A handshake takes only a `Hello` (or a version complaint) as its answer: anything else
        // with its number is a previous session's.
        let Some(i) = window.iter().position(|e| {
            e.seq == seq
                && e.reply.is_none()
                && (!matches!(e.request, Request::Hello { .. }) || is_handshake_answer(&body))
        }) else {
            self.stats.stale_answers += 1;
            return Ok(false);
        };
        let was_oldest = window.iter().position(|e| e.reply.is_none()) == Some(i);
        window[i].reply = Some(body);
        let now = Instant::now();
        // Not the handshake's `Hello`: a QEMU pty passes it on only once QEMU notices the pty
        // was opened (up to a second), which says nothing about the line's round trip.
        let handshake = matches!(window[i].request, Request::Hello { .. });
        if was_oldest && window[i].retries == 0 && window[i].accepted.is_none() && !handshake {
            // How long the target took for it once it was the oldest: its frame's time on the
            // line and its handling, without the queue before it.
            let sample = now - window[i].timer;
            self.measure(sample);
        }
        // The next request without a reply starts its timer now.
        if was_oldest {
            if let Some(next) = window.iter_mut().find(|e| e.reply.is_none()) {
                next.timer = next.timer.max(now);
            }
        }
        self.fetch_lost_replies(window, i)?;
        Ok(true)
    }

    /// A NAK: resends the frame it names, and, since the target handles requests in order and
    /// names the one it waits for, acknowledges every request before that one.
    fn on_nak(
        &mut self,
        expected: u16,
        window: &mut VecDeque<InFlight>,
    ) -> Result<bool, LinkError> {
        self.stats.naks += 1;
        // The requests before `expected`; a NAK naming a number older than them all (a stale
        // one, or a target answering something outside this window) acknowledges nothing.
        let handled = window
            .iter()
            .take_while(|e| {
                let distance = expected.wrapping_sub(e.seq);
                distance != 0 && distance <= 2 * WINDOW
            })
            .count();
        let progress = window
            .iter()
            .take(handled)
            .any(|e| e.reply.is_none() && !e.handled);
        self.fetch_lost_replies(window, handled)?;
        let guard = self.nak_guard();
        if let Some(entry) = window
            .iter_mut()
            .find(|e| e.seq == expected && e.reply.is_none() && !e.damage_counted)
        {
            // One damaged frame however many NAKs name it before it is sent again.
            entry.damage_counted = true;
            self.adapt.damage();
        }
        if let Some(entry) = window.iter_mut().find(|e| e.seq == expected) {
            // Several NAKs may name the same frame (each corrupt frame that follows the loss
            // draws one); resend it at once, then at most once per round trip.
            let resent_lately = entry.retries > 0 && entry.last_sent.elapsed() < guard;
            if entry.reply.is_none() && !resent_lately {
                self.retransmit(entry)?;
            }
        }
        Ok(progress)
    }

    /// The first `handled` requests of the window were handled by the target: those still without
    /// a reply lost it (the target sends its replies in order, before whatever told us), so they
    /// are resent and the target answers them from its reply cache: at once when we learn it,
    /// then at most once per [`Self::nak_guard`] (the cached reply may be on its way).
    fn fetch_lost_replies(
        &mut self,
        window: &mut VecDeque<InFlight>,
        handled: usize,
    ) -> Result<(), LinkError> {
        let now = Instant::now();
        let guard = self.nak_guard();
        for entry in window.iter_mut().take(handled) {
            if entry.reply.is_some() {
                continue;
            }
            let news = !entry.handled;
            entry.handled = true;
            if news || now >= entry.last_sent + guard {
                self.retransmit(entry)?;
            }
        }
        Ok(())
    }

    /// Signs of a damaged line so far: NAKs and frames from the target that did not decode.
    fn damage_seen(&self) -> u64 {
        self.stats.naks + self.stats.corrupt_frames
    }

    /// Folds one service-time sample into `srtt` and `rttvar` (RFC 6298's estimator).
    fn measure(&mut self, sample: Duration) {
        match self.srtt {
            Some(srtt) => {
                let deviation = srtt.abs_diff(sample);
                self.rttvar = (self.rttvar * 3 + deviation) / 4;
                self.srtt = Some((srtt * 7 + sample) / 8);
            }
            None => {
                self.srtt = Some(sample);
                self.rttvar = sample / 2;
            }
        }
    }

    /// The retransmit timeout before back-off: the smoothed service time plus four times its
    /// variation (RFC 6298), at least [`MIN_RETRANSMIT`], at most the configured
    /// [`LinkConfig::retransmit`] (which is also the timeout until the first sample).
    fn base_rto(&self) -> Duration {
        let ceiling = self.config.retransmit;
        match self.srtt {
            Some(srtt) => (srtt + self.rttvar * 4).clamp(MIN_RETRANSMIT.min(ceiling), ceiling),
            None => ceiling,
        }
    }

    /// The least time between two sends of a frame prompted by NAKs or later replies: half the
    /// smoothed service time (at most a quarter of the retransmit timeout). The target sends
    /// about one NAK per damaged frame, and a NAK that arrives after a resend is as likely to be about the resent copy (which
    /// then waits behind the rest of the window) as about an older one: resending too often
    /// costs a frame's time on the line, not resending costs a retransmit timeout.
    fn nak_guard(&self) -> Duration {
        let rto = self.base_rto();
        (self.srtt.unwrap_or(rto) / 2).min(rto / 4)
    }

    fn on_notice(&mut self, seq: u16, body: Response) {
        self.stats.notices += 1;
        if let Some(last) = self.last_notice {
            let gap = seq.wrapping_sub(last).wrapping_sub(1);
            if gap < u16::MAX / 2 {
                self.stats.notices_lost += u64::from(gap);
            }
        }
        self.last_notice = Some(seq);
        if let Some(handler) = self.notice_handler.as_mut() {
            handler(seq, body);
        }
    }

    /// Writes bytes as they are, outside any frame: for tests that put noise on the line.
    pub fn send_raw(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        self.write(bytes)
    }

    pub fn port_mut(&mut self) -> &mut P {
        &mut self.port
    }

    fn encode(&self, seq: u16, request: &Request) -> Result<Vec<u8>, LinkError> {
        let mut out = vec![0u8; MAX_FRAME_LEN + 1];
        // The very first frame of a link is preceded by a lone delimiter, which ends whatever
        // partial frame the target may hold (noise from before the port was opened).
        let start = usize::from(!self.flushed);
        out[0] = DELIMITER;
        let len = frame::encode(&Envelope { seq, body: request }, &mut out[start..]).map_err(
            |source| LinkError::Encode {
                request: request.name(),
                source,
            },
        )?;
        out.truncate(start + len);
        Ok(out)
    }

    fn write(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        // A target that is slow to drain its input may hold up the write, but not forever.
        let started = Instant::now();
        self.port.set_timeout(self.timeout)?;
        self.port.write_all(bytes).map_err(io_error)?;
        self.port.flush().map_err(io_error)?;
        self.held += held_past(started);
        self.flushed = true;
        self.stats.bytes_sent += bytes.len() as u64;
        self.adapt.traffic(bytes.len());
        Ok(())
    }

    fn take_seq(&mut self) -> u16 {
        let seq = self.next_seq;
        self.next_seq = seq.wrapping_add(1);
        seq
    }

    /// The next well-formed frame, or `Nothing` once `deadline` passes (or the port's read
    /// returned nothing). Corrupt frames are counted and skipped.
    /// The frame comes with its length on the line (its encoded bytes and the delimiter).
    fn receive(&mut self, deadline: Instant) -> Result<Option<(Uplink, usize)>, LinkError> {
        loop {
            let stats = &mut self.stats;
            let event = self
                .reader
                .next(
                    &mut self.port,
                    deadline,
                    |n| stats.bytes_received += n as u64,
                    |body| (body.len() + 1, frame::decode::<Uplink>(body)),
                )
                .map_err(io_error)?;
            match event {
                FrameEvent::Frame((bytes, Ok(up))) => return Ok(Some((up, bytes))),
                FrameEvent::Frame((_, Err(e))) => {
                    self.stats.corrupt_frames += 1;
                    if e == deform_shared::frame::FrameError::Message {
                        self.stats.undecodable += 1;
                    }
                }
                FrameEvent::Overflow => self.stats.corrupt_frames += 1,
                FrameEvent::EndOfFile => {
                    return Err(LinkError::Disconnected("the port reached end of file"))
                }
                FrameEvent::TimedOut => return Ok(None),
            }
        }
    }
}

/// An I/O error, recognising a line that went away (QEMU exited, a board was unplugged).
fn io_error(e: std::io::Error) -> LinkError {
    // EIO is what a pty reports once its other end is closed.
    if matches!(
        e.kind(),
        ErrorKind::BrokenPipe | ErrorKind::UnexpectedEof | ErrorKind::ConnectionReset
    ) || e.raw_os_error() == Some(5)
    {
        return LinkError::Disconnected("the serial line closed");
    }
    if matches!(e.kind(), ErrorKind::TimedOut | ErrorKind::WouldBlock) {
        return LinkError::WriteStalled;
    }
    LinkError::Io(e)
}

fn is_handshake_answer(body: &Response) -> bool {
    matches!(
        body,
        Response::Hello(_) | Response::Error(ErrorCode::VersionMismatch { .. })
    )
}

/// A starting sequence number that differs between runs, so that replies still in flight from
/// a previous host process cannot match this one's first requests.
fn initial_seq() -> u16 {
    let nanos = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.subsec_nanos())
        .unwrap_or(0);
    let mixed = nanos ^ std::process::id().rotate_left(16);
    (mixed ^ (mixed >> 16)) as u16
}

#[cfg(test)]
mod tests;
