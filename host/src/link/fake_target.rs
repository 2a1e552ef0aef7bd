//! In-process targets for the link's unit tests: a thread on the far end of a socket pair that
//! decodes the host's frames and answers them, either with the firmware's real session logic
//! (`deform-target-core`) or with a script that misbehaves on purpose.

use std::io::{Read, Write};
use std::os::unix::net::UnixStream;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::thread;

use deform_shared::frame::{self, Feed, FrameAccumulator, FrameError};
use deform_shared::matrix::TileHeader;
use deform_shared::protocol::{
    Envelope, Request, Response, TargetInfo, MAX_FRAME_LEN, PROTOCOL_VERSION, UNKNOWN_SEQ,
};
use deform_target_core::exec::Sequential;
use deform_target_core::session::{DirectionStorage, Session, Storage};

/// What the fake target got from the host.
#[derive(Debug)]
pub enum Received {
    Request(Box<Envelope<Request>>),
    Unreadable(FrameError),
}

/// One answer frame, delimiter included.
pub fn answer_frame(seq: u16, body: Response) -> Vec<u8> {
    let mut buf = [0u8; MAX_FRAME_LEN];
    let len = frame::encode(&Envelope { seq, body }, &mut buf).expect("answers fit a frame");
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

/// A target running the firmware's own session logic with `info`'s capacities. Returns the
/// number of requests it has received so far.
pub fn serve_session(stream: UnixStream, info: TargetInfo) -> Arc<AtomicUsize> {
    let requests = Arc::new(AtomicUsize::new(0));
    let counter = Arc::clone(&requests);
    let n = info.max_n as usize;
    // The session borrows its storage, so the storage is leaked for the test's lifetime.
    let direction = || DirectionStorage {
        b: vec![0; n].leak(),
        x: vec![0; n].leak(),
        x0: vec![0; n].leak(),
        r: vec![0; n].leak(),
    };
    let storage = Storage {
        words: vec![0; info.word_capacity as usize].leak(),
        tiles: vec![TileHeader::default(); info.tile_capacity as usize].leak(),
        directions: [direction(), direction(), direction()],
        p: vec![[0; 4]; n].leak(),
        kp: vec![[0; 3]; n].leak(),
        partial: vec![[0; 3]; 2 * n].leak(),
    };
    // The session's MVUs run one after another on this thread, as many as `info` reports.
    let harts = Sequential {
        harts: usize::from(info.harts),
    };
    let mut session = Session::new(storage, info, harts);
    serve(stream, move |received| match received {
        Received::Request(req) => {
            counter.fetch_add(1, Ordering::SeqCst);
            answer_frame(req.seq, session.handle(req.body))
        }
        Received::Unreadable(e) => answer_frame(
            UNKNOWN_SEQ,
            Response::Error(deform_shared::protocol::ErrorCode::Frame(e)),
        ),
    });
    requests
}
