//! The stock LiteX BIOS's serial boot (SFL), as `litex_term --kernel` speaks it: how a LiteX
//! board receives a program. Our own loader (`deform_shared::loader`) stays for QEMU.
//!
//! 1. The BIOS sends the magic request `sL5DdSMmkekro\n` at boot (and whenever its console is
//!    given `serialboot`) and waits a quarter of a second of its clock for the answer
//!    `z6IHG7cYDID6o\n`. A BIOS already sitting at its prompt is sent `serialboot` here.
//! 2. Frames: payload length (1 byte), CRC-16/XMODEM of command and payload (2 bytes, big
//!    endian), command (1 byte), payload (≤ 255 bytes). `LOAD` (1) carries a big-endian address
//!    and the bytes for it (60 per frame here, as litex_term's safe mode); `JUMP` (2) an entry
//!    address.
//! 3. Each frame is answered with one byte: `K` success, `C` CRC error, `U` unknown command,
//!    `E` a frame that timed out half-way. As litex_term does, a frame answered `C` or `E` is
//!    sent again (a `LOAD` is idempotent); one with no answer is too.
//!
//! The BIOS checks each frame but not the image as a whole; the started firmware's build id
//! (checked by the caller, as after our own loader) confirms the right image runs.

use std::io;
use std::time::{Duration, Instant};

use crc::{Crc, CRC_16_XMODEM};

use super::FlashImage;
use crate::link::{is_timeout, Port};

/// What the BIOS sends when it is ready for a serial boot.
pub const MAGIC_REQUEST: &[u8] = b"sL5DdSMmkekro\n";
/// Our answer, which starts the frame exchange.
pub const MAGIC_ACK: &[u8] = b"z6IHG7cYDID6o\n";
/// The BIOS console's command that starts a serial boot again.
pub const SERIALBOOT_COMMAND: &[u8] = b"\nserialboot\n";
/// The BIOS console's prompt, for auto-detection.
pub const BIOS_PROMPT: &[u8] = b"litex>";

const CMD_LOAD: u8 = 0x01;
const CMD_JUMP: u8 = 0x02;
/// Most payload bytes of a frame; a `LOAD` spends 4 of them on the address.
pub const MAX_PAYLOAD: usize = 255;
/// Image bytes per `LOAD`: 60, as litex_term's safe mode sends (64-byte frames). The BIOS
/// allows 251, but in the simulated SoC a 255-byte payload was answered `E` (the frame timed
/// out half-way) while 64-byte ones were answered `K`.
const LOAD_DATA: usize = 60;

const ACK_SUCCESS: u8 = b'K';
const ACK_CRC_ERROR: u8 = b'C';
const ACK_UNKNOWN: u8 = b'U';
const ACK_ERROR: u8 = b'E';

/// CRC-16 with polynomial 0x1021, initial value 0, no reflection: LiteX's `crc16`.
const CRC16: Crc<u16> = Crc::<u16>::new(&CRC_16_XMODEM);

#[derive(Debug, thiserror::Error)]
pub enum SflError {
    #[error(
        "no LiteX BIOS serial-boot request within {0:?} (is the board's BIOS running on this \
         port? it asks at reset, or after `serialboot` at its prompt)"
    )]
    NoBios(Duration),
    #[error("the BIOS does not know command {command:#04x} (answered `U`)")]
    Unknown { command: u8 },
    #[error("the BIOS answered {answer:?} to a frame; expected K, C or E")]
    BadAnswer { answer: char },
    #[error("a frame failed {0} times in a row (CRC errors, timeouts or no answer)")]
    TooManyResends(u32),
    #[error("the serial line: {0}")]
    Io(#[from] io::Error),
}

/// How patient the SFL client is.
#[derive(Debug, Clone, Copy)]
pub struct SflTimeouts {
    /// How long to wait for the BIOS's magic request, `serialboot` prompts included.
    pub boot: Duration,
    /// How long quiet means a BIOS at its prompt, which is then sent `serialboot`.
    pub prompt_after: Duration,
    /// How long one frame waits for its one-byte answer before it is sent again.
    pub answer: Duration,
    /// Resends of one frame before the upload fails.
    pub retries: u32,
}

impl Default for SflTimeouts {
    fn default() -> Self {
        SflTimeouts {
            boot: Duration::from_secs(60),
            prompt_after: Duration::from_secs(3),
            answer: Duration::from_secs(5),
            retries: 16,
        }
    }
}

/// How an SFL upload went.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct SflReport {
    pub frames: usize,
    /// Frames sent again after a `C`, an `E` or no answer.
    pub resends: u64,
    pub wire_bytes: u64,
}

/// One SFL frame on the wire.
pub fn encode_frame(command: u8, payload: &[u8]) -> Vec<u8> {
    assert!(
        payload.len() <= MAX_PAYLOAD,
        "SFL payloads are at most 255 bytes"
    );
    let mut digest = CRC16.digest();
    digest.update(&[command]);
    digest.update(payload);
    let crc = digest.finalize();
    let mut frame = Vec::with_capacity(4 + payload.len());
    frame.push(payload.len() as u8);
    frame.extend_from_slice(&crc.to_be_bytes());
    frame.push(command);
    frame.extend_from_slice(payload);
    frame
}

/// The SFL side of a serial line.
pub struct SflClient<'a, P: Port> {
    port: &'a mut P,
    timeouts: SflTimeouts,
    report: SflReport,
}

impl<'a, P: Port> SflClient<'a, P> {
    pub fn new(port: &'a mut P, timeouts: SflTimeouts) -> Self {
        SflClient {
            port,
            timeouts,
            report: SflReport::default(),
        }
    }

    /// Waits for the magic request (sending `serialboot` whenever the line stays quiet) and
    /// answers it.
    pub fn handshake(&mut self) -> Result<(), SflError> {
        let deadline = Instant::now() + self.timeouts.boot;
        let mut seen: Vec<u8> = Vec::new();
        let mut quiet_since = Instant::now();
        let mut buf = [0u8; 256];
        self.port.set_timeout(Duration::from_millis(50))?;
        loop {
            if Instant::now() >= deadline {
                return Err(SflError::NoBios(self.timeouts.boot));
            }
            match self.port.read(&mut buf) {
                Ok(0) => {}
                Ok(n) => {
                    seen.extend_from_slice(&buf[..n]);
                    quiet_since = Instant::now();
                    if contains(&seen, MAGIC_REQUEST) {
                        self.write(MAGIC_ACK)?;
                        return Ok(());
                    }
                    // Keep only what could still start the request.
                    let keep = seen.len().saturating_sub(MAGIC_REQUEST.len());
                    seen.drain(..keep);
                }
                Err(e) if is_timeout(&e) => {}
                Err(e) => return Err(e.into()),
            }
            if quiet_since.elapsed() >= self.timeouts.prompt_after {
                self.write(SERIALBOOT_COMMAND)?;
                quiet_since = Instant::now();
            }
        }
    }

    /// Loads `image` into the board's memory, frame by frame, then jumps to its entry point.
    pub fn boot(
        mut self,
        image: &FlashImage,
        mut progress: impl FnMut(usize),
    ) -> Result<SflReport, SflError> {
        let mut address = image.load_address;
        for chunk in image.bytes.chunks(LOAD_DATA) {
            let mut payload = Vec::with_capacity(4 + chunk.len());
            payload.extend_from_slice(&address.to_be_bytes());
            payload.extend_from_slice(chunk);
            self.send(CMD_LOAD, &payload)?;
            address = address.wrapping_add(chunk.len() as u32);
            progress((address - image.load_address) as usize);
        }
        self.send(CMD_JUMP, &image.entry.to_be_bytes())?;
        Ok(self.report)
    }

    /// Sends one frame until the BIOS answers `K`.
    fn send(&mut self, command: u8, payload: &[u8]) -> Result<(), SflError> {
        let frame = encode_frame(command, payload);
        self.report.frames += 1;
        for attempt in 0..=self.timeouts.retries {
            if attempt > 0 {
                self.report.resends += 1;
            }
            self.write(&frame)?;
            match self.answer()? {
                Some(ACK_SUCCESS) => return Ok(()),
                Some(ACK_CRC_ERROR) | Some(ACK_ERROR) | None => continue,
                Some(ACK_UNKNOWN) => return Err(SflError::Unknown { command }),
                Some(other) => {
                    return Err(SflError::BadAnswer {
                        answer: other as char,
                    })
                }
            }
        }
        Err(SflError::TooManyResends(self.timeouts.retries + 1))
    }

    /// The next answer byte; `None` if none came in time.
    fn answer(&mut self) -> Result<Option<u8>, SflError> {
        self.port.set_timeout(self.timeouts.answer)?;
        let mut byte = [0u8; 1];
        match self.port.read(&mut byte) {
            Ok(1) => Ok(Some(byte[0])),
            Ok(_) => Ok(None),
            Err(e) if is_timeout(&e) => Ok(None),
            Err(e) => Err(e.into()),
        }
    }

    fn write(&mut self, bytes: &[u8]) -> Result<(), SflError> {
        self.report.wire_bytes += bytes.len() as u64;
        self.port.write_all(bytes)?;
        self.port.flush()?;
        Ok(())
    }
}

/// Listens for `listen` after poking the line with a newline: a LiteX BIOS answers with its
/// prompt (or is just sending its serial-boot request); our own loader answers nothing.
pub fn detect_bios<P: Port>(port: &mut P, listen: Duration) -> Result<bool, io::Error> {
    port.write_all(b"\n")?;
    port.flush()?;
    port.set_timeout(Duration::from_millis(50))?;
    let deadline = Instant::now() + listen;
    let mut seen = Vec::new();
    let mut buf = [0u8; 256];
    while Instant::now() < deadline {
        match port.read(&mut buf) {
            Ok(n) => seen.extend_from_slice(&buf[..n]),
            Err(e) if is_timeout(&e) => {}
            Err(e) => return Err(e),
        }
        if shows_prompt(&seen) || contains(&seen, MAGIC_REQUEST) {
            return Ok(true);
        }
    }
    Ok(false)
}

/// Whether `seen` shows the BIOS's prompt. The stock BIOS colours it
/// (`\e[92;1mlitex\e[0m> `), so escape sequences are dropped before [`BIOS_PROMPT`] is looked
/// for: in the raw bytes `litex` and `>` are apart.
pub fn shows_prompt(seen: &[u8]) -> bool {
    contains(&without_escapes(seen), BIOS_PROMPT)
}

/// `bytes` without ANSI escape sequences: from ESC to the sequence's final letter.
pub fn without_escapes(bytes: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(bytes.len());
    let mut in_escape = false;
    for &b in bytes {
        if in_escape {
            in_escape = !b.is_ascii_alphabetic();
        } else if b == 0x1b {
            in_escape = true;
        } else {
            out.push(b);
        }
    }
    out
}

fn contains(haystack: &[u8], needle: &[u8]) -> bool {
    haystack.windows(needle.len()).any(|w| w == needle)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::{Read, Write};
    use std::os::unix::net::UnixStream;
    use std::thread;

    /// The stock BIOS's prompt as it sends it (LiteX's bios/readline.h), answering the newline
    /// that `detect_bios` pokes the line with.
    const COLOURED_PROMPT: &[u8] = b"\x1b[92;1mlitex\x1b[0m> ";

    #[test]
    fn a_bios_at_its_coloured_prompt_is_detected_and_a_silent_line_is_not() {
        assert!(shows_prompt(COLOURED_PROMPT));
        assert!(
            !contains(COLOURED_PROMPT, BIOS_PROMPT),
            "the raw bytes hide it"
        );
        assert_eq!(without_escapes(b"a\x1b[0mb\x1b[92;1mc"), b"abc");

        let (mut host, mut bios) = UnixStream::pair().unwrap();
        let board = thread::spawn(move || {
            let mut poke = [0u8; 1];
            bios.read_exact(&mut poke).unwrap();
            assert_eq!(&poke, b"\n");
            bios.write_all(COLOURED_PROMPT).unwrap();
            bios
        });
        assert!(detect_bios(&mut host, Duration::from_secs(5)).unwrap());
        drop(board.join().unwrap());

        let (mut host, _silent) = UnixStream::pair().unwrap();
        assert!(!detect_bios(&mut host, Duration::from_millis(300)).unwrap());
    }

    #[test]
    fn frames_carry_length_crc16_command_and_payload() {
        // CRC-16/XMODEM of "123456789" is 0x31C3 (the catalogue's check value).
        assert_eq!(CRC16.checksum(b"123456789"), 0x31C3);
        let frame = encode_frame(CMD_JUMP, &0x4000_0000u32.to_be_bytes());
        assert_eq!(frame[0], 4);
        assert_eq!(frame[3], CMD_JUMP);
        assert_eq!(&frame[4..], &[0x40, 0, 0, 0]);
        let crc = CRC16.checksum(&[CMD_JUMP, 0x40, 0, 0, 0]);
        assert_eq!(u16::from_be_bytes([frame[1], frame[2]]), crc);
    }

    /// A scripted BIOS: asks for the boot, answers the first LOAD with `C` and the second not
    /// at all, checks every CRC, and records what it was sent.
    #[test]
    fn a_corrupt_or_unanswered_frame_is_sent_again() {
        let (mut host, mut bios) = UnixStream::pair().unwrap();
        let image = FlashImage {
            load_address: 0x4000_0000,
            entry: 0x4000_0000,
            bytes: (0..150u32).map(|i| i as u8).collect(),
            build_id: None,
        };
        let expected = image.bytes.clone();
        let board = thread::spawn(move || {
            bios.write_all(b"banner\n").unwrap();
            bios.write_all(MAGIC_REQUEST).unwrap();
            let mut ack = [0u8; 14];
            bios.read_exact(&mut ack).unwrap();
            assert_eq!(&ack, MAGIC_ACK);
            let mut memory = vec![0u8; 150];
            let mut loads = 0;
            loop {
                let mut head = [0u8; 4];
                bios.read_exact(&mut head).unwrap();
                let mut payload = vec![0u8; head[0] as usize];
                bios.read_exact(&mut payload).unwrap();
                let mut check = vec![head[3]];
                check.extend_from_slice(&payload);
                assert_eq!(
                    CRC16.checksum(&check),
                    u16::from_be_bytes([head[1], head[2]])
                );
                loads += 1;
                match (head[3], loads) {
                    (CMD_LOAD, 1) => bios.write_all(b"C").unwrap(),
                    (CMD_LOAD, 2) => {} // lost answer
                    (CMD_LOAD, _) => {
                        let at = u32::from_be_bytes(payload[..4].try_into().unwrap()) - 0x4000_0000;
                        let data = &payload[4..];
                        memory[at as usize..at as usize + data.len()].copy_from_slice(data);
                        bios.write_all(b"K").unwrap();
                    }
                    (CMD_JUMP, _) => {
                        bios.write_all(b"K").unwrap();
                        return memory;
                    }
                    other => panic!("unexpected {other:?}"),
                }
            }
        });
        let timeouts = SflTimeouts {
            answer: Duration::from_millis(200),
            ..SflTimeouts::default()
        };
        let mut client = SflClient::new(&mut host, timeouts);
        client.handshake().unwrap();
        let report = client.boot(&image, |_| {}).unwrap();
        assert_eq!(board.join().unwrap(), expected);
        assert_eq!(report.frames, 4); // three LOADs (60 + 60 + 30 bytes) and the JUMP
        assert_eq!(report.resends, 2);
    }
}
