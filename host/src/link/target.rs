use std::time::Duration;

use deform_shared::frame;
use deform_shared::matrix::{validate_tile, words_crc, MatrixError};
use deform_shared::protocol::{
    Envelope, ErrorCode, Request, Response, SolveParams, SolveReport, Start, StateVector,
    TargetInfo, VectorSlot, CHUNK_LEN, MAX_DIRECTIONS, MAX_FRAME_LEN, PROTOCOL_VERSION,
};
use deform_shared::qformat::{block_exponent, from_mantissa, to_mantissa};
use deform_shared::transport::WINDOW;
use deform_shared::word::{Word, VALUE_MASK};
use serialport::SerialPort;

use super::adapt::ChunkSize;
use super::transport::{LinkConfig, DEFAULT_REQUEST_TIMEOUT};
use super::{open_serial, Capacity, Link, LinkError, LinkStats, Port};
use crate::encode::EncodedMatrix;

/// How long each kind of exchange may take.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Timeouts {
    /// The whole handshake, retries included.
    pub handshake: Duration,
    /// How long every request but `Solve` may wait for its reply, retransmissions included.
    pub request: Duration,
    /// `Solve`: CG on the target may take far longer than a round trip.
    pub solve: Duration,
    /// How long a frame waits for its reply before it is sent again (doubled per retry, up to
    /// 8×); see [`LinkConfig`].
    pub retransmit: Duration,
    /// Retransmissions of one frame before its request fails.
    pub retries: u32,
}

impl Timeouts {
    /// The transport settings these imply.
    pub fn link_config(&self) -> LinkConfig {
        LinkConfig {
            retransmit: self.retransmit,
            retries: self.retries,
            window: WINDOW,
        }
    }
}

/// How long one target solve may take unless told otherwise: the one default every command
/// (`solve --timeout`, `simulate --timeout`, `estimate --timeout`) and [`Timeouts::default`]
/// share. An 8-MVU 24³ solve under QEMU takes about a minute; five minutes leaves room.
pub const DEFAULT_SOLVE_TIMEOUT: Duration = Duration::from_secs(300);

impl Default for Timeouts {
    fn default() -> Self {
        Timeouts {
            handshake: Duration::from_secs(10),
            request: DEFAULT_REQUEST_TIMEOUT,
            solve: DEFAULT_SOLVE_TIMEOUT,
            retransmit: LinkConfig::default().retransmit,
            retries: LinkConfig::default().retries,
        }
    }
}

/// How far a matrix upload has got, reported after every chunk.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct UploadProgress {
    pub words_sent: usize,
    pub words_total: usize,
}

/// A target after a successful handshake: the protocol session from the host's side.
///
/// The methods follow the session order of [`deform_shared::protocol`]: upload a matrix, then
/// per right-hand side upload it, solve, and read the solution.
pub struct Target<P: Port = Box<dyn SerialPort>> {
    link: Link<P>,
    info: TargetInfo,
    timeouts: Timeouts,
    /// The matrix the target holds, as far as the host knows: its pattern decides whether a
    /// values-only update is possible, and it is uploaded again if the target resets.
    resident: Option<EncodedMatrix>,
    /// Times a reset target was given its matrix again (see [`Target::solve_for`]).
    resumes: u32,
}

/// What a values-only update sent, against what a full upload of the same matrix would send.
/// Both count request frames as they go on the wire (COBS, CRC and delimiter included, each
/// with a two-byte sequence number), not the target's answers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct UpdateReport {
    pub bytes_sent: u64,
    pub full_upload_bytes: u64,
}

impl UpdateReport {
    pub fn bytes_saved(&self) -> u64 {
        self.full_upload_bytes.saturating_sub(self.bytes_sent)
    }
}

/// Why a values-only update was not made.
#[derive(Debug, thiserror::Error)]
pub enum UpdateError {
    #[error("the target holds no matrix the host knows of; upload it in full")]
    NoResidentMatrix,
    #[error("the matrix's sparsity pattern (n, tiles, columns or row ends) differs from the resident one; upload it in full")]
    PatternChanged,
    #[error(transparent)]
    Link(#[from] LinkError),
}

/// Bytes one request takes on the wire, framed, with a two-byte sequence number. A request
/// that does not fit a frame is an error (it could not be sent either), never a silent 0.
fn frame_bytes(request: &Request) -> Result<u64, LinkError> {
    let mut buf = [0u8; MAX_FRAME_LEN];
    let envelope = Envelope {
        seq: 0x1000,
        body: request.clone(),
    };
    frame::encode(&envelope, &mut buf)
        .map(|n| n as u64)
        .map_err(|source| LinkError::Encode {
            request: request.name(),
            source,
        })
}

/// The requests of a full upload of `matrix`, in order, each tile's words in chunks of the size
/// `chunk` holds when the link takes them.
fn upload_requests(matrix: &EncodedMatrix, chunk: ChunkSize) -> impl Iterator<Item = Request> + '_ {
    let begin = Request::BeginMatrix {
        n: matrix.n,
        frac_bits: matrix.frac_bits,
        tiles: matrix.tiles.len() as u32,
        words: matrix.words.len() as u32,
    };
    let mut offset = 0usize;
    let tiles = matrix.tile_words().flat_map(move |(header, words)| {
        let start = offset;
        offset += words.len();
        std::iter::once(Request::Tile(*header)).chain(chunk.ranges(words.len()).map(move |range| {
            Request::Words {
                offset: (start + range.start) as u32,
                words: words[range].iter().copied().collect(),
            }
        }))
    });
    std::iter::once(begin)
        .chain(tiles)
        .chain(std::iter::once(Request::EndMatrix {
            crc32: words_crc(&matrix.words),
        }))
}

/// The requests of a values-only update to `matrix`'s values, in order, in chunks of the size
/// `chunk` holds when the link takes them.
fn update_requests(matrix: &EncodedMatrix, chunk: ChunkSize) -> impl Iterator<Item = Request> + '_ {
    let begin = Request::BeginUpdate {
        words: matrix.words.len() as u32,
        frac_bits: matrix.frac_bits,
    };
    let chunks = chunk
        .ranges(matrix.words.len())
        .map(|range| Request::UpdateValues {
            offset: range.start as u32,
            values: matrix.words[range]
                .iter()
                .map(|&w| Word(w).raw_value())
                .collect(),
        });
    std::iter::once(begin)
        .chain(chunks)
        .chain(std::iter::once(Request::EndUpdate {
            crc32: words_crc(&matrix.words),
        }))
}

/// Bytes a full upload of `matrix` in full-size chunks puts on the wire (see [`UpdateReport`]).
pub fn full_upload_bytes(matrix: &EncodedMatrix) -> Result<u64, LinkError> {
    upload_requests(matrix, ChunkSize::fixed(CHUNK_LEN))
        .map(|r| frame_bytes(&r))
        .sum()
}

/// Bytes a values-only update to `matrix` in full-size chunks puts on the wire (see
/// [`UpdateReport`]).
pub fn update_bytes(matrix: &EncodedMatrix) -> Result<u64, LinkError> {
    update_requests(matrix, ChunkSize::fixed(CHUNK_LEN))
        .map(|r| frame_bytes(&r))
        .sum()
}

impl Target<Box<dyn SerialPort>> {
    /// Opens the serial port (a board's, or QEMU's pty) and shakes hands.
    pub fn connect(port_path: &str, timeouts: Timeouts) -> Result<Self, LinkError> {
        let link = Link::new(open_serial(port_path)?);
        Target::handshake(link, timeouts)
    }
}

impl<P: Port> Target<P> {
    /// Shakes hands over an open link: `Hello` until the target answers, then checks that it
    /// speaks our protocol version.
    pub fn handshake(link: Link<P>, timeouts: Timeouts) -> Result<Self, LinkError> {
        let mut link = link.with_timeout(timeouts.request);
        link.set_config(timeouts.link_config());
        let info = hello(&mut link, &timeouts)?;
        Ok(Target {
            link,
            info,
            timeouts,
            resident: None,
            resumes: 0,
        })
    }

    /// What the target said it is and holds, at the last handshake.
    pub fn info(&self) -> &TargetInfo {
        &self.info
    }

    pub fn timeouts(&self) -> Timeouts {
        self.timeouts
    }

    /// Changes the deadlines of the following requests (e.g. a longer solve).
    pub fn set_timeouts(&mut self, timeouts: Timeouts) {
        self.timeouts = timeouts;
        self.link.set_timeout(timeouts.request);
        self.link.set_config(timeouts.link_config());
    }

    /// How often a target that reset mid-session was given its matrix again.
    pub fn resumes(&self) -> u32 {
        self.resumes
    }

    pub fn stats(&self) -> LinkStats {
        self.link.stats()
    }

    /// The link underneath, e.g. to put noise on the line in tests.
    pub fn link_mut(&mut self) -> &mut Link<P> {
        &mut self.link
    }

    /// Shakes hands again, which resets the target's session (matrix, vectors, solution).
    pub fn reset(&mut self) -> Result<&TargetInfo, LinkError> {
        self.resident = None;
        self.info = hello(&mut self.link, &self.timeouts)?;
        Ok(&self.info)
    }

    /// Refuses a matrix that exceeds one of the target's capacities.
    pub fn check_matrix_fits(&self, matrix: &EncodedMatrix) -> Result<(), LinkError> {
        fits(Capacity::Dimension, matrix.n as usize, self.info.max_n)?;
        fits(
            Capacity::MatrixWords,
            matrix.words.len(),
            self.info.word_capacity,
        )?;
        fits(
            Capacity::MatrixTiles,
            matrix.tiles.len(),
            self.info.tile_capacity,
        )
    }

    /// Uploads `matrix`, which then stays resident for any number of solves.
    pub fn upload_matrix(&mut self, matrix: &EncodedMatrix) -> Result<(), LinkError> {
        self.upload_matrix_with_progress(matrix, |_| {})
    }

    /// Like [`upload_matrix`](Self::upload_matrix), calling `progress` after every chunk.
    ///
    /// Nothing is sent unless the matrix fits the target's capacities and every tile passes the
    /// same validation the target does, so a bad matrix fails fast with the host's diagnosis.
    pub fn upload_matrix_with_progress(
        &mut self,
        matrix: &EncodedMatrix,
        mut progress: impl FnMut(UploadProgress),
    ) -> Result<(), LinkError> {
        self.check_matrix_fits(matrix)?;
        validate_matrix(matrix).map_err(LinkError::MalformedMatrix)?;
        let words_total = matrix.words.len();
        self.resident = None;
        let chunk = self.link.chunk_size();
        self.link
            .run(upload_requests(matrix, chunk), |request, reply| {
                expect_ack_reply(request, reply)?;
                if let Request::Words { offset, words } = request {
                    progress(UploadProgress {
                        words_sent: *offset as usize + words.len(),
                        words_total,
                    });
                }
                Ok(())
            })?;
        self.resident = Some(matrix.clone());
        Ok(())
    }

    /// True if the target holds a matrix with `matrix`'s sparsity pattern, so that
    /// [`update_values`](Self::update_values) can replace its values.
    pub fn pattern_matches(&self, matrix: &EncodedMatrix) -> bool {
        self.resident.as_ref().is_some_and(|p| {
            p.n == matrix.n
                && p.tiles == matrix.tiles
                && p.words.len() == matrix.words.len()
                && p.words
                    .iter()
                    .zip(&matrix.words)
                    .all(|(r, w)| r & !VALUE_MASK == w & !VALUE_MASK)
        })
    }

    /// Replaces the values of the resident matrix by `matrix`'s (`BeginUpdate`,
    /// `UpdateValues`…, `EndUpdate`): only the 21-bit value fields travel. `matrix` must have
    /// the resident matrix's pattern (checked here, before anything is sent); its Q-format may
    /// differ. The vectors and the previous solution stay on the target.
    pub fn update_values(&mut self, matrix: &EncodedMatrix) -> Result<UpdateReport, UpdateError> {
        if self.resident.is_none() {
            return Err(UpdateError::NoResidentMatrix);
        }
        if !self.pattern_matches(matrix) {
            return Err(UpdateError::PatternChanged);
        }
        self.resident = None;
        let bytes_sent = update_bytes(matrix)?;
        let full_upload_bytes = full_upload_bytes(matrix)?;
        let chunk = self.link.chunk_size();
        self.link
            .run(update_requests(matrix, chunk), expect_ack_reply)?;
        self.resident = Some(matrix.clone());
        Ok(UpdateReport {
            bytes_sent,
            full_upload_bytes,
        })
    }

    /// A values-only update when the pattern allows it, else a full upload. Returns the
    /// update's report, or `None` after a full upload.
    pub fn upload_or_update(
        &mut self,
        matrix: &EncodedMatrix,
    ) -> Result<Option<UpdateReport>, LinkError> {
        if self.pattern_matches(matrix) {
            match self.update_values(matrix) {
                Ok(report) => return Ok(Some(report)),
                Err(UpdateError::Link(e)) => return Err(e),
                Err(_) => {}
            }
        }
        self.upload_matrix(matrix)?;
        Ok(None)
    }

    /// Uploads a vector (the right-hand side, or an initial guess) in block floating point.
    /// Its length must be the uploaded matrix's n.
    pub fn upload_vector(&mut self, slot: VectorSlot, values: &[f64]) -> Result<(), LinkError> {
        fits(Capacity::Dimension, values.len(), self.info.max_n)?;
        let max_abs = values.iter().fold(0.0f64, |max, v| max.max(v.abs()));
        let exponent = block_exponent(max_abs);
        let mantissas = values
            .iter()
            .enumerate()
            .map(|(index, &value)| {
                to_mantissa(value, exponent).ok_or(LinkError::NotFinite { slot, index, value })
            })
            .collect::<Result<Vec<i32>, _>>()?;
        let begin = Request::BeginVector {
            slot,
            exponent,
            len: values.len() as u32,
        };
        let chunks =
            self.link
                .chunk_size()
                .ranges(mantissas.len())
                .map(|range| Request::VectorData {
                    slot,
                    offset: range.start as u32,
                    mantissas: mantissas[range].iter().copied().collect(),
                });
        self.link
            .run(std::iter::once(begin).chain(chunks), expect_ack_reply)
    }

    /// Runs CG on the target, waiting up to [`Timeouts::solve`].
    pub fn solve(&mut self, params: SolveParams) -> Result<SolveReport, LinkError> {
        let request = Request::Solve(params);
        match self.link.request_within(&request, self.timeouts.solve)? {
            Response::Solved(report) => Ok(report),
            other => Err(unexpected(&request, "Solved", &other)),
        }
    }

    /// Reads the first `n` entries of the last solution (direction 0).
    pub fn read_solution(&mut self, n: usize) -> Result<Vec<f64>, LinkError> {
        self.read_direction_solution(0, n)
    }

    /// Reads the first `n` entries of the last solution of `direction`, chunk by chunk with the
    /// window full, each answer as long as the link's adapted chunk size when it is asked for.
    /// It is returned only once every chunk arrived, of the direction and at the offset asked
    /// for, with the same exponent (each in a frame whose CRC passed).
    pub fn read_direction_solution(
        &mut self,
        direction: u8,
        n: usize,
    ) -> Result<Vec<f64>, LinkError> {
        self.read_chunks(direction, n, |offset, len| Request::ReadSolution {
            direction,
            offset,
            len,
        })
    }

    /// Reads the first `n` entries of a session vector of `direction` other than the solution
    /// (protocol version 13): a dynamic step's right-hand side, velocities or residual, as
    /// [`Target::read_direction_solution`] reads the solution.
    pub fn read_vector(
        &mut self,
        vector: StateVector,
        direction: u8,
        n: usize,
    ) -> Result<Vec<f64>, LinkError> {
        self.read_chunks(direction, n, |offset, len| Request::ReadVector {
            vector,
            direction,
            offset,
            len,
        })
    }

    /// The requests `ask(offset, len)` over `0..n` in the link's chunk size, whose answers are
    /// `Solution` chunks of `direction`, joined.
    fn read_chunks(
        &mut self,
        direction: u8,
        n: usize,
        ask: impl Fn(u32, u16) -> Request,
    ) -> Result<Vec<f64>, LinkError> {
        let mut solution = Vec::with_capacity(n);
        let mut first_exponent = None;
        let requests = self
            .link
            .chunk_size()
            .ranges(n)
            .map(|range| ask(range.start as u32, range.len() as u16));
        self.link.run(requests, |request, reply| {
            let (Request::ReadSolution { offset, len, .. } | Request::ReadVector { offset, len, .. }) =
                *request
            else {
                return Err(unexpected(request, "Solution", &reply));
            };
            let wanted = usize::from(len);
            match reply {
                Response::Solution {
                    direction: got_direction,
                    offset: got,
                    exponent,
                    mantissas,
                } if got == offset
                    && got_direction == direction
                    && mantissas.len() >= wanted
                    && *first_exponent.get_or_insert(exponent) == exponent =>
                {
                    solution.extend(
                        mantissas
                            .iter()
                            .take(wanted)
                            .map(|&m| from_mantissa(m, exponent)),
                    );
                    Ok(())
                }
                other => Err(unexpected(
                    request,
                    "a Solution chunk of the requested direction and offset, as long as asked, with the \
                     exponent of the others",
                    &other,
                )),
            }
        })?;
        if solution.len() != n {
            return Err(LinkError::Protocol {
                request: ask(0, 0).name(),
                expected: "the whole vector",
                got: format!("{} of {n} entries", solution.len()),
            });
        }
        Ok(solution)
    }

    /// Uploads `rhs`, solves and reads the solution: one right-hand side against the resident
    /// matrix (direction 0; `params.directions` is taken as 1).
    pub fn solve_for(
        &mut self,
        rhs: &[f64],
        params: SolveParams,
    ) -> Result<(SolveReport, Vec<f64>), LinkError> {
        let (report, mut solutions) = self.solve_fused(&[rhs], params)?;
        Ok((report, solutions.pop().unwrap_or_default()))
    }

    /// Solves up to [`MAX_DIRECTIONS`] systems with the resident matrix in one fused CG run:
    /// uploads `rhs[d]` as direction d's right-hand side, solves with
    /// `params.directions = rhs.len()`, and reads every direction's solution. For
    /// [`Start::Uploaded`], upload each direction's `InitialGuess { direction }` first.
    ///
    /// If the target resets meanwhile (it answers `NotSynced`), a cold solve (`Start::Zero`)
    /// resumes: the host shakes hands again, uploads the matrix it holds a copy of, and
    /// repeats the whole right-hand sides. A warm start cannot resume, since the state it
    /// starts from died with the target; it fails with [`LinkError::TargetReset`].
    pub fn solve_fused(
        &mut self,
        rhs: &[&[f64]],
        params: SolveParams,
    ) -> Result<(SolveReport, Vec<Vec<f64>>), LinkError> {
        if rhs.is_empty() || rhs.len() > MAX_DIRECTIONS {
            return Err(LinkError::Directions(rhs.len()));
        }
        let params = SolveParams {
            directions: rhs.len() as u8,
            ..params
        };
        match self.solve_fused_once(rhs, params) {
            Err(LinkError::TargetReset) if params.start == Start::Zero => {
                let Some(matrix) = self.resident.take() else {
                    return Err(LinkError::TargetReset);
                };
                self.reset()?;
                self.upload_matrix(&matrix)?;
                self.resumes += 1;
                self.solve_fused_once(rhs, params)
            }
            other => other,
        }
    }

    fn solve_fused_once(
        &mut self,
        rhs: &[&[f64]],
        params: SolveParams,
    ) -> Result<(SolveReport, Vec<Vec<f64>>), LinkError> {
        for (d, b) in rhs.iter().enumerate() {
            self.upload_vector(VectorSlot::Rhs { direction: d as u8 }, b)?;
        }
        let report = self.solve(params)?;
        let solutions = rhs
            .iter()
            .enumerate()
            .map(|(d, b)| self.read_direction_solution(d as u8, b.len()))
            .collect::<Result<Vec<_>, _>>()?;
        Ok((report, solutions))
    }
}

fn expect_ack_reply(request: &Request, reply: Response) -> Result<(), LinkError> {
    match reply {
        Response::Ack => Ok(()),
        other => Err(unexpected(request, "Ack", &other)),
    }
}

/// `Hello` until an answer arrives within `timeouts.handshake`; checks the version.
///
/// One `Hello`, retransmitted with its own number like any request: the target answers a copy of
/// the `Hello` it last handled from its reply cache, without resetting the session again, so an
/// answer to any copy counts and the copies may follow as quickly as any request's (the
/// retransmit timeout, doubled while the line stays silent: a QEMU pty or a booting board may
/// hold the first for a second). On a noisy line that is what gets the handshake through:
/// waiting seconds between fresh `Hello`s left five tries in ten seconds, each lost half the time
/// at a byte-error rate of 1e-2.
///
/// Only `timeouts.handshake` bounds it, not the cap on quiet retransmissions
/// ([`LinkConfig::retries`]): a target that is still booting is silent exactly like an absent
/// one, and a slow one (a simulated SoC clearing its memory under load) took longer than the
/// ~30 s that 16 doubling retransmissions last, whatever handshake time the caller allowed.
fn hello<P: Port>(link: &mut Link<P>, timeouts: &Timeouts) -> Result<TargetInfo, LinkError> {
    let request = Request::Hello {
        protocol_version: PROTOCOL_VERSION,
    };
    let request_timeout = link.timeout();
    let config = link.config();
    link.set_timeout(timeouts.handshake);
    link.set_config(LinkConfig {
        retries: u32::MAX,
        ..config
    });
    let answer = link.request(&request);
    link.set_timeout(request_timeout);
    link.set_config(config);
    match answer {
        Ok(Response::Hello(info)) if info.protocol_version == PROTOCOL_VERSION => Ok(info),
        Ok(Response::Hello(info)) => Err(LinkError::VersionMismatch {
            host: PROTOCOL_VERSION,
            target: info.protocol_version,
        }),
        Ok(other) => Err(unexpected(&request, "Hello", &other)),
        Err(LinkError::Target {
            code: ErrorCode::VersionMismatch { target },
            ..
        }) => Err(LinkError::VersionMismatch {
            host: PROTOCOL_VERSION,
            target,
        }),
        Err(LinkError::Timeout { .. }) if link.stats().undecodable > 0 => {
            Err(LinkError::Incompatible {
                frames: link.stats().undecodable,
                host: PROTOCOL_VERSION,
            })
        }
        Err(e) => Err(e),
    }
}

fn fits(what: Capacity, requested: usize, capacity: u32) -> Result<(), LinkError> {
    if requested as u64 > capacity as u64 {
        return Err(LinkError::TooLarge {
            what,
            requested: requested as u64,
            capacity,
        });
    }
    Ok(())
}

/// The checks the target makes, made before anything is sent.
fn validate_matrix(matrix: &EncodedMatrix) -> Result<(), MatrixError> {
    if matrix.n == 0 || matrix.tiles.is_empty() {
        return Err(MatrixError::EmptyTile { tile: 0 });
    }
    let declared: u64 = matrix.tiles.iter().map(|t| t.words as u64).sum();
    if declared != matrix.words.len() as u64 {
        return Err(MatrixError::TotalWordsMismatch {
            expected: matrix.words.len() as u32,
            found: declared.min(u32::MAX as u64) as u32,
        });
    }
    let mut offset = 0;
    for (i, header) in matrix.tiles.iter().enumerate() {
        let end = offset + header.words as usize;
        validate_tile(i as u32, header, &matrix.words[offset..end], matrix.n)?;
        offset = end;
    }
    Ok(())
}

fn unexpected(request: &Request, expected: &'static str, got: &Response) -> LinkError {
    LinkError::Protocol {
        request: request.name(),
        expected,
        got: format!("{got:?}"),
    }
}

#[cfg(test)]
mod tests;
