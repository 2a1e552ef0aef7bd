//! The fuzz harnesses: one function per cargo-fuzz target (`fuzz/fuzz_targets/*.rs` call them),
//! also run over the committed seed corpus and every crash found as plain tests
//! (`target-core/tests/fuzz_corpus.rs`), so a regression fails `cargo test` without libFuzzer.
//!
//! Each panics only on a broken invariant: the decoders must refuse bad input with an error,
//! and the target must answer every frame with well-formed frames.

extern crate std;

use std::vec;
use std::vec::Vec;

use deform_shared::frame::{self, Feed, FrameAccumulator, CRC32, DELIMITER};
use deform_shared::loader::{
    self, LoaderAction, LoaderEnvelope, LoaderInfo, LoaderRequest, LoaderResponse, LoaderSession,
    LOADER_FRAME_LEN, LOADER_PROTOCOL_VERSION,
};
use deform_shared::protocol::{
    Envelope, Request, StateVector, TargetInfo, CHUNK_LEN, MAX_FRAME_LEN, PROTOCOL_VERSION,
};
use deform_shared::transport::Uplink;

use super::OwnedStorage;
use crate::transport::{TargetLink, Tx};

/// The input split into records, each a two-byte little-endian length and that many bytes (the
/// last one takes what is left): how the stateful harnesses get a sequence of messages from one
/// input.
fn records(mut data: &[u8]) -> impl Iterator<Item = &[u8]> {
    core::iter::from_fn(move || {
        let (len, rest) = data.split_first_chunk::<2>()?;
        let (record, rest) = rest.split_at(usize::from(u16::from_le_bytes(*len)).min(rest.len()));
        data = rest;
        Some(record)
    })
}

/// The inverse of [`records`].
fn join(records: &[Vec<u8>]) -> Vec<u8> {
    let mut out = Vec::new();
    for r in records {
        out.extend((r.len() as u16).to_le_bytes());
        out.extend(r);
    }
    out
}

/// COBS + CRC around `payload`, delimiter included: a frame whose CRC is right whatever the
/// payload, so that random payloads reach the message decoder.
fn framed(payload: &[u8]) -> Vec<u8> {
    let mut data = payload.to_vec();
    data.extend(CRC32.checksum(payload).to_le_bytes());
    let mut out = vec![0; cobs::max_encoding_length(data.len()) + 1];
    let n = cobs::encode(&data, &mut out);
    out.truncate(n);
    out.push(DELIMITER);
    out
}

/// The frame decoder: the accumulator over the raw bytes, and every frame it yields decoded as
/// each message the two programs read. Nothing may panic.
pub fn frame_decoder(data: &[u8]) {
    let mut acc = FrameAccumulator::<MAX_FRAME_LEN>::new();
    for &byte in data {
        if let Feed::Frame(body) = acc.feed(byte) {
            let _ = frame::decode::<Envelope<Request>>(&mut body.to_vec());
            let _ = frame::decode::<Uplink>(&mut body.to_vec());
            let _ = loader::decode_frame::<LoaderRequest>(body);
        }
    }
    let _ = frame::decode::<Envelope<Request>>(&mut data.to_vec());
}

/// The message decoder behind a valid CRC: whatever decodes must encode again, and decode to
/// the same bytes once more (a decoded value is one the encoder can write).
pub fn message_decoder(data: &[u8]) {
    fn check<T>(data: &[u8])
    where
        T: serde::Serialize + for<'de> serde::Deserialize<'de>,
    {
        let mut body = framed(data);
        body.pop();
        let Ok(value) = frame::decode::<T>(&mut body) else {
            return;
        };
        let mut buf = [0u8; 2 * MAX_FRAME_LEN];
        let n = frame::encode(&value, &mut buf).expect("a decoded message encodes again");
        let again: T = frame::decode(&mut buf[..n - 1].to_vec()).expect("and decodes again");
        let mut buf2 = [0u8; 2 * MAX_FRAME_LEN];
        let m = frame::encode(&again, &mut buf2).expect("and encodes again");
        assert_eq!(&buf[..n], &buf2[..m], "re-encoding is stable");
    }
    check::<Envelope<Request>>(data);
    check::<Uplink>(data);
    check::<LoaderEnvelope<LoaderRequest>>(data);
    check::<LoaderEnvelope<LoaderResponse>>(data);
}

/// Checks every frame the target writes: delimited, within a frame's length, an `Uplink`.
struct CheckedWire;

impl Tx for CheckedWire {
    fn write(&mut self, frame: &[u8]) {
        assert!(frame.len() <= MAX_FRAME_LEN, "an overlong frame");
        assert_eq!(frame.last(), Some(&DELIMITER), "an undelimited frame");
        let mut body = frame[..frame.len() - 1].to_vec();
        frame::decode::<Uplink>(&mut body).expect("the target writes valid frames");
    }
}

/// A small target: two MVUs (run in turn), room for 2048 words, 8 tiles and n ≤ 64, so that
/// capacity limits are within the fuzzer's reach.
fn small_target() -> TargetInfo {
    TargetInfo {
        protocol_version: PROTOCOL_VERSION,
        firmware_version: "fuzz".try_into().expect("a short version"),
        harts: 2,
        word_capacity: 2048,
        tile_capacity: 8,
        max_n: 64,
        build_id: Default::default(),
    }
}

/// The target's transport and session, fed a sequence of frames. A record starting with 0 is
/// raw line bytes (noise, damaged frames); any other is the postcard bytes of a message, framed
/// with a valid CRC, so that the fuzzer explores the state machine behind the CRC.
pub fn target_session(data: &[u8]) {
    let info = small_target();
    let mut storage = OwnedStorage::for_info(&info);
    let mut session = storage.session(info, 2);
    let mut link = std::boxed::Box::new(TargetLink::new());
    let mut handle = |request| session.handle(request);
    for record in records(data) {
        let bytes = match record.split_first() {
            Some((0, raw)) => raw.to_vec(),
            Some((_, payload)) => framed(payload),
            None => continue,
        };
        for byte in bytes {
            link.feed(byte, &mut handle, &mut CheckedWire);
        }
    }
}

/// The loader's RAM in the harness: 16 KiB, the loader in its first KiB.
const RAM_START: u32 = 0x8000_0000;
const RAM_LEN: u32 = 16 * 1024;
const LOADER_END: u32 = RAM_START + 1024;

/// The loader's session, fed a sequence of requests (each record the postcard bytes of a
/// `LoaderEnvelope<LoaderRequest>`, through a frame with a valid CRC), doing its writes,
/// checksums and starts on a simulated RAM. It must never write outside the RAM or over itself,
/// never checksum outside the image, and only start a verified image at its entry.
pub fn loader(data: &[u8]) {
    let info = LoaderInfo {
        version: LOADER_PROTOCOL_VERSION,
        ram_start: RAM_START,
        ram_end: RAM_START + RAM_LEN,
        loader_start: RAM_START,
        loader_end: LOADER_END,
    };
    let mut ram = vec![0u8; RAM_LEN as usize];
    let mut session = LoaderSession::new();
    let mut last_begin = None;
    for record in records(data) {
        let mut body = framed(record);
        if body.len() > LOADER_FRAME_LEN {
            continue;
        }
        body.pop();
        let Ok(envelope) = loader::decode_frame::<LoaderRequest>(&mut body) else {
            continue;
        };
        if let LoaderRequest::Begin(header) = envelope.body {
            last_begin = Some(header);
        }
        let answer = match session.handle(&info, &envelope.body) {
            LoaderAction::Reply(answer) => answer,
            LoaderAction::Write { address, data } => {
                assert!(address >= LOADER_END, "a write over the loader");
                let at = (address - RAM_START) as usize;
                ram[at..at + data.len()].copy_from_slice(data);
                LoaderResponse::Ack
            }
            LoaderAction::Checksum { address, length } => {
                let image = last_begin.expect("a checksum needs an image");
                assert_eq!((address, length), (image.load_address, image.length));
                let at = (address - RAM_START) as usize;
                session.verified(CRC32.checksum(&ram[at..at + length as usize]))
            }
            LoaderAction::Start { entry } => {
                let image = last_begin.expect("a start needs an image");
                assert_eq!(entry, image.entry);
                let crc = CRC32.checksum(
                    &ram[(image.load_address - RAM_START) as usize..][..image.length as usize],
                );
                assert_eq!(crc, image.crc32, "only a verified image starts");
                LoaderResponse::Starting { entry }
            }
        };
        let mut out = [0u8; LOADER_FRAME_LEN];
        frame::encode(&LoaderEnvelope::new(envelope.seq, answer), &mut out)
            .expect("every answer fits a loader frame");
    }
}

/// A force tool (protocol 9) on the seed session's matrix: the tool, its compliance model,
/// the static loads of the three directions, a frame, a query and the field.
fn force_tool_requests() -> Vec<Request> {
    use deform_shared::live::LiveParams;
    use deform_shared::protocol::VectorSlot;
    let mut out = vec![
        Request::LiveForceTool {
            nodes: [3].into_iter().collect(),
        },
        Request::LiveStart(LiveParams {
            tolerance: 1e-4,
            max_iterations: 50,
            cycle_budget: 0,
            scale: [1.0, 2.0, 0.5],
        }),
    ];
    for direction in 0..3 {
        let slot = VectorSlot::Rhs { direction };
        out.push(Request::BeginVector {
            slot,
            exponent: 0,
            len: 8,
        });
        out.push(Request::VectorData {
            slot,
            offset: 0,
            mantissas: (0..8).map(|i| (i - 4) << 18).collect(),
        });
    }
    let load: heapless::Vec<[f32; 3], 8> = [[0.5, 0.0, -2.0]].into_iter().collect();
    out.push(Request::LiveLoad { load: load.clone() });
    out.push(Request::LiveLoadQuery { load });
    out.push(Request::ReadField {
        offset: 0,
        stride: 1,
        surface: None,
    });
    out
}

/// A dynamic session (protocol version 12) on the seed matrix: K's values (the matrix's own)
/// into the stiffness copy, a tool at node 3, the start and two steps.
fn dynamic_requests(system: &super::TestSystem) -> Vec<Request> {
    use deform_shared::dynamics::{DynamicParams, DynamicTool};
    use deform_shared::live::{Coupling, ToolRow};
    use deform_shared::matrix::words_crc;
    use deform_shared::word::VALUE_MASK;
    let values = system
        .words
        .iter()
        .map(|&w| (((w & VALUE_MASK) << 11) as i32) >> 11);
    let row = ToolRow {
        node: 3,
        diagonal: 2 << 18,
        row: [2, 4]
            .map(|column| Coupling {
                column,
                value: -(1 << 18),
            })
            .into_iter()
            .collect(),
    };
    let mut out = vec![
        Request::BeginStiffness {
            frac_bits: system.frac_bits,
        },
        Request::UpdateValues {
            offset: 0,
            values: values.collect(),
        },
        Request::EndUpdate {
            crc32: words_crc(&system.words),
        },
        Request::DynamicTool(DynamicTool {
            s: row.clone(),
            k: row,
        }),
        Request::DynamicStart(DynamicParams {
            h: 1e-3,
            mass: 0.5,
            s_scale: 0,
            k_scale: 0,
            tolerance: 1e-4,
            max_iterations: 50,
            cycle_budget: 0,
        }),
    ];
    for u in [0.01f32, 0.02] {
        out.push(Request::DynamicFrame {
            tool: [[0.0, -u, u]].into_iter().collect(),
        });
    }
    // The step's vectors (protocol version 13), the fuzzer's way into `ReadVector`.
    for vector in [
        StateVector::Rhs,
        StateVector::Velocity,
        StateVector::Residual,
    ] {
        out.push(Request::ReadVector {
            vector,
            direction: 2,
            offset: 0,
            len: CHUNK_LEN as u16,
        });
    }
    out
}

/// A whole session in request order, sequence numbers from 0: handshake, an 8×8 Laplacian in
/// one tile, a right-hand side, a solve, the solution, a surface field request.
fn session_requests() -> Vec<Envelope<Request>> {
    use deform_shared::matrix::words_crc;
    use deform_shared::protocol::{SolveParams, Start, VectorSlot};
    let system = super::encode_rows(8, 8, 8, 18, super::banded_row(8, 1));
    let requests = [
        Request::Hello {
            protocol_version: PROTOCOL_VERSION,
        },
        Request::BeginMatrix {
            n: system.n,
            frac_bits: system.frac_bits,
            tiles: 1,
            words: system.words.len() as u32,
        },
        Request::Tile(system.tiles[0]),
        Request::Words {
            offset: 0,
            words: system.words.iter().copied().collect(),
        },
        Request::EndMatrix {
            crc32: words_crc(&system.words),
        },
        Request::BeginVector {
            slot: VectorSlot::RHS,
            exponent: 0,
            len: 8,
        },
        Request::VectorData {
            slot: VectorSlot::RHS,
            offset: 0,
            mantissas: (0..8).map(|i| (i - 4) << 20).collect(),
        },
        Request::Solve(SolveParams {
            max_iterations: 50,
            tolerance: 1e-6,
            start: Start::Zero,
            directions: 1,
            cycle_budget: 0,
        }),
        Request::ReadSolution {
            direction: 0,
            offset: 0,
            len: CHUNK_LEN as u16,
        },
        // The 8 nodes as a 2 × 2 × 2 box: the field path's checks (refused: no live frame).
        Request::ReadField {
            offset: 0,
            stride: 1,
            surface: Some([2, 2, 2]),
        },
    ];
    requests
        .into_iter()
        .chain(force_tool_requests())
        .chain(dynamic_requests(&system))
        .enumerate()
        .map(|(seq, body)| Envelope {
            seq: seq as u16,
            body,
        })
        .collect()
}

/// A whole loader session: an image of 300 bytes loaded, verified and started.
fn loader_requests() -> Vec<LoaderEnvelope<LoaderRequest>> {
    use deform_shared::loader::{ImageHeader, LOADER_CHUNK};
    let image: Vec<u8> = (0..300u32).map(|i| (i * 7) as u8).collect();
    let header = ImageHeader {
        load_address: LOADER_END,
        length: image.len() as u32,
        entry: LOADER_END + 4,
        crc32: CRC32.checksum(&image),
    };
    let mut requests = vec![
        LoaderRequest::Hello {
            version: LOADER_PROTOCOL_VERSION,
        },
        LoaderRequest::Begin(header),
    ];
    for (index, chunk) in image.chunks(LOADER_CHUNK).enumerate() {
        requests.push(LoaderRequest::Chunk {
            index: index as u32,
            data: chunk.iter().copied().collect(),
        });
    }
    requests.extend([LoaderRequest::Verify, LoaderRequest::Start]);
    requests
        .into_iter()
        .enumerate()
        .map(|(seq, body)| LoaderEnvelope::new(seq as u16, body))
        .collect()
}

/// The seed corpus of each target, `(target, name, input)`: well-formed sessions, so that the
/// fuzzer starts from the deep states and mutates from there. `cargo run -p
/// deform-target-core --features testkit --example fuzz_seeds` writes them to `fuzz/corpus/`.
pub fn seeds() -> Vec<(&'static str, &'static str, Vec<u8>)> {
    let payload = |e: &Envelope<Request>| postcard_vec(e);
    let session = session_requests();
    let mut line = Vec::new();
    for e in &session {
        let mut buf = [0u8; MAX_FRAME_LEN];
        let n = frame::encode(e, &mut buf).expect("seeds fit a frame");
        line.extend(&buf[..n]);
    }
    let payloads: Vec<Vec<u8>> = session.iter().map(payload).collect();
    let session_records: Vec<Vec<u8>> = payloads
        .iter()
        .map(|p| {
            let mut r = vec![1];
            r.extend(p);
            r
        })
        .collect();
    let loader_records: Vec<Vec<u8>> = loader_requests().iter().map(postcard_vec).collect();
    vec![
        ("frame_decoder", "session", line),
        ("message_decoder", "words", payloads[3].clone()),
        ("message_decoder", "solve", payloads[7].clone()),
        ("target_session", "session", join(&session_records)),
        ("loader", "load_and_start", join(&loader_records)),
    ]
}

fn postcard_vec<T: serde::Serialize>(value: &T) -> Vec<u8> {
    let mut buf = [0u8; 2 * MAX_FRAME_LEN];
    let bytes = postcard::to_slice(value, &mut buf).expect("seeds encode");
    bytes.to_vec()
}

#[cfg(test)]
mod tests {
    use super::*;
    use deform_shared::protocol::Response;

    /// The seed session reaches the force tool's answers (not refusals), so the fuzzer starts
    /// from inside the live state machine.
    #[test]
    fn the_seed_session_reaches_the_force_tools_and_dynamic_answers() {
        let info = small_target();
        let mut storage = OwnedStorage::for_info(&info);
        let mut session = storage.session(info, 2);
        let answers: std::vec::Vec<Response> = session_requests()
            .into_iter()
            .map(|e| session.handle(e.body))
            .collect();
        let dynamic = dynamic_requests(&crate::testkit::encode_rows(
            8,
            8,
            8,
            18,
            crate::testkit::banded_row(8, 1),
        ));
        let (live, tail) = answers.split_at(answers.len() - dynamic.len());
        let live = &live[live.len() - 3..];
        assert!(matches!(live[0], Response::LiveMotion(_)), "{answers:?}");
        assert!(matches!(live[1], Response::LiveMotionQuery(_)), "{live:?}");
        assert!(matches!(live[2], Response::Field(_)), "{live:?}");
        // And the dynamic frames' answers, not refusals.
        assert!(tail[..5].iter().all(|a| *a == Response::Ack), "{tail:?}");
        let (frames, vectors) = tail[5..].split_at(tail.len() - 8);
        assert!(
            frames.iter().all(|a| matches!(a, Response::LiveFrame(_))),
            "{tail:?}"
        );
        // And the step's b, v and r (protocol version 13).
        assert!(
            vectors
                .iter()
                .all(|a| matches!(a, Response::Solution { direction: 2, .. })),
            "{tail:?}"
        );
    }
}
