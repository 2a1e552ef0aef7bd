//! The host's side of the loader protocol ([`deform_shared::loader`]): stop and wait, every
//! request resent until its answer arrives or the retries run out.
//!
//! This is not the application's [`Link`](crate::link::Link): the loader speaks another message
//! set, one request at a time, and must stay small enough to trust; a lost or corrupted frame
//! costs one resend of a 256-byte chunk.

use std::time::{Duration, Instant};

use deform_shared::frame::{self, FrameError, DELIMITER};
use deform_shared::loader::{
    decode_frame, LoaderEnvelope, LoaderError, LoaderInfo, LoaderRequest, LoaderResponse,
    LOADER_FRAME_LEN, LOADER_PROTOCOL_VERSION, UNKNOWN_SEQ,
};
use deform_shared::protocol::{Envelope, Request, PROTOCOL_VERSION};

use crate::link::{FrameEvent, FrameReader, Port};

/// Deadlines and retries of a loader session.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LoaderTimeouts {
    /// The whole handshake, `Hello` resent every [`hello_retry`](Self::hello_retry).
    pub handshake: Duration,
    pub hello_retry: Duration,
    /// One request's wait for its answer before it is sent again.
    pub request: Duration,
    /// Resends of one request (after a timeout or a corrupt-frame complaint) before giving up.
    pub retries: u32,
}

impl Default for LoaderTimeouts {
    fn default() -> Self {
        LoaderTimeouts {
            handshake: Duration::from_secs(10),
            hello_retry: Duration::from_secs(2),
            request: Duration::from_secs(2),
            retries: 8,
        }
    }
}

/// What went wrong talking to the loader.
#[derive(Debug, thiserror::Error)]
pub enum LoaderLinkError {
    #[error("serial I/O with the loader failed: {0}")]
    Io(#[from] std::io::Error),
    #[error(
        "no answer to {request} after {attempts} attempts (is the loader running on this port?)"
    )]
    Timeout {
        request: &'static str,
        attempts: u32,
    },
    #[error(
        "the target answers, but not as the loader ({frames} well-formed frames in another \
         format): it is probably running an application; reset it into the loader"
    )]
    NotTheLoader { frames: u64 },
    #[error("loader protocol version mismatch: the host speaks {host}, the loader {loader}")]
    VersionMismatch { host: u16, loader: u16 },
    #[error("the loader refused {request}: {error}")]
    Refused {
        request: &'static str,
        error: LoaderError,
    },
    #[error("unexpected answer to {request}: {got:?}")]
    Unexpected {
        request: &'static str,
        got: LoaderResponse,
    },
    #[error("cannot frame {request}: {source}")]
    Encode {
        request: &'static str,
        #[source]
        source: FrameError,
    },
}

/// Counters of a loader session.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LoaderStats {
    pub requests: u64,
    /// Requests sent again after a timeout or a corrupt-frame complaint.
    pub resends: u64,
    /// Frames from the target that did not decode at all.
    pub corrupt_frames: u64,
    /// Frames with a good CRC that are not loader answers (an application talking).
    pub foreign_frames: u64,
    /// Bytes written to the port.
    pub bytes_sent: u64,
}

/// A loader on a [`Port`].
pub struct LoaderLink<P: Port> {
    port: P,
    reader: FrameReader<{ 2 * LOADER_FRAME_LEN }>,
    next_seq: u16,
    flushed: bool,
    timeouts: LoaderTimeouts,
    stats: LoaderStats,
}

/// One received frame, as far as the session cares.
enum Received {
    Answer(LoaderEnvelope<LoaderResponse>),
    /// Good CRC, not a loader answer.
    Foreign,
    Corrupt,
}

impl<P: Port> LoaderLink<P> {
    pub fn new(port: P, timeouts: LoaderTimeouts) -> Self {
        LoaderLink {
            port,
            reader: FrameReader::default(),
            next_seq: 1,
            flushed: false,
            timeouts,
            stats: LoaderStats::default(),
        }
    }

    pub fn stats(&self) -> LoaderStats {
        self.stats
    }

    pub fn timeouts(&self) -> LoaderTimeouts {
        self.timeouts
    }

    /// The port, for the application's link once the loader has started it.
    pub fn into_port(self) -> P {
        self.port
    }

    /// `Hello` until the loader answers (a QEMU pty passes bytes on only once it notices the
    /// host; a board may still be booting), then checks its version.
    pub fn hello(&mut self) -> Result<LoaderInfo, LoaderLinkError> {
        let request = LoaderRequest::Hello {
            version: LOADER_PROTOCOL_VERSION,
        };
        let deadline = Instant::now() + self.timeouts.handshake;
        let mut attempts = 0;
        loop {
            attempts += 1;
            let left = deadline.saturating_duration_since(Instant::now());
            let wait = left.min(self.timeouts.hello_retry);
            match self.exchange_once(&request, wait, false)? {
                Some(LoaderResponse::Hello(info)) if info.version == LOADER_PROTOCOL_VERSION => {
                    return Ok(info)
                }
                Some(LoaderResponse::Hello(info)) => {
                    return Err(LoaderLinkError::VersionMismatch {
                        host: LOADER_PROTOCOL_VERSION,
                        loader: info.version,
                    })
                }
                Some(LoaderResponse::Error(LoaderError::VersionMismatch { loader })) => {
                    return Err(LoaderLinkError::VersionMismatch {
                        host: LOADER_PROTOCOL_VERSION,
                        loader,
                    })
                }
                // No answer, or a complaint about a partial frame that our flushing delimiter
                // ended: try again, unless an application is what answers.
                _ => {}
            }
            if self.stats.foreign_frames > 0 {
                return Err(LoaderLinkError::NotTheLoader {
                    frames: self.stats.foreign_frames,
                });
            }
            if Instant::now() >= deadline {
                return Err(LoaderLinkError::Timeout {
                    request: "Hello",
                    attempts,
                });
            }
            self.probe_application()?;
        }
    }

    /// Sends the application's `Hello`: an application (which stays silent to frames it cannot
    /// read) answers it, the loader complains about it. Either way the next wait sees who is
    /// there.
    fn probe_application(&mut self) -> Result<(), LoaderLinkError> {
        let probe = Envelope {
            seq: 0,
            body: Request::Hello {
                protocol_version: PROTOCOL_VERSION,
            },
        };
        let mut out = [0u8; 64];
        let len = frame::encode(&probe, &mut out).map_err(|source| LoaderLinkError::Encode {
            request: "Hello (application probe)",
            source,
        })?;
        self.send_raw(&out[..len])
    }

    /// Writes bytes as they are, outside any frame: for tests that put noise on the line.
    pub fn send_raw(&mut self, bytes: &[u8]) -> Result<(), LoaderLinkError> {
        self.port.set_timeout(self.timeouts.request)?;
        self.port.write_all(bytes)?;
        self.port.flush()?;
        self.stats.bytes_sent += bytes.len() as u64;
        Ok(())
    }

    /// Sends `request` until its answer arrives (resending after a timeout or when the loader
    /// says a frame arrived corrupt); an `Error` answer becomes [`LoaderLinkError::Refused`].
    pub fn request(&mut self, request: &LoaderRequest) -> Result<LoaderResponse, LoaderLinkError> {
        let name = request_name(request);
        for attempt in 0..=self.timeouts.retries {
            if attempt > 0 {
                self.stats.resends += 1;
            }
            match self.exchange_once(request, self.timeouts.request, true)? {
                Some(LoaderResponse::Error(LoaderError::Frame(_))) | None => continue,
                Some(LoaderResponse::Error(error)) => {
                    return Err(LoaderLinkError::Refused {
                        request: name,
                        error,
                    })
                }
                Some(answer) => return Ok(answer),
            }
        }
        if self.stats.foreign_frames > 0 {
            return Err(LoaderLinkError::NotTheLoader {
                frames: self.stats.foreign_frames,
            });
        }
        Err(LoaderLinkError::Timeout {
            request: name,
            attempts: self.timeouts.retries + 1,
        })
    }

    /// Sends `request` once and waits up to `wait` for the answer with its sequence number.
    /// `None`: none came. With `complaints_answer`, a complaint about an unreadable frame counts
    /// as the answer (mid-session it is most likely about this request, which the caller then
    /// resends); while shaking hands the line may still carry noise, so they are skipped.
    fn exchange_once(
        &mut self,
        request: &LoaderRequest,
        wait: Duration,
        complaints_answer: bool,
    ) -> Result<Option<LoaderResponse>, LoaderLinkError> {
        let seq = self.next_seq;
        self.next_seq = match seq.wrapping_add(1) {
            UNKNOWN_SEQ => 0,
            next => next,
        };
        let mut out = [0u8; LOADER_FRAME_LEN + 1];
        // The first frame ends whatever partial frame the loader holds from before.
        let start = usize::from(!self.flushed);
        out[0] = DELIMITER;
        let len = frame::encode(&LoaderEnvelope::new(seq, request), &mut out[start..]).map_err(
            |source| LoaderLinkError::Encode {
                request: request_name(request),
                source,
            },
        )?;
        self.port.set_timeout(wait.max(Duration::from_millis(1)))?;
        self.port.write_all(&out[..start + len])?;
        self.port.flush()?;
        self.flushed = true;
        self.stats.requests += 1;
        self.stats.bytes_sent += (start + len) as u64;

        let deadline = Instant::now() + wait;
        while let Some(received) = self.receive(deadline)? {
            match received {
                Received::Answer(LoaderEnvelope { seq: got, body, .. }) if got == seq => {
                    return Ok(Some(body))
                }
                Received::Answer(LoaderEnvelope {
                    seq: UNKNOWN_SEQ,
                    body: body @ LoaderResponse::Error(LoaderError::Frame(_)),
                    ..
                }) if complaints_answer => return Ok(Some(body)),
                Received::Answer(_) => {}
                Received::Foreign => self.stats.foreign_frames += 1,
                Received::Corrupt => self.stats.corrupt_frames += 1,
            }
        }
        Ok(None)
    }

    /// The next frame, or `None` once `deadline` passes.
    fn receive(&mut self, deadline: Instant) -> Result<Option<Received>, LoaderLinkError> {
        let event = self.reader.next(
            &mut self.port,
            deadline,
            |_| {},
            |body| match decode_frame::<LoaderResponse>(body) {
                Ok(answer) => Received::Answer(answer),
                Err(FrameError::Message) => Received::Foreign,
                Err(_) => Received::Corrupt,
            },
        )?;
        match event {
            FrameEvent::Frame(received) => Ok(Some(received)),
            FrameEvent::Overflow => Ok(Some(Received::Corrupt)),
            FrameEvent::EndOfFile => Err(LoaderLinkError::Io(std::io::Error::new(
                std::io::ErrorKind::UnexpectedEof,
                "the target closed the connection",
            ))),
            FrameEvent::TimedOut => Ok(None),
        }
    }
}

/// The request's variant name, for messages.
pub fn request_name(request: &LoaderRequest) -> &'static str {
    match request {
        LoaderRequest::Hello { .. } => "Hello",
        LoaderRequest::Begin(_) => "Begin",
        LoaderRequest::Chunk { .. } => "Chunk",
        LoaderRequest::Verify => "Verify",
        LoaderRequest::Start => "Start",
    }
}
