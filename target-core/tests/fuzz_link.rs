//! Seeded fuzzing of everything the target does with UART bytes: the frame decoder (COBS, CRC),
//! the message decoder (postcard, behind a *valid* CRC so that the random bytes reach it), and
//! the whole target transport with the real session behind it. None may panic, whatever the
//! input. A fixed-seed generator drives them here, so they run in every `cargo test`; the
//! coverage-guided libFuzzer targets over the same code are in `fuzz/` (docs/PROTOCOL.md §8).
//!
//! `cargo test` runs a short round of each; the long run, at least a million inputs each, is
//!
//! ```text
//! cargo test --release -p deform-target-core --test fuzz_link -- --ignored --nocapture
//! ```

use std::time::Instant;

use deform_shared::frame::{self, FrameAccumulator, CRC32, DELIMITER};
use deform_shared::matrix::TileHeader;
use deform_shared::protocol::{
    Envelope, Request, Response, SolveParams, Start, TargetInfo, VectorSlot, CHUNK_LEN,
    MAX_FRAME_LEN, PROTOCOL_VERSION,
};
use deform_shared::transport::Uplink;
use deform_target_core::testkit::OwnedStorage;
use deform_target_core::transport::{TargetLink, Tx};

/// Inputs per fuzzer in the short run (every `cargo test`).
const SHORT: u64 = 20_000;
/// Inputs per fuzzer in the long run.
const LONG: u64 = 1_000_000;

/// xorshift64*: fixed seed, the same inputs every run.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n.max(1)
    }
    fn chance(&mut self, one_in: u64) -> bool {
        self.below(one_in) == 0
    }
    fn bytes(&mut self, len: usize) -> Vec<u8> {
        (0..len).map(|_| self.next() as u8).collect()
    }
    /// A number from a few interesting ranges: small, near a power of two, anything.
    fn number(&mut self) -> u32 {
        match self.below(4) {
            0 => self.below(8) as u32,
            1 => (1u32 << self.below(32))
                .wrapping_add(self.below(3) as u32)
                .wrapping_sub(1),
            2 => self.below(300) as u32,
            _ => self.next() as u32,
        }
    }
}

/// The body of a frame (without delimiter) around `payload`, with a valid CRC: COBS by hand,
/// since `frame::encode` only frames what it serialises itself (these tests must reach the
/// message decoder with bytes postcard never wrote).
fn valid_frame(payload: &[u8]) -> Vec<u8> {
    let mut data = payload.to_vec();
    data.extend(CRC32.checksum(payload).to_le_bytes());
    let mut out = Vec::with_capacity(data.len() + data.len() / 254 + 2);
    let mut code_at = 0;
    out.push(0);
    let mut code = 1u8;
    for &b in &data {
        if b == 0 {
            out[code_at] = code;
            code_at = out.len();
            out.push(0);
            code = 1;
        } else {
            out.push(b);
            code += 1;
            if code == 0xFF {
                out[code_at] = code;
                code_at = out.len();
                out.push(0);
                code = 1;
            }
        }
    }
    out[code_at] = code;
    out
}

/// A random, mostly well-formed request.
fn random_request(rng: &mut Rng) -> Request {
    let chunk_u32 = |rng: &mut Rng| -> heapless::Vec<u32, CHUNK_LEN> {
        let len = rng.below(CHUNK_LEN as u64 + 1) as usize;
        (0..len).map(|_| rng.number()).collect()
    };
    let chunk_i32 = |rng: &mut Rng| -> heapless::Vec<i32, CHUNK_LEN> {
        let len = rng.below(CHUNK_LEN as u64 + 1) as usize;
        (0..len)
            .map(|_| rng.number() as i32 >> rng.below(12))
            .collect()
    };
    let slot = |rng: &mut Rng| {
        // Mostly a valid direction, sometimes any.
        let direction = if rng.chance(8) {
            rng.number() as u8
        } else {
            rng.below(3) as u8
        };
        if rng.chance(2) {
            VectorSlot::Rhs { direction }
        } else {
            VectorSlot::InitialGuess { direction }
        }
    };
    match rng.below(12) {
        0 => Request::Hello {
            protocol_version: if rng.chance(8) {
                rng.number() as u16
            } else {
                PROTOCOL_VERSION
            },
        },
        1 => Request::BeginMatrix {
            n: rng.number(),
            frac_bits: rng.below(24) as u8,
            tiles: rng.number(),
            words: rng.number(),
        },
        2 => Request::Tile(TileHeader {
            row_base: rng.number(),
            col_base: rng.number(),
            rows: rng.number(),
            words: rng.number(),
            mvu: rng.below(4) as u8,
            mirrored: rng.chance(4),
        }),
        3 => Request::Words {
            offset: rng.number(),
            words: chunk_u32(rng),
        },
        4 => Request::EndMatrix {
            crc32: rng.number(),
        },
        5 => Request::BeginVector {
            slot: slot(rng),
            exponent: rng.number() as i32,
            len: rng.number(),
        },
        6 => Request::VectorData {
            slot: slot(rng),
            offset: rng.number(),
            mantissas: chunk_i32(rng),
        },
        7 => Request::Solve(SolveParams {
            max_iterations: rng.below(50) as u32,
            tolerance: f64::from_bits(rng.next()),
            start: match rng.below(4) {
                0 => Start::Zero,
                1 => Start::Previous,
                2 => Start::Uploaded,
                _ => Start::Predicted,
            },
            directions: rng.below(5) as u8,
            cycle_budget: rng.below(3) * u64::from(rng.number()),
        }),
        8 => Request::ReadSolution {
            direction: rng.below(4) as u8,
            offset: rng.number(),
            len: rng.below(200) as u16,
        },
        9 => Request::BeginUpdate {
            words: rng.number(),
            frac_bits: rng.below(24) as u8,
        },
        10 => Request::UpdateValues {
            offset: rng.number(),
            values: chunk_i32(rng),
        },
        _ => Request::EndUpdate {
            crc32: rng.number(),
        },
    }
}

fn encode_request(seq: u16, request: &Request) -> Vec<u8> {
    let mut buf = [0u8; MAX_FRAME_LEN];
    let n = frame::encode(&Envelope { seq, body: request }, &mut buf).unwrap();
    buf[..n].to_vec()
}

/// Damages `bytes` a little: flips, deletions, insertions, truncation.
fn mutate(rng: &mut Rng, bytes: &mut Vec<u8>) {
    for _ in 0..=rng.below(4) {
        if bytes.is_empty() {
            return;
        }
        let at = rng.below(bytes.len() as u64) as usize;
        match rng.below(4) {
            0 => bytes[at] ^= 1 << rng.below(8),
            1 => {
                bytes.remove(at);
            }
            2 => bytes.insert(at, rng.next() as u8),
            _ => bytes.truncate(at),
        }
    }
}

/// One input for the decoders: random bytes, a damaged real frame, or random payload bytes
/// behind a valid CRC.
fn decoder_input(rng: &mut Rng) -> Vec<u8> {
    match rng.below(3) {
        0 => {
            let len = rng.below(MAX_FRAME_LEN as u64) as usize;
            rng.bytes(len)
        }
        1 => {
            let request = random_request(rng);
            let mut f = encode_request(rng.next() as u16, &request);
            f.pop();
            mutate(rng, &mut f);
            f
        }
        _ => {
            let len = rng.below(600) as usize;
            valid_frame(&rng.bytes(len))
        }
    }
}

fn fuzz_frame_decoder(inputs: u64) {
    let mut rng = Rng(0xF4A3_E0DE_C0DE_0001);
    let started = Instant::now();
    let mut decoded = 0u64;
    for _ in 0..inputs {
        let input = decoder_input(&mut rng);
        decoded += u64::from(frame::decode::<Envelope<Request>>(&mut input.clone()).is_ok());
        let _ = frame::decode::<Uplink>(&mut input.clone());
    }
    println!(
        "frame decoder: {inputs} inputs ({decoded} decoded) in {:.1?}",
        started.elapsed()
    );
}

fn fuzz_message_decoder(inputs: u64) {
    let mut rng = Rng(0x3E55_A6E0_0000_0002);
    let started = Instant::now();
    let mut decoded = 0u64;
    for _ in 0..inputs {
        // Random payloads and damaged real messages, all behind a valid CRC.
        let payload = if rng.chance(2) {
            let len = rng.below(600) as usize;
            rng.bytes(len)
        } else {
            let request = random_request(&mut rng);
            let mut buf = [0u8; MAX_FRAME_LEN];
            let mut f = postcard_bytes(rng.next() as u16, &request, &mut buf);
            mutate(&mut rng, &mut f);
            f
        };
        let body = valid_frame(&payload);
        decoded += u64::from(frame::decode::<Envelope<Request>>(&mut body.clone()).is_ok());
        let _ = frame::decode::<Uplink>(&mut body.clone());
    }
    println!(
        "message decoder: {inputs} inputs ({decoded} decoded) in {:.1?}",
        started.elapsed()
    );
}

/// The postcard bytes of an envelope (the frame's payload before CRC and COBS).
fn postcard_bytes(seq: u16, request: &Request, buf: &mut [u8]) -> Vec<u8> {
    let mut body = encode_request(seq, request);
    body.pop();
    let len = cobs_decode(&mut body);
    let _ = buf;
    body.truncate(len - 4);
    body
}

/// COBS-decodes in place (through the frame module: a valid frame's payload plus CRC).
fn cobs_decode(body: &mut [u8]) -> usize {
    // Reverse COBS by hand: each code byte gives the distance to the next zero.
    let mut out = Vec::with_capacity(body.len());
    let mut i = 0;
    while i < body.len() {
        let code = body[i] as usize;
        i += 1;
        for _ in 1..code {
            out.push(body[i]);
            i += 1;
        }
        if code != 0xFF && i < body.len() {
            out.push(0);
        }
    }
    let crc = CRC32.checksum(&out[..out.len() - 4]).to_le_bytes();
    assert_eq!(
        &out[out.len() - 4..],
        crc,
        "the hand-made COBS decoder is right"
    );
    body[..out.len()].copy_from_slice(&out);
    out.len()
}

/// Sends nothing anywhere, but checks that every frame is well formed.
struct CheckedWire {
    frames: u64,
}

impl Tx for CheckedWire {
    fn write(&mut self, frame: &[u8]) {
        assert!(frame.len() <= MAX_FRAME_LEN && frame.last() == Some(&DELIMITER));
        let mut body = frame[..frame.len() - 1].to_vec();
        frame::decode::<Uplink>(&mut body).expect("the target writes valid frames");
        self.frames += 1;
    }
}

fn info() -> TargetInfo {
    TargetInfo {
        protocol_version: PROTOCOL_VERSION,
        firmware_version: "fuzz".try_into().unwrap(),
        harts: 2,
        word_capacity: 4096,
        tile_capacity: 16,
        max_n: 256,
        build_id: Default::default(),
    }
}

fn fuzz_target_link(inputs: u64) {
    let mut storage = OwnedStorage::for_info(&info());
    // Two MVUs, run one after the other, so tiles for MVU 1 are legal and 2, 3 refused.
    let mut session = storage.session(info(), 2);
    let mut link = Box::new(TargetLink::new());
    let mut wire = CheckedWire { frames: 0 };
    let mut rng = Rng(0x7A26_E71C_0000_0003);
    let mut seq: u16 = 0;
    let mut damaged = false;
    let mut handled = 0u64;
    let started = Instant::now();
    let mut handle = |request| {
        handled += 1;
        session.handle(request)
    };
    for _ in 0..inputs {
        // Mostly the next number, sometimes a repeat, a skip or anything (which loses the
        // sync until the next `Hello`).
        seq = match rng.below(40) {
            0 => seq.wrapping_sub(rng.below(10) as u16),
            1 => seq.wrapping_add(rng.below(10) as u16),
            2 => rng.next() as u16,
            // A damaged frame is sent again under its number, as the host would.
            _ if damaged => seq,
            _ => seq.wrapping_add(1),
        };
        damaged = false;
        let request = random_request(&mut rng);
        let mut bytes = encode_request(seq, &request);
        match rng.below(8) {
            0 => {
                mutate(&mut rng, &mut bytes);
                damaged = true;
            }
            1 => {
                damaged = true;
                let len = rng.below(2 * MAX_FRAME_LEN as u64) as usize;
                bytes = rng.bytes(len);
            }
            _ => {}
        }
        if damaged {
            // Whatever the damage, the next frame starts clean (a real host would resend until
            // one copy came through whole).
            bytes.push(DELIMITER);
        }
        for byte in bytes {
            link.feed(byte, &mut handle, &mut wire);
        }
    }
    println!(
        "target link + session: {inputs} frames, {handled} requests handled, {} frames \
         answered, in {:.1?}",
        wire.frames,
        started.elapsed()
    );
    assert!(wire.frames > 0);
    assert!(
        handled > inputs / 4,
        "too few requests reach the session: {handled}"
    );
}

/// The accumulator alone on an unbroken random stream (delimiters about one byte in 256).
fn fuzz_accumulator(inputs: u64) {
    let mut rng = Rng(0xACC0_0000_0000_0004);
    let mut acc = FrameAccumulator::<MAX_FRAME_LEN>::new();
    for _ in 0..inputs * 64 {
        let _ = acc.feed(rng.next() as u8);
    }
}

#[test]
fn the_frame_decoder_survives_random_input() {
    fuzz_frame_decoder(SHORT);
    fuzz_accumulator(SHORT);
}

#[test]
fn the_message_decoder_survives_random_input_behind_a_valid_crc() {
    fuzz_message_decoder(SHORT);
}

#[test]
fn the_target_link_and_session_survive_random_frames() {
    fuzz_target_link(SHORT);
}

#[test]
#[ignore = "the long fuzz run (a million inputs each); see the module doc"]
fn long_fuzz_a_million_inputs_each() {
    fuzz_frame_decoder(LONG);
    fuzz_accumulator(LONG);
    fuzz_message_decoder(LONG);
    fuzz_target_link(LONG);
}

#[test]
fn the_generators_reach_the_interesting_paths() {
    // Damaged frames must sometimes still decode (a mutation that misses) and random payloads
    // behind a valid CRC must sometimes decode as messages, or the fuzzers test little.
    let mut rng = Rng(9);
    let decoded = (0..5000)
        .filter(|_| {
            let request = random_request(&mut rng);
            let mut buf = [0u8; MAX_FRAME_LEN];
            let payload = postcard_bytes(7, &request, &mut buf);
            let mut body = valid_frame(&payload);
            // Compared as bytes: a random tolerance may be NaN, which is not equal to itself.
            frame::decode::<Envelope<Request>>(&mut body).is_ok_and(|back| {
                back.seq == 7 && postcard_bytes(7, &back.body, &mut buf) == payload
            })
        })
        .count();
    assert_eq!(
        decoded, 5000,
        "payloads re-framed with a valid CRC decode as themselves"
    );
    let _ = Response::Ack;
}
