//! In-process targets for the link's unit tests: a thread on the far end of a socket pair that
//! decodes the host's frames and answers them, either with the firmware's real transport and
//! session logic (`deform-target-core`) or with a script that misbehaves on purpose.

use std::io::{Read, Write};
use std::os::unix::net::UnixStream;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::thread;

use deform_shared::frame::{self, Feed, FrameAccumulator, FrameError};
use deform_shared::protocol::{
    Envelope, Request, Response, TargetInfo, MAX_FRAME_LEN, PROTOCOL_VERSION,
};
use deform_shared::transport::Uplink;
use deform_target_core::exec::Sequential;
use deform_target_core::session::Session;
use deform_target_core::testkit::OwnedStorage;
use deform_target_core::transport::{TargetLink, Tx};

/// What the fake target got from the host.
#[derive(Debug)]
pub enum Received {
    Request(Box<Envelope<Request>>),
    Unreadable(#[allow(dead_code)] FrameError),
}

/// One reply frame, delimiter included.
pub fn answer_frame(seq: u16, body: Response) -> Vec<u8> {
    uplink_frame(&Uplink::Reply { seq, body })
}

/// Any target frame, delimiter included.
pub fn uplink_frame(up: &Uplink) -> Vec<u8> {
    let mut buf = [0u8; MAX_FRAME_LEN];
    let len = frame::encode(up, &mut buf).expect("answers fit a frame");
    buf[..len].to_vec()
}

/// The info of a fake target with room for a few thousand words.
pub fn info() -> TargetInfo {
    TargetInfo {
        protocol_version: PROTOCOL_VERSION,
        firmware_version: "fake".try_into().unwrap(),
        harts: 1,
        word_capacity: 4096,
        tile_capacity: 16,
        max_n: 1024,
        build_id: [0xB1, 0x1D].as_slice().try_into().unwrap(),
    }
}

/// Answers every frame from the host with the bytes `answer` returns, until the host hangs up.
pub fn serve(mut stream: UnixStream, mut answer: impl FnMut(Received) -> Vec<u8> + Send + 'static) {
    thread::spawn(move || {
        let mut acc = FrameAccumulator::<MAX_FRAME_LEN>::new();
        let mut buf = [0u8; 256];
        loop {
            let n = match stream.read(&mut buf) {
                Ok(0) | Err(_) => return,
                Ok(n) => n,
            };
            for &byte in &buf[..n] {
                let received = match acc.feed(byte) {
                    Feed::Pending => continue,
                    Feed::Overflow => Received::Unreadable(FrameError::TooLong),
                    Feed::Frame(body) => match frame::decode(body) {
                        Ok(envelope) => Received::Request(Box::new(envelope)),
                        Err(e) => Received::Unreadable(e),
                    },
                };
                if stream.write_all(&answer(received)).is_err() {
                    return;
                }
            }
        }
    });
}

/// A target running the firmware's own transport and session logic with `info`'s capacities.
/// Returns the number of requests its session has handled so far.
pub fn serve_session(stream: UnixStream, info: TargetInfo) -> Arc<AtomicUsize> {
    serve_session_through(stream, info, |bytes| bytes.to_vec())
}

/// Like [`serve_session`], with every frame the target writes passed through `line` on its way
/// to the host (which may corrupt, drop or duplicate it), and every byte from the host through
/// the same `line` before it reaches the target.
pub fn serve_session_through(
    stream: UnixStream,
    info: TargetInfo,
    line: impl FnMut(&[u8]) -> Vec<u8> + Send + 'static,
) -> Arc<AtomicUsize> {
    serve_resetting(stream, info, line, None)
}

/// A fresh session over freshly leaked storage (the session borrows it for the test's life).
/// Its MVUs run one after another on this thread, as many as `info` reports.
fn fresh_session(info: TargetInfo) -> Session<'static, Sequential> {
    OwnedStorage::leaked_session(info)
}

/// Like [`serve_session_through`]; after `reset_after` handled requests the target "reboots":
/// a fresh transport (not synchronised) and a fresh, empty session.
pub fn serve_resetting(
    mut stream: UnixStream,
    info: TargetInfo,
    line: impl FnMut(&[u8]) -> Vec<u8> + Send + 'static,
    reset_after: Option<usize>,
) -> Arc<AtomicUsize> {
    let requests = Arc::new(AtomicUsize::new(0));
    let counter = Arc::clone(&requests);
    thread::spawn(move || {
        let mut session = fresh_session(info.clone());
        let mut link = Box::new(TargetLink::new());
        let mut line = line;
        let mut reset_pending = reset_after;
        let mut buf = [0u8; 1024];
        loop {
            let n = match stream.read(&mut buf) {
                Ok(0) | Err(_) => return,
                Ok(n) => n,
            };
            let received = line(&buf[..n]);
            let mut out = Outbox(Vec::new());
            for &byte in &received {
                let mut handle = |request| {
                    counter.fetch_add(1, Ordering::SeqCst);
                    session.handle(request)
                };
                link.feed(byte, &mut handle, &mut out);
                if reset_pending.is_some_and(|at| counter.load(Ordering::SeqCst) >= at) {
                    reset_pending = None;
                    session = fresh_session(info.clone());
                    *link = TargetLink::new();
                }
            }
            let sent = line(&out.0);
            if stream.write_all(&sent).is_err() {
                return;
            }
        }
    });
    requests
}

/// Collects the fake target's frames.
struct Outbox(Vec<u8>);

impl Tx for Outbox {
    fn write(&mut self, frame: &[u8]) {
        self.0.extend_from_slice(frame);
    }
}
