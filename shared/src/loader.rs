//! The loader protocol: how the host puts an application image into the target's RAM through
//! the serial loader (`firmware/src/bin/loader.rs`) and starts it, like a soft core on an FPGA
//! that boots a small loader from on-chip RAM and receives its application over the UART.
//!
//! Frames are the application's ([`crate::frame`]: postcard, CRC-32, COBS, `0x00`), each holding
//! a [`LoaderEnvelope`]: the magic bytes [`LOADER_MAGIC`] and a sequence number. The magic makes
//! the two programs' frames impossible to mistake for each other (no application frame starts
//! with the bytes `D L`), so each end can tell which program it is talking to.
//!
//! The host sends one request at a time and waits for the answer with the same sequence number
//! (stop and wait: the image is small and the loader simple). A frame that does not decode is
//! answered with [`LoaderError::Frame`] and sequence number [`UNKNOWN_SEQ`]; the host then
//! resends its request.
//!
//! Session:
//!
//! 1. `Hello { version }` → `Hello(LoaderInfo)`: the loader's version, the RAM it may write and
//!    the range it occupies itself.
//! 2. `Begin(ImageHeader)` → `Ack`: load address, length, entry point and the CRC-32 of the whole
//!    image. Refused if the image leaves RAM, overlaps the loader, or its entry lies outside it.
//!    A new `Begin` discards any previous image.
//! 3. `Chunk { index, data }` → `Ack`, for `index` = 0, 1, … in order: bytes
//!    `index·LOADER_CHUNK ..` of the image, [`LOADER_CHUNK`] bytes each but the last. A chunk
//!    already received is accepted again (its `Ack` may have been lost); one beyond the next
//!    expected is refused with [`LoaderError::ChunkOutOfOrder`].
//! 4. `Verify` → `Verified { crc32 }` once every chunk is in and the CRC-32 of the image *as it
//!    is in RAM* equals the header's; otherwise an error, and the image cannot be started.
//! 5. `Start` → `Starting { entry }`, then the loader jumps to `entry`. Only a verified image
//!    starts: anything else is [`LoaderError::NotVerified`].

use heapless::Vec;
use serde::{Deserialize, Serialize};

use crate::frame::FrameError;
pub use crate::frame::CRC32;

/// Bumped on any change to these types.
pub const LOADER_PROTOCOL_VERSION: u16 = 1;

/// The sequence number of the loader's answer to a frame it could not read (so it cannot know
/// the frame's number): the host takes it as "resend". The application protocol does not use it;
/// its transport answers an unreadable frame with a NAK.
pub const UNKNOWN_SEQ: u16 = 0xFFFF;

/// The first bytes of every loader frame's message.
pub const LOADER_MAGIC: [u8; 2] = *b"DL";

/// What every loader frame holds: [`LOADER_MAGIC`], a sequence number and the message.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct LoaderEnvelope<T> {
    pub magic: [u8; 2],
    pub seq: u16,
    pub body: T,
}

impl<T> LoaderEnvelope<T> {
    pub fn new(seq: u16, body: T) -> Self {
        LoaderEnvelope {
            magic: LOADER_MAGIC,
            seq,
            body,
        }
    }
}

/// Decodes a loader frame in place, like [`crate::frame::decode`]; a frame with a good CRC but
/// without the magic (an application's) is [`FrameError::Message`].
pub fn decode_frame<'a, T: Deserialize<'a>>(
    frame: &'a mut [u8],
) -> Result<LoaderEnvelope<T>, FrameError> {
    let envelope: LoaderEnvelope<T> = crate::frame::decode(frame)?;
    if envelope.magic != LOADER_MAGIC {
        return Err(FrameError::Message);
    }
    Ok(envelope)
}

/// Image bytes per chunk.
pub const LOADER_CHUNK: usize = 256;

/// Largest frame, delimiter included, either side sends: a `Chunk` (≈ 270 bytes) with room.
pub const LOADER_FRAME_LEN: usize = 320;

/// Where a flat image goes and how it starts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct ImageHeader {
    /// Address of the image's first byte.
    pub load_address: u32,
    /// Bytes in the image.
    pub length: u32,
    /// Where execution starts; inside the image.
    pub entry: u32,
    /// CRC-32 ([`CRC32`]) of all `length` bytes.
    pub crc32: u32,
}

impl ImageHeader {
    /// One past the image's last byte, or `None` if that overflows the address space.
    pub fn end(&self) -> Option<u32> {
        self.load_address.checked_add(self.length)
    }

    /// Chunks the image takes.
    pub fn chunks(&self) -> u32 {
        self.length.div_ceil(LOADER_CHUNK as u32)
    }

    /// Bytes chunk `index` must hold.
    pub fn chunk_len(&self, index: u32) -> u32 {
        let start = index.saturating_mul(LOADER_CHUNK as u32);
        self.length.saturating_sub(start).min(LOADER_CHUNK as u32)
    }

    /// Checks the header against what the loader may write; the loader and the host (before it
    /// sends anything) both call this.
    pub fn check(&self, info: &LoaderInfo) -> Result<(), LoaderError> {
        let start = self.load_address;
        let Some(end) = self.end().filter(|_| self.length > 0) else {
            return Err(if self.length == 0 {
                LoaderError::EmptyImage
            } else {
                LoaderError::OutOfRange {
                    start,
                    end: u32::MAX,
                }
            });
        };
        if start < info.ram_start || end > info.ram_end {
            return Err(LoaderError::OutOfRange { start, end });
        }
        if start < info.loader_end && info.loader_start < end {
            return Err(LoaderError::OverlapsLoader { start, end });
        }
        if !(start..end).contains(&self.entry) {
            return Err(LoaderError::EntryOutsideImage { entry: self.entry });
        }
        Ok(())
    }
}

/// What the loader says about itself.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct LoaderInfo {
    pub version: u16,
    /// The RAM an image may occupy: `ram_start..ram_end`.
    pub ram_start: u32,
    pub ram_end: u32,
    /// What the loader itself occupies (code, data, stack), which no image may overlap.
    pub loader_start: u32,
    pub loader_end: u32,
}

// `Chunk` is large by design (one frame's worth of image); no_std has no Box to shrink it.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub enum LoaderRequest {
    Hello {
        version: u16,
    },
    Begin(ImageHeader),
    Chunk {
        index: u32,
        data: Vec<u8, LOADER_CHUNK>,
    },
    Verify,
    Start,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum LoaderResponse {
    Hello(LoaderInfo),
    Ack,
    Verified { crc32: u32 },
    Starting { entry: u32 },
    Error(LoaderError),
}

/// Every error the loader answers with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, thiserror::Error)]
pub enum LoaderError {
    #[error("bad frame: {0}")]
    Frame(FrameError),
    #[error("loader protocol version mismatch: the loader speaks {loader}")]
    VersionMismatch { loader: u16 },
    #[error("no image announced (Begin first)")]
    NoImage,
    #[error("the image is empty")]
    EmptyImage,
    #[error("image {start:#010x}..{end:#010x} is not inside the loadable RAM")]
    OutOfRange { start: u32, end: u32 },
    #[error("image {start:#010x}..{end:#010x} overlaps the loader itself")]
    OverlapsLoader { start: u32, end: u32 },
    #[error("entry point {entry:#010x} is outside the image")]
    EntryOutsideImage { entry: u32 },
    #[error("chunk {got} arrived, chunk {expected} was expected")]
    ChunkOutOfOrder { expected: u32, got: u32 },
    #[error("chunk {index} holds {got} bytes, it must hold {expected}")]
    ChunkLength { index: u32, expected: u32, got: u32 },
    #[error("only {received} of {chunks} chunks have arrived")]
    ImageIncomplete { received: u32, chunks: u32 },
    #[error("image CRC mismatch: the header says {expected:#010x}, RAM holds {computed:#010x}")]
    ImageCrc { expected: u32, computed: u32 },
    #[error("the image has not been verified (Verify must succeed before Start)")]
    NotVerified,
}

/// The loader's side of a session, without hardware: it checks every request and says where
/// each chunk goes; the loader binary does the memory writes, the CRC over RAM and the jump.
/// Kept here so that its rules are unit-tested on the host.
#[derive(Debug, Clone, Default)]
pub struct LoaderSession {
    image: Option<ImageHeader>,
    /// Chunks stored so far (the next one expected).
    received: u32,
    verified: bool,
}

/// What the loader binary must do for a request, once [`LoaderSession::handle`] accepted it.
#[derive(Debug, PartialEq, Eq)]
pub enum LoaderAction<'a> {
    /// Answer at once.
    Reply(LoaderResponse),
    /// Copy `data` to `address`, then answer `Ack`.
    Write { address: u32, data: &'a [u8] },
    /// Compute the CRC-32 of `length` bytes at `address` and pass it to
    /// [`LoaderSession::verified`] for the answer.
    Checksum { address: u32, length: u32 },
    /// Answer `Starting { entry }`, then jump to `entry`.
    Start { entry: u32 },
}

impl LoaderSession {
    pub const fn new() -> Self {
        LoaderSession {
            image: None,
            received: 0,
            verified: false,
        }
    }

    pub fn handle<'a>(
        &mut self,
        info: &LoaderInfo,
        request: &'a LoaderRequest,
    ) -> LoaderAction<'a> {
        let error = |e| LoaderAction::Reply(LoaderResponse::Error(e));
        match request {
            LoaderRequest::Hello { version } if *version != LOADER_PROTOCOL_VERSION => {
                error(LoaderError::VersionMismatch {
                    loader: LOADER_PROTOCOL_VERSION,
                })
            }
            LoaderRequest::Hello { .. } => {
                *self = LoaderSession::new();
                LoaderAction::Reply(LoaderResponse::Hello(*info))
            }
            LoaderRequest::Begin(header) => {
                *self = LoaderSession::new();
                if let Err(e) = header.check(info) {
                    return error(e);
                }
                self.image = Some(*header);
                LoaderAction::Reply(LoaderResponse::Ack)
            }
            LoaderRequest::Chunk { index, data } => {
                let Some(image) = self.image else {
                    return error(LoaderError::NoImage);
                };
                if *index > self.received || *index >= image.chunks() {
                    return error(LoaderError::ChunkOutOfOrder {
                        expected: self.received,
                        got: *index,
                    });
                }
                let expected = image.chunk_len(*index);
                if data.len() as u32 != expected {
                    return error(LoaderError::ChunkLength {
                        index: *index,
                        expected,
                        got: data.len() as u32,
                    });
                }
                if *index == self.received {
                    self.received += 1;
                }
                self.verified = false;
                LoaderAction::Write {
                    address: image.load_address + index * LOADER_CHUNK as u32,
                    data,
                }
            }
            LoaderRequest::Verify => {
                let Some(image) = self.image else {
                    return error(LoaderError::NoImage);
                };
                if self.received < image.chunks() {
                    return error(LoaderError::ImageIncomplete {
                        received: self.received,
                        chunks: image.chunks(),
                    });
                }
                LoaderAction::Checksum {
                    address: image.load_address,
                    length: image.length,
                }
            }
            LoaderRequest::Start => match self.image {
                Some(image) if self.verified => LoaderAction::Start { entry: image.entry },
                _ => error(LoaderError::NotVerified),
            },
        }
    }

    /// The answer to `Verify`, given the CRC-32 of the image as it is in RAM.
    pub fn verified(&mut self, computed: u32) -> LoaderResponse {
        let expected = self.image.map_or(0, |i| i.crc32);
        self.verified = self.image.is_some() && computed == expected;
        if self.verified {
            LoaderResponse::Verified { crc32: computed }
        } else {
            LoaderResponse::Error(LoaderError::ImageCrc { expected, computed })
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame;

    const INFO: LoaderInfo = LoaderInfo {
        version: LOADER_PROTOCOL_VERSION,
        ram_start: 0x8000_0000,
        ram_end: 0x8400_0000,
        loader_start: 0x8300_0000,
        loader_end: 0x8310_0000,
    };

    fn header(length: u32, crc32: u32) -> ImageHeader {
        ImageHeader {
            load_address: 0x8000_0000,
            length,
            entry: 0x8000_0000,
            crc32,
        }
    }

    fn chunk(index: u32, len: usize) -> LoaderRequest {
        LoaderRequest::Chunk {
            index,
            data: (0..len).map(|i| i as u8).collect(),
        }
    }

    fn reply(action: LoaderAction) -> LoaderResponse {
        match action {
            LoaderAction::Reply(r) => r,
            other => panic!("expected a reply, got {other:?}"),
        }
    }

    #[test]
    fn headers_that_leave_ram_overlap_the_loader_or_miss_their_entry_are_refused() {
        let ok = header(1000, 0);
        assert_eq!(ok.check(&INFO), Ok(()));
        let cases = [
            (header(0, 0), LoaderError::EmptyImage),
            (
                ImageHeader {
                    load_address: 0x7FFF_FF00,
                    ..ok
                },
                LoaderError::OutOfRange {
                    start: 0x7FFF_FF00,
                    end: 0x7FFF_FF00 + 1000,
                },
            ),
            (
                ImageHeader {
                    load_address: 0x83FF_FF00,
                    entry: 0x83FF_FF00,
                    ..ok
                },
                LoaderError::OutOfRange {
                    start: 0x83FF_FF00,
                    end: 0x83FF_FF00 + 1000,
                },
            ),
            (
                ImageHeader {
                    load_address: 0xFFFF_FF00,
                    ..ok
                },
                LoaderError::OutOfRange {
                    start: 0xFFFF_FF00,
                    end: u32::MAX,
                },
            ),
            (
                ImageHeader {
                    load_address: 0x830F_FF00,
                    entry: 0x830F_FF00,
                    ..ok
                },
                LoaderError::OverlapsLoader {
                    start: 0x830F_FF00,
                    end: 0x830F_FF00 + 1000,
                },
            ),
            (
                ImageHeader {
                    entry: 0x8000_0000 + 1000,
                    ..ok
                },
                LoaderError::EntryOutsideImage {
                    entry: 0x8000_0000 + 1000,
                },
            ),
        ];
        for (h, e) in cases {
            assert_eq!(h.check(&INFO), Err(e), "{h:?}");
            let mut s = LoaderSession::new();
            assert_eq!(
                reply(s.handle(&INFO, &LoaderRequest::Begin(h))),
                LoaderResponse::Error(e)
            );
            // Nothing was accepted: chunks have no image to go to.
            assert_eq!(
                reply(s.handle(&INFO, &chunk(0, LOADER_CHUNK))),
                LoaderResponse::Error(LoaderError::NoImage)
            );
        }
    }

    #[test]
    fn chunks_go_in_order_repeats_are_accepted_and_only_a_verified_image_starts() {
        let mut s = LoaderSession::new();
        let h = header(LOADER_CHUNK as u32 + 10, 0x1234);
        assert_eq!(
            reply(s.handle(&INFO, &LoaderRequest::Start)),
            LoaderResponse::Error(LoaderError::NotVerified)
        );
        assert_eq!(
            reply(s.handle(&INFO, &LoaderRequest::Begin(h))),
            LoaderResponse::Ack
        );
        assert_eq!(
            reply(s.handle(&INFO, &chunk(1, 10))),
            LoaderResponse::Error(LoaderError::ChunkOutOfOrder {
                expected: 0,
                got: 1
            })
        );
        assert_eq!(
            reply(s.handle(&INFO, &chunk(0, 10))),
            LoaderResponse::Error(LoaderError::ChunkLength {
                index: 0,
                expected: LOADER_CHUNK as u32,
                got: 10
            })
        );
        let first = chunk(0, LOADER_CHUNK);
        assert!(matches!(
            s.handle(&INFO, &first),
            LoaderAction::Write {
                address: 0x8000_0000,
                ..
            }
        ));
        assert_eq!(
            reply(s.handle(&INFO, &LoaderRequest::Verify)),
            LoaderResponse::Error(LoaderError::ImageIncomplete {
                received: 1,
                chunks: 2
            })
        );
        // A retransmission of chunk 0 (its Ack was lost) is written again.
        assert!(matches!(
            s.handle(&INFO, &first),
            LoaderAction::Write { .. }
        ));
        assert!(matches!(
            s.handle(&INFO, &chunk(1, 10)),
            LoaderAction::Write {
                address,
                data
            } if address == 0x8000_0000 + LOADER_CHUNK as u32 && data.len() == 10
        ));
        assert_eq!(
            reply(s.handle(&INFO, &chunk(2, 10))),
            LoaderResponse::Error(LoaderError::ChunkOutOfOrder {
                expected: 2,
                got: 2
            })
        );
        assert_eq!(
            s.handle(&INFO, &LoaderRequest::Verify),
            LoaderAction::Checksum {
                address: 0x8000_0000,
                length: LOADER_CHUNK as u32 + 10
            }
        );
        // A wrong CRC: never started.
        assert_eq!(
            s.verified(0x9999),
            LoaderResponse::Error(LoaderError::ImageCrc {
                expected: 0x1234,
                computed: 0x9999
            })
        );
        assert_eq!(
            reply(s.handle(&INFO, &LoaderRequest::Start)),
            LoaderResponse::Error(LoaderError::NotVerified)
        );
        assert_eq!(
            s.verified(0x1234),
            LoaderResponse::Verified { crc32: 0x1234 }
        );
        assert_eq!(
            s.handle(&INFO, &LoaderRequest::Start),
            LoaderAction::Start { entry: 0x8000_0000 }
        );
        // Any write after the verification undoes it.
        s.handle(&INFO, &first);
        assert_eq!(
            reply(s.handle(&INFO, &LoaderRequest::Start)),
            LoaderResponse::Error(LoaderError::NotVerified)
        );
    }

    #[test]
    fn the_largest_messages_fit_a_loader_frame() {
        let mut buf = [0u8; LOADER_FRAME_LEN];
        let request = LoaderEnvelope::new(
            u16::MAX,
            LoaderRequest::Chunk {
                index: u32::MAX,
                data: (0..LOADER_CHUNK).map(|_| 0xFF).collect(),
            },
        );
        let n = frame::encode(&request, &mut buf).unwrap();
        let back: LoaderEnvelope<LoaderRequest> = decode_frame(&mut buf[..n - 1]).unwrap();
        assert_eq!(back, request);
        let response = LoaderEnvelope::new(
            u16::MAX,
            LoaderResponse::Error(LoaderError::ChunkLength {
                index: u32::MAX,
                expected: u32::MAX,
                got: u32::MAX,
            }),
        );
        assert!(frame::encode(&response, &mut buf).is_ok());
    }

    #[test]
    fn application_frames_are_never_taken_for_loader_frames() {
        use crate::protocol::{Envelope, Request, Response, PROTOCOL_VERSION};
        let mut buf = [0u8; 64];
        let n = frame::encode(
            &Envelope {
                seq: 0x4C44,
                body: Request::Hello {
                    protocol_version: PROTOCOL_VERSION,
                },
            },
            &mut buf,
        )
        .unwrap();
        assert_eq!(
            decode_frame::<LoaderRequest>(&mut buf[..n - 1]),
            Err(FrameError::Message)
        );
        let n = frame::encode(
            &Envelope {
                seq: 1,
                body: Response::Ack,
            },
            &mut buf,
        )
        .unwrap();
        assert_eq!(
            decode_frame::<LoaderResponse>(&mut buf[..n - 1]),
            Err(FrameError::Message)
        );
    }

    proptest::proptest! {
        #[test]
        fn arbitrary_frames_and_requests_never_panic(
            mut bytes in proptest::collection::vec(proptest::prelude::any::<u8>(), 0..400),
            load_address: u32, length: u32, entry: u32, index: u32, len in 0usize..=LOADER_CHUNK,
        ) {
            let _ = decode_frame::<LoaderRequest>(&mut bytes);
            let mut s = LoaderSession::new();
            let h = ImageHeader { load_address, length, entry, crc32: 0 };
            let _ = s.handle(&INFO, &LoaderRequest::Begin(h));
            let _ = s.handle(&INFO, &chunk(index, len));
            let _ = s.handle(&INFO, &LoaderRequest::Verify);
            let _ = s.handle(&INFO, &LoaderRequest::Start);
        }
    }
}
