use deform_shared::protocol::{SolveParams, Start, TargetInfo, PROTOCOL_VERSION};

use super::*;

/// Collects every frame the link writes, decoded.
#[derive(Default)]
struct Wire {
    frames: std::vec::Vec<Uplink>,
    notices: std::vec::Vec<Response>,
}

impl Tx for Wire {
    fn write(&mut self, bytes: &[u8]) {
        let (last, body) = bytes.split_last().expect("a frame");
        assert_eq!(*last, frame::DELIMITER);
        let mut body = body.to_vec();
        self.frames
            .push(frame::decode(&mut body).expect("the link writes valid frames"));
    }
    fn pending_notice(&mut self) -> Option<Response> {
        self.notices.pop()
    }
}

fn info() -> TargetInfo {
    TargetInfo {
        protocol_version: PROTOCOL_VERSION,
        firmware_version: "t".try_into().unwrap(),
        harts: 1,
        word_capacity: 0,
        tile_capacity: 0,
        max_n: 0,
        build_id: Default::default(),
    }
}

/// A service that records the requests it handles and answers Hello or `Ack`.
struct Recorder(std::vec::Vec<Request>);

impl Recorder {
    fn handler(&mut self) -> impl FnMut(Request) -> Response + '_ {
        |request| {
            let answer = match request {
                Request::Hello { .. } => Response::Hello(info()),
                _ => Response::Ack,
            };
            self.0.push(request);
            answer
        }
    }
}

fn frame_of(seq: u16, body: Request) -> std::vec::Vec<u8> {
    let mut buf = [0u8; MAX_FRAME_LEN];
    let n = frame::encode(&Envelope { seq, body }, &mut buf).unwrap();
    buf[..n].to_vec()
}

fn hello() -> Request {
    Request::Hello {
        protocol_version: PROTOCOL_VERSION,
    }
}

fn end(crc32: u32) -> Request {
    Request::EndMatrix { crc32 }
}

fn feed_all(
    link: &mut TargetLink,
    bytes: &[u8],
    service: &mut Recorder,
    wire: &mut Wire,
) -> std::vec::Vec<LinkEvent> {
    let mut handler = service.handler();
    bytes
        .iter()
        .filter_map(|&b| link.feed(b, &mut handler, wire))
        .collect()
}

fn synced(seq: u16) -> (TargetLink, Recorder, Wire) {
    let mut link = TargetLink::new();
    let mut service = Recorder(vec![]);
    let mut wire = Wire::default();
    feed_all(&mut link, &frame_of(seq, hello()), &mut service, &mut wire);
    assert!(matches!(
        wire.frames.as_slice(),
        [Uplink::Reply { seq: s, body: Response::Hello(_) }] if *s == seq
    ));
    wire.frames.clear();
    (link, service, wire)
}

#[test]
fn before_hello_everything_else_is_not_synced_and_corrupt_frames_are_ignored() {
    let mut link = TargetLink::new();
    let mut service = Recorder(vec![]);
    let mut wire = Wire::default();
    let events = feed_all(&mut link, &frame_of(5, end(1)), &mut service, &mut wire);
    assert_eq!(events, [LinkEvent::NotSynced]);
    assert_eq!(wire.frames, [Uplink::NotSynced { seq: 5 }]);
    let events = feed_all(&mut link, &[1, 2, 3, 0], &mut service, &mut wire);
    assert!(matches!(events.as_slice(), [LinkEvent::Corrupt(_)]));
    assert_eq!(wire.frames.len(), 1, "no NAK before the handshake");
    assert!(service.0.is_empty());
    assert!(!link.synced());
}

#[test]
fn in_order_requests_are_handled_and_answered_with_their_numbers() {
    let (mut link, mut service, mut wire) = synced(0xFFFE);
    let mut bytes = frame_of(0xFFFF, end(1));
    bytes.extend(frame_of(0, end(2)));
    feed_all(&mut link, &bytes, &mut service, &mut wire);
    assert_eq!(
        wire.frames,
        [
            Uplink::Reply {
                seq: 0xFFFF,
                body: Response::Ack
            },
            Uplink::Reply {
                seq: 0,
                body: Response::Ack
            }
        ]
    );
    assert_eq!(service.0, [hello(), end(1), end(2)]);
}

#[test]
fn a_gap_is_naked_once_and_held_frames_are_handled_once_it_is_filled() {
    let (mut link, mut service, mut wire) = synced(10);
    // 11 is lost; 12 and 13 arrive.
    let mut bytes = frame_of(12, end(12));
    bytes.extend(frame_of(13, end(13)));
    let events = feed_all(&mut link, &bytes, &mut service, &mut wire);
    assert_eq!(events, [LinkEvent::Held, LinkEvent::Held]);
    assert_eq!(wire.frames, [Uplink::Nak { expected: 11 }]);
    wire.frames.clear();
    feed_all(&mut link, &frame_of(11, end(11)), &mut service, &mut wire);
    let seqs: std::vec::Vec<u16> = wire
        .frames
        .iter()
        .map(|f| match f {
            Uplink::Reply { seq, .. } => *seq,
            other => panic!("{other:?}"),
        })
        .collect();
    assert_eq!(seqs, [11, 12, 13]);
    assert_eq!(service.0[1..], [end(11), end(12), end(13)]);
}

#[test]
fn a_second_gap_is_naked_after_the_first_is_filled() {
    let (mut link, mut service, mut wire) = synced(0);
    // 1 and 3 are lost; 2 and 4 arrive.
    let mut bytes = frame_of(2, end(2));
    bytes.extend(frame_of(4, end(4)));
    feed_all(&mut link, &bytes, &mut service, &mut wire);
    assert_eq!(wire.frames, [Uplink::Nak { expected: 1 }]);
    wire.frames.clear();
    feed_all(&mut link, &frame_of(1, end(1)), &mut service, &mut wire);
    assert_eq!(wire.frames.last(), Some(&Uplink::Nak { expected: 3 }));
    wire.frames.clear();
    feed_all(&mut link, &frame_of(3, end(3)), &mut service, &mut wire);
    assert_eq!(wire.frames.len(), 2);
    assert_eq!(service.0[1..], [end(1), end(2), end(3), end(4)]);
}

#[test]
fn duplicates_get_the_cached_reply_and_are_not_handled_again() {
    let (mut link, mut service, mut wire) = synced(100);
    feed_all(&mut link, &frame_of(101, end(7)), &mut service, &mut wire);
    let first = wire.frames.clone();
    wire.frames.clear();
    let events = feed_all(&mut link, &frame_of(101, end(7)), &mut service, &mut wire);
    assert_eq!(events, [LinkEvent::Duplicate]);
    assert_eq!(wire.frames, first);
    assert_eq!(service.0.len(), 2);
    // A retransmitted Hello does not reset again.
    wire.frames.clear();
    let (mut link, mut service, mut wire2) = synced(7);
    let events = feed_all(&mut link, &frame_of(7, hello()), &mut service, &mut wire2);
    assert_eq!(events, [LinkEvent::Duplicate]);
    assert_eq!(service.0.len(), 1);
}

#[test]
fn corrupt_frames_are_naked_with_the_expected_number() {
    let (mut link, mut service, mut wire) = synced(40);
    let mut bytes = frame_of(41, end(1));
    bytes[3] ^= 0x08;
    let events = feed_all(&mut link, &bytes, &mut service, &mut wire);
    assert_eq!(events, [LinkEvent::Corrupt(FrameError::Crc)]);
    assert_eq!(wire.frames, [Uplink::Nak { expected: 41 }]);
    let overlong = vec![0x55; 2 * MAX_FRAME_LEN];
    let mut events = feed_all(&mut link, &overlong, &mut service, &mut wire);
    events.extend(feed_all(&mut link, &[0], &mut service, &mut wire));
    assert_eq!(events, [LinkEvent::Corrupt(FrameError::TooLong)]);
    assert_eq!(wire.frames.len(), 2);
}

#[test]
fn a_new_hello_resynchronises_anywhere() {
    let (mut link, mut service, mut wire) = synced(40);
    feed_all(&mut link, &frame_of(9000, hello()), &mut service, &mut wire);
    feed_all(&mut link, &frame_of(9001, end(3)), &mut service, &mut wire);
    assert_eq!(
        wire.frames.last(),
        Some(&Uplink::Reply {
            seq: 9001,
            body: Response::Ack
        })
    );
    // Far outside the window: NAKed, not handled.
    let events = feed_all(&mut link, &frame_of(20, end(4)), &mut service, &mut wire);
    assert_eq!(events, [LinkEvent::OutOfWindow]);
    assert_eq!(wire.frames.last(), Some(&Uplink::Nak { expected: 9002 }));
    assert_eq!(service.0.len(), 3);
}

#[test]
fn long_running_requests_are_acknowledged_first_and_notices_precede_replies() {
    let (mut link, mut service, mut wire) = synced(1);
    wire.notices.push(Response::Ack);
    let solve = Request::Solve(SolveParams {
        max_iterations: 1,
        tolerance: 0.1,
        start: Start::Zero,
        directions: 1,
        cycle_budget: 0,
    });
    feed_all(&mut link, &frame_of(2, solve), &mut service, &mut wire);
    assert_eq!(
        wire.frames,
        [
            Uplink::Ack { seq: 2 },
            Uplink::Notice {
                seq: 0,
                body: Response::Ack
            },
            Uplink::Reply {
                seq: 2,
                body: Response::Ack
            }
        ]
    );
}

#[test]
fn the_panic_frame_is_truncated_at_a_character_boundary() {
    let mut buf = [0u8; MAX_FRAME_LEN];
    let long: std::string::String = "é".repeat(100);
    let n = panic_frame(&long, &mut buf);
    let up: Uplink = frame::decode(&mut buf[..n - 1]).unwrap();
    match up {
        Uplink::Panic { message } => {
            assert_eq!(message.len(), PANIC_MESSAGE_LEN);
            assert!(message.chars().all(|c| c == 'é'));
        }
        other => panic!("{other:?}"),
    }
}
