//! The protocol state machine: one [`Response`] for every [`Request`], in the order documented in
//! [`deform_shared::protocol`].
//!
//! A [`Session`] owns no memory. The firmware (or a test) lends it a [`Storage`]: the matrix store
//! (`words`, `tiles`), per direction the vectors `b` (right-hand side), `x` (solution), `x0`
//! (uploaded initial guess) and `r`, the shared `p`, `kp` and partial sums, plus a
//! [`TargetInfo`] and an [`Executor`] (the harts, or a host stand-in). The session
//! never panics and never indexes out of bounds, whatever the requests: every access goes through
//! `get`/`get_mut` and checked arithmetic, and a proptest throws random request sequences at it.
//!
//! # Capacities
//!
//! [`Session::new`] clamps the capacities advertised in the [`TargetInfo`] to what the lent
//! slices really hold (`max_n` is the largest n that all vectors hold), sets `protocol_version` to
//! [`PROTOCOL_VERSION`], and then enforces exactly the capacities it advertises.
//!
//! # Policies
//!
//! - **Hello** always answers `Hello(TargetInfo)` and resets the session (no matrix, no vectors,
//!   no solution). If the host's `protocol_version` differs from ours we still answer `Hello`
//!   with our info, so the host can report both versions; but until the next `Hello` with the
//!   right version, every other request is answered `Error(VersionMismatch { target })`. A fresh
//!   session needs no `Hello` (it behaves as after a matching one).
//! - **Refused requests change nothing**, so a host may correct and resend (e.g. a chunk at the
//!   wrong offset: the error says which offset is expected). Two exceptions:
//!   - `BeginMatrix` first drops the loaded matrix, both vectors and the solution, and
//!     `BeginVector` first drops that slot's vector, even when they are then refused: the host
//!     has said it is done with them.
//!   - Faults found in data already received abort the matrix upload (back to "no matrix"): a
//!     tile that fails [`validate_tile`] when its last word arrives, a word total that differs
//!     from `BeginMatrix`'s at `EndMatrix`, and a CRC mismatch.
//! - **Matrix upload**: `BeginMatrix` needs `1 ≤ n ≤ max_n`, `words ≤ word_capacity`,
//!   `tiles ≤ tile_capacity`, `frac_bits ≤ 20` and at least one tile (`n = 0` or `tiles = 0` is
//!   answered `Matrix(EmptyTile { tile: 0 })`: such a matrix cannot be positive definite). A
//!   `Tile` header is checked at once (`EmptyTile`, `RowsOutOfRange`, and `TotalWordsMismatch` if
//!   its words would run past the announced total); a `Tile` beyond the announced count, or
//!   `Words` after all tiles are complete, is `ChunkTooLong`. `Words` offsets count from the
//!   start of the whole word stream and must continue exactly where the previous chunk ended;
//!   empty chunks are allowed (they change nothing).
//! - **Vectors** need a loaded matrix (`OutOfOrder(NoMatrix)`) and `len == n`. Loading a new
//!   matrix invalidates both vectors. A completed vector stays until replaced; a new `Rhs` does
//!   not invalidate the solution.
//! - **Solve** invalidates the previous solution only once its own checks passed; a failed solve
//!   leaves no solution. `Start::Previous` uses the solution still in `x`. `Start::Predicted`
//!   extrapolates 2u(t−1) − u(t−2) ([`crate::predict`]) from the solution in `x` and the one
//!   before it, which it keeps in `x0` (so it consumes an uploaded guess); with fewer solutions
//!   it starts from u(t−1) or 0, never refused. Any other start, a new guess or a new matrix
//!   restarts the prediction.
//! - **Live loop** (`LiveTool`, `LiveStart`, `LiveFrame`, `LiveForce`, `ReadField`; force
//!   tools: `LiveForceTool`, `LiveLoad`, `LiveLoadQuery`): see
//!   [`crate::live`] and `live_glue.rs`; `BeginMatrix` and `Hello` forget the tool set. A
//!   live frame starts from the superposition of the response columns `LiveStart` kept in
//!   [`Storage::responses`] ([`crate::superpose`]) and solves with `Start::Previous`; without
//!   room for them, with `Start::Predicted`.
//! - **ReadSolution** at `offset ≥ n` is `ChunkTooLong`.
//! - **Values-only update** (`BeginUpdate`, `UpdateValues`…, `EndUpdate`): needs a loaded
//!   matrix (`OutOfOrder(NoMatrix)`; a `BeginUpdate` during an update starts it over) whose
//!   word count equals `BeginUpdate`'s (`Matrix(TotalWordsMismatch)`), and `frac_bits ≤ 20`.
//!   `UpdateValues` offsets continue exactly where the previous chunk ended, chunks may not run
//!   past the word count (`ChunkTooLong`), and every raw value must fit 21 bits
//!   (`ValueOutOfRange`); a refused chunk writes nothing. Each value replaces the value field of
//!   the resident word in place, keeping EM, ER and the column. `EndUpdate` before all words
//!   are replaced is `OutOfOrder(UpdateIncomplete)`; a CRC mismatch drops the matrix and its
//!   vectors. During an update `Solve` is `OutOfOrder(UpdateIncomplete)`, while vectors may be
//!   uploaded and the solution read; vectors and the solution survive a completed update, so
//!   `Start::Previous` warm-starts after it.

use deform_shared::dynamics::DynamicError;
use deform_shared::matrix::{validate_mvu, validate_tile, words_crc, MatrixError, TileHeader};
use deform_shared::protocol::{
    ErrorCode, Request, Response, SessionStep, SolveFailure, SolveParams, SolveReport, Start,
    StateVector, TargetInfo, VectorSlot, CHUNK_LEN, MAX_DIRECTIONS, MAX_HARTS, PROTOCOL_VERSION,
};
use deform_shared::qformat::{MANTISSA_LIMIT, MAX_FRAC_BITS};
use deform_shared::word::{VALUE_MASK, VALUE_MAX, VALUE_MIN};

use crate::cg::{self, GivenResidual, Matrix, Outcome, Plan, PlanError, System, Work};
use crate::dynamics::Dynamic;
use crate::exec::Executor;
use crate::kernel::{Lanes, Sums};
use crate::live::Live;
use crate::mvu_backend::MvuBackend;
use crate::predict;

/// The memory a [`Session`] works in, lent by its owner.
///
/// The vectors may differ in length; the session's `max_n` is the largest n they all hold.
pub struct Storage<'a> {
    /// The matrix's instruction words, all tiles back to back.
    pub words: &'a mut [u32],
    /// The matrix's tile headers.
    pub tiles: &'a mut [TileHeader],
    /// One set of vectors per direction a fused solve can run.
    pub directions: [DirectionStorage<'a>; MAX_DIRECTIONS],
    /// The search directions of all directions, interleaved (see [`crate::kernel`]).
    pub p: &'a mut [Lanes],
    /// K·p of all directions, in double width.
    pub kp: &'a mut [Sums],
    /// Private partial sums of MVUs whose rows overlap (thesis 4.1.1); its length limits how
    /// much they may overlap.
    pub partial: &'a mut [Sums],
    /// The live loop's response columns, one of n per tool node back to back
    /// ([`crate::superpose`]); held only if all of a tool set's fit, else (or if empty) live
    /// frames fall back to the extrapolation of [`Start::Predicted`].
    pub responses: &'a mut [i32],
    /// The response columns' own residuals, `i16` mantissas laid out as `responses`
    /// ([`crate::superpose`]'s residual estimate); held only where as long as `responses`.
    pub residuals: &'a mut [i16],
    /// The stiffness copy of a dynamic session ([`crate::dynamics`]): the resident matrix's
    /// words with K's values; its length limits the matrices a dynamic session takes.
    pub stiffness: &'a mut [u32],
}

/// The vectors of one direction.
pub struct DirectionStorage<'a> {
    /// Right-hand side mantissas.
    pub b: &'a mut [i32],
    /// Solution mantissas (CG iterates on them in place).
    pub x: &'a mut [i32],
    /// Uploaded initial-guess mantissas.
    pub x0: &'a mut [i32],
    /// CG residual.
    pub r: &'a mut [i32],
}

impl Storage<'_> {
    /// The largest dimension all vectors can hold.
    pub fn max_n(&self) -> usize {
        self.directions
            .iter()
            .map(DirectionStorage::max_n)
            .chain([self.p.len(), self.kp.len()])
            .min()
            .unwrap_or(0)
    }
}

/// What a solve or an MVU pass borrows of the store at once: a matrix (the resident words, or
/// the stiffness copy's), the work arrays and the direction vectors.
struct Parts<'s, 'a> {
    matrix: Matrix<'s>,
    work: Work<'s>,
    directions: &'s mut [DirectionStorage<'a>; MAX_DIRECTIONS],
}

/// Which words a pass reads: the resident matrix's, or the stiffness copy's (a dynamic
/// session's K, with its own fractional bits).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Words {
    Resident,
    Stiffness { frac_bits: u8 },
}

impl<'a> Storage<'a> {
    /// The parts for a matrix of `shape` planned by `plan`, its words chosen by `which`. A
    /// shape that does not fit the store (the upload's checks make that impossible) is
    /// refused as too large for its capacity, `max_n`.
    fn parts<'s>(
        &'s mut self,
        shape: Shape,
        which: Words,
        plan: &'s Plan,
    ) -> Result<Parts<'s, 'a>, ErrorCode> {
        let too_large = ErrorCode::DimensionTooLarge {
            requested: shape.n,
            capacity: to_u32(self.max_n()),
        };
        let Storage {
            words,
            tiles,
            directions,
            p,
            kp,
            partial,
            stiffness: copy,
            ..
        } = self;
        let (words, frac_bits): (&[u32], u8) = match which {
            Words::Resident => (words, shape.frac_bits),
            Words::Stiffness { frac_bits } => (copy, frac_bits),
        };
        let n = to_usize(shape.n);
        let (Some(tiles), Some(words)) = (
            tiles.get(..to_usize(shape.tiles)),
            words.get(..to_usize(shape.words)),
        ) else {
            return Err(too_large);
        };
        Ok(Parts {
            matrix: Matrix {
                n,
                frac_bits,
                tiles,
                words,
                plan,
            },
            work: Work { p, kp, partial },
            directions,
        })
    }
}

impl DirectionStorage<'_> {
    fn max_n(&self) -> usize {
        [self.b.len(), self.x.len(), self.x0.len(), self.r.len()]
            .into_iter()
            .min()
            .unwrap_or(0)
    }
}

/// The shape announced by `BeginMatrix`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Shape {
    n: u32,
    frac_bits: u8,
    tiles: u32,
    words: u32,
}

/// A matrix upload in progress.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Upload {
    shape: Shape,
    /// Tiles whose words are all in and validated.
    tiles_done: u32,
    /// Words received so far: the offset the next chunk must have.
    words_done: u32,
    /// The tile whose words are arriving, with the offset of its first word.
    current: Option<(TileHeader, u32)>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum MatrixState {
    Empty,
    Uploading(Upload),
    Loaded(Shape),
    /// A values-only update of the resident matrix `shape` (whose `frac_bits` becomes
    /// `frac_bits` once it ends): `done` words have their new values.
    Updating {
        shape: Shape,
        frac_bits: u8,
        done: u32,
    },
}

/// The stiffness copy of the resident matrix (protocol version 12).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum StiffnessState {
    Empty,
    /// K's values arriving: `done` words have theirs.
    Updating {
        frac_bits: u8,
        done: u32,
    },
    Complete {
        frac_bits: u8,
    },
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum VectorState {
    Empty,
    Uploading { exponent: i32, received: u32 },
    Complete { exponent: i32 },
}

impl VectorState {
    /// The exponent of a complete vector, or why there is none.
    fn exponent(self, missing: SessionStep) -> Result<i32, ErrorCode> {
        match self {
            VectorState::Complete { exponent } => Ok(exponent),
            VectorState::Uploading { .. } => {
                Err(ErrorCode::OutOfOrder(SessionStep::VectorIncomplete))
            }
            VectorState::Empty => Err(ErrorCode::OutOfOrder(missing)),
        }
    }
}

/// The target's side of the protocol. See the module documentation for its policies.
pub struct Session<'a, E: Executor> {
    store: Storage<'a>,
    info: TargetInfo,
    exec: E,
    /// False after a `Hello` with another protocol version.
    compatible: bool,
    matrix: MatrixState,
    rhs: [VectorState; MAX_DIRECTIONS],
    guess: [VectorState; MAX_DIRECTIONS],
    /// Per direction, the exponent of the solution in its `x`, if there is one.
    solution: [Option<i32>; MAX_DIRECTIONS],
    /// Per direction, the exponent of the solution before the last, kept in its `x0` for
    /// [`Start::Predicted`]: set by a predicted solve that had a previous solution, cleared by
    /// any other solve, a new initial guess or a new matrix.
    kept: [Option<i32>; MAX_DIRECTIONS],
    /// The live loop's tool set and local force model ([`crate::live`]).
    live: Live,
    /// The stiffness copy's state (protocol version 12).
    stiffness: StiffnessState,
    /// A dynamic session's tools and state ([`crate::dynamics`]).
    dynamic: Dynamic,
    /// How the MVUs share the resident matrix.
    plan: Option<Plan>,
}

fn to_usize(v: u32) -> usize {
    usize::try_from(v).unwrap_or(usize::MAX)
}

fn to_u32(v: usize) -> u32 {
    u32::try_from(v).unwrap_or(u32::MAX)
}

const fn out_of_order(step: SessionStep) -> ErrorCode {
    ErrorCode::OutOfOrder(step)
}

impl<'a, E: Executor> Session<'a, E> {
    /// A fresh session over `store`. `info`'s capacities are clamped to what `store` holds and
    /// its protocol version is set to ours; the rest (firmware version, harts) is passed through.
    pub fn new(store: Storage<'a>, mut info: TargetInfo, exec: E) -> Self {
        info.protocol_version = PROTOCOL_VERSION;
        info.word_capacity = info.word_capacity.min(to_u32(store.words.len()));
        info.tile_capacity = info.tile_capacity.min(to_u32(store.tiles.len()));
        info.max_n = info.max_n.min(to_u32(store.max_n()));
        info.harts = info.harts.clamp(1, exec.harts().min(MAX_HARTS) as u8);
        Self {
            store,
            info,
            exec,
            plan: None,
            compatible: true,
            matrix: MatrixState::Empty,
            rhs: [VectorState::Empty; MAX_DIRECTIONS],
            guess: [VectorState::Empty; MAX_DIRECTIONS],
            solution: [None; MAX_DIRECTIONS],
            kept: [None; MAX_DIRECTIONS],
            live: Live::default(),
            stiffness: StiffnessState::Empty,
            dynamic: Dynamic::default(),
        }
    }

    /// What this session answers `Hello` with.
    pub fn info(&self) -> &TargetInfo {
        &self.info
    }

    /// The executor lent to the solver.
    pub fn executor(&self) -> &E {
        &self.exec
    }

    /// True once a matrix is completely uploaded and validated.
    pub fn matrix_loaded(&self) -> bool {
        matches!(self.matrix, MatrixState::Loaded(_))
    }

    /// Turns one request into its response.
    pub fn handle(&mut self, req: Request) -> Response {
        match self.dispatch(req) {
            Ok(response) => response,
            Err(code) => Response::Error(code),
        }
    }

    fn dispatch(&mut self, req: Request) -> Result<Response, ErrorCode> {
        if let Request::Hello { protocol_version } = req {
            return Ok(self.hello(protocol_version));
        }
        if !self.compatible {
            return Err(ErrorCode::VersionMismatch {
                target: PROTOCOL_VERSION,
            });
        }
        match req {
            Request::Hello { .. } => Ok(self.hello(PROTOCOL_VERSION)),
            Request::BeginMatrix {
                n,
                frac_bits,
                tiles,
                words,
            } => self.begin_matrix(Shape {
                n,
                frac_bits,
                tiles,
                words,
            }),
            Request::Tile(header) => self.tile(header),
            Request::Words { offset, words } => self.words(offset, &words),
            Request::EndMatrix { crc32 } => self.end_matrix(crc32),
            Request::BeginVector {
                slot,
                exponent,
                len,
            } => self.begin_vector(slot, exponent, len),
            Request::VectorData {
                slot,
                offset,
                mantissas,
            } => self.vector_data(slot, offset, &mantissas),
            Request::Solve(params) => self.solve(&params),
            Request::ReadSolution {
                direction,
                offset,
                len,
            } => self.read_solution(direction, offset, len),
            Request::BeginUpdate { words, frac_bits } => self.begin_update(words, frac_bits),
            Request::UpdateValues { offset, values } => self.update_values(offset, &values),
            Request::EndUpdate { crc32 } => self.end_update(crc32),
            Request::LiveTool(row) => self.live_tool(row),
            Request::LiveStart(params) => self.live_start(params),
            Request::LiveFrame { tool } => self.live_frame(&tool),
            Request::LiveForce { tool } => self.live_force(&tool),
            Request::ReadField {
                offset,
                stride,
                surface,
            } => self.read_field(offset, stride, surface),
            Request::LiveForceTool { nodes } => self.live_force_tool(&nodes),
            Request::LiveLoad { load } => self.live_load(&load),
            Request::LiveLoadQuery { load } => self.live_load_query(&load),
            Request::BeginStiffness { frac_bits } => self.begin_stiffness(frac_bits),
            Request::DynamicTool(tool) => self.dynamic_tool(tool),
            Request::DynamicStart(params) => self.dynamic_start(params),
            Request::DynamicFrame { tool } => self.dynamic_frame(&tool),
            Request::ReadVector {
                vector,
                direction,
                offset,
                len,
            } => self.read_vector(vector, direction, offset, len),
        }
    }

    fn hello(&mut self, protocol_version: u16) -> Response {
        self.compatible = protocol_version == PROTOCOL_VERSION;
        self.drop_matrix();
        Response::Hello(self.info.clone())
    }

    /// Forgets the matrix, the vectors that belong to it and the solution.
    fn drop_matrix(&mut self) {
        self.unload_mvus();
        self.matrix = MatrixState::Empty;
        self.rhs = [VectorState::Empty; MAX_DIRECTIONS];
        self.guess = [VectorState::Empty; MAX_DIRECTIONS];
        self.solution = [None; MAX_DIRECTIONS];
        self.kept = [None; MAX_DIRECTIONS];
        self.live.clear();
        self.stiffness = StiffnessState::Empty;
        self.dynamic.clear();
    }

    fn begin_matrix(&mut self, shape: Shape) -> Result<Response, ErrorCode> {
        self.drop_matrix();
        if shape.n == 0 || shape.tiles == 0 {
            return Err(ErrorCode::Matrix(MatrixError::EmptyTile { tile: 0 }));
        }
        if shape.n > self.info.max_n {
            return Err(ErrorCode::DimensionTooLarge {
                requested: shape.n,
                capacity: self.info.max_n,
            });
        }
        if shape.words > self.info.word_capacity {
            return Err(ErrorCode::TooManyWords {
                requested: shape.words,
                capacity: self.info.word_capacity,
            });
        }
        if shape.tiles > self.info.tile_capacity {
            return Err(ErrorCode::TooManyTiles {
                requested: shape.tiles,
                capacity: self.info.tile_capacity,
            });
        }
        if shape.frac_bits > MAX_FRAC_BITS {
            return Err(ErrorCode::BadFracBits(shape.frac_bits));
        }
        self.matrix = MatrixState::Uploading(Upload {
            shape,
            tiles_done: 0,
            words_done: 0,
            current: None,
        });
        Ok(Response::Ack)
    }

    fn upload(&self) -> Result<Upload, ErrorCode> {
        match self.matrix {
            MatrixState::Uploading(up) => Ok(up),
            _ => Err(out_of_order(SessionStep::NoMatrixUpload)),
        }
    }

    fn tile(&mut self, header: TileHeader) -> Result<Response, ErrorCode> {
        let mut up = self.upload()?;
        if up.current.is_some() {
            return Err(out_of_order(SessionStep::TileIncomplete));
        }
        if up.tiles_done >= up.shape.tiles {
            return Err(ErrorCode::ChunkTooLong);
        }
        let tile = up.tiles_done;
        validate_mvu(tile, &header, self.info.harts).map_err(ErrorCode::Matrix)?;
        if header.rows == 0 || header.words == 0 {
            return Err(ErrorCode::Matrix(MatrixError::EmptyTile { tile }));
        }
        if header
            .row_base
            .checked_add(header.rows)
            .is_none_or(|end| end > up.shape.n)
        {
            return Err(ErrorCode::Matrix(MatrixError::RowsOutOfRange { tile }));
        }
        if up
            .words_done
            .checked_add(header.words)
            .is_none_or(|end| end > up.shape.words)
        {
            return Err(ErrorCode::Matrix(MatrixError::TotalWordsMismatch {
                expected: up.shape.words,
                found: up.words_done.saturating_add(header.words),
            }));
        }
        // `tiles ≤ tile_capacity ≤ tiles.len()` was checked by `BeginMatrix`.
        let slot = self
            .store
            .tiles
            .get_mut(to_usize(tile))
            .ok_or(ErrorCode::TooManyTiles {
                requested: up.shape.tiles,
                capacity: self.info.tile_capacity,
            })?;
        *slot = header;
        up.current = Some((header, up.words_done));
        self.matrix = MatrixState::Uploading(up);
        Ok(Response::Ack)
    }

    fn words(&mut self, offset: u32, words: &[u32]) -> Result<Response, ErrorCode> {
        let mut up = self.upload()?;
        let Some((header, start)) = up.current else {
            return Err(if up.tiles_done < up.shape.tiles {
                out_of_order(SessionStep::TileExpected)
            } else {
                ErrorCode::ChunkTooLong
            });
        };
        let tile_end = start
            .checked_add(header.words)
            .ok_or(ErrorCode::ChunkTooLong)?;
        let end = chunk_end(up.words_done, offset, words.len(), tile_end)?;
        // `tile_end ≤ words ≤ word_capacity ≤ words.len()` was checked by `Tile`/`BeginMatrix`.
        let dst = self
            .store
            .words
            .get_mut(to_usize(offset)..to_usize(end))
            .ok_or(ErrorCode::ChunkTooLong)?;
        for (d, s) in dst.iter_mut().zip(words) {
            *d = *s;
        }
        up.words_done = end;
        if end == tile_end {
            up.current = None;
            let tile = up.tiles_done;
            let stored = self
                .store
                .words
                .get(to_usize(start)..to_usize(end))
                .unwrap_or(&[]);
            if let Err(e) = validate_tile(tile, &header, stored, up.shape.n) {
                self.matrix = MatrixState::Empty;
                return Err(ErrorCode::Matrix(e));
            }
            up.tiles_done = tile.saturating_add(1);
        }
        self.matrix = MatrixState::Uploading(up);
        Ok(Response::Ack)
    }

    fn end_matrix(&mut self, crc32: u32) -> Result<Response, ErrorCode> {
        let up = self.upload()?;
        if up.current.is_some() {
            return Err(out_of_order(SessionStep::TileIncomplete));
        }
        if up.tiles_done < up.shape.tiles {
            return Err(out_of_order(SessionStep::TilesMissing));
        }
        if up.words_done != up.shape.words {
            self.matrix = MatrixState::Empty;
            return Err(ErrorCode::Matrix(MatrixError::TotalWordsMismatch {
                expected: up.shape.words,
                found: up.words_done,
            }));
        }
        let computed = words_crc(
            self.store
                .words
                .get(..to_usize(up.words_done))
                .unwrap_or(&[]),
        );
        if computed != crc32 {
            self.matrix = MatrixState::Empty;
            return Err(ErrorCode::MatrixCrc { computed });
        }
        let n = to_usize(up.shape.n);
        let planned = cg::plan(
            self.store
                .tiles
                .get(..to_usize(up.shape.tiles))
                .unwrap_or(&[]),
            self.store
                .words
                .get(..to_usize(up.shape.words))
                .unwrap_or(&[]),
            n,
            self.store.kp,
            self.store.partial.len(),
        );
        self.plan = match planned {
            Ok(plan) => Some(plan),
            Err(e) => {
                self.matrix = MatrixState::Empty;
                return Err(match e {
                    PlanError::Overlap { rows, capacity } => {
                        ErrorCode::OverlapTooLarge { rows, capacity }
                    }
                    PlanError::Matrix(e) => ErrorCode::Matrix(e),
                });
            }
        };
        self.matrix = MatrixState::Loaded(up.shape);
        self.load_mvus();
        Ok(Response::Ack)
    }

    /// The matrix is about to change: the hardware MVUs (if any) forget it.
    fn unload_mvus(&self) {
        if let Some(hardware) = self.exec.mvu_backend() {
            hardware.unload();
        }
    }

    /// The matrix just became resident: the hardware MVUs (if any) take it if it fits; the
    /// partial-sum pool is their scratch space (it holds n rows on every target that has them).
    fn load_mvus(&mut self) {
        let (Some(hardware), Some(plan), MatrixState::Loaded(shape)) =
            (self.exec.mvu_backend(), self.plan.as_ref(), self.matrix)
        else {
            return;
        };
        let (tiles, words) = (
            self.store.tiles.get(..to_usize(shape.tiles)),
            self.store.words.get(..to_usize(shape.words)),
        );
        if let (Some(tiles), Some(words)) = (tiles, words) {
            let matrix = Matrix {
                n: to_usize(shape.n),
                frac_bits: shape.frac_bits,
                tiles,
                words,
                plan,
            };
            hardware.load(&matrix, self.store.partial);
        }
    }

    /// The matrix ready to solve with.
    fn loaded(&self) -> Result<Shape, ErrorCode> {
        match self.matrix {
            MatrixState::Loaded(shape) => Ok(shape),
            MatrixState::Updating { .. } => Err(out_of_order(SessionStep::UpdateIncomplete)),
            _ => Err(out_of_order(SessionStep::NoMatrix)),
        }
    }

    /// The resident matrix's shape, also while its values are being updated (vectors and the
    /// solution only need n).
    fn resident(&self) -> Result<Shape, ErrorCode> {
        match self.matrix {
            MatrixState::Loaded(shape) | MatrixState::Updating { shape, .. } => Ok(shape),
            _ => Err(out_of_order(SessionStep::NoMatrix)),
        }
    }

    fn begin_update(&mut self, words: u32, frac_bits: u8) -> Result<Response, ErrorCode> {
        let shape = self.resident()?;
        if words != shape.words {
            return Err(ErrorCode::Matrix(MatrixError::TotalWordsMismatch {
                expected: shape.words,
                found: words,
            }));
        }
        if frac_bits > MAX_FRAC_BITS {
            return Err(ErrorCode::BadFracBits(frac_bits));
        }
        self.unload_mvus();
        self.matrix = MatrixState::Updating {
            shape,
            frac_bits,
            done: 0,
        };
        Ok(Response::Ack)
    }

    fn update_values(&mut self, offset: u32, values: &[i32]) -> Result<Response, ErrorCode> {
        if let StiffnessState::Updating { .. } = self.stiffness {
            return self.stiffness_values(offset, values);
        }
        let MatrixState::Updating {
            shape,
            frac_bits,
            done,
        } = self.matrix
        else {
            return Err(out_of_order(SessionStep::NoUpdate));
        };
        let end = chunk_end(done, offset, values.len(), shape.words)?;
        // `shape.words ≤ word_capacity ≤ words.len()` was checked when the matrix was announced.
        replace_values(
            self.store.words.get_mut(to_usize(offset)..to_usize(end)),
            values,
        )?;
        self.matrix = MatrixState::Updating {
            shape,
            frac_bits,
            done: end,
        };
        Ok(Response::Ack)
    }

    fn end_update(&mut self, crc32: u32) -> Result<Response, ErrorCode> {
        if let StiffnessState::Updating { .. } = self.stiffness {
            return self.end_stiffness(crc32);
        }
        let MatrixState::Updating {
            shape,
            frac_bits,
            done,
        } = self.matrix
        else {
            return Err(out_of_order(SessionStep::NoUpdate));
        };
        if done != shape.words {
            return Err(out_of_order(SessionStep::UpdateIncomplete));
        }
        let computed = words_crc(self.store.words.get(..to_usize(done)).unwrap_or(&[]));
        if computed != crc32 {
            self.drop_matrix();
            return Err(ErrorCode::MatrixCrc { computed });
        }
        self.matrix = MatrixState::Loaded(Shape { frac_bits, ..shape });
        self.load_mvus();
        Ok(Response::Ack)
    }

    /// The state of `slot`, or `DirectionOutOfRange`.
    fn slot_state(&mut self, slot: VectorSlot) -> Result<&mut VectorState, ErrorCode> {
        let d = direction_index(slot.direction())?;
        let states = match slot {
            VectorSlot::Rhs { .. } => &mut self.rhs,
            VectorSlot::InitialGuess { .. } => &mut self.guess,
        };
        states
            .get_mut(d)
            .ok_or(direction_out_of_range(slot.direction()))
    }

    fn begin_vector(
        &mut self,
        slot: VectorSlot,
        exponent: i32,
        len: u32,
    ) -> Result<Response, ErrorCode> {
        *self.slot_state(slot)? = VectorState::Empty;
        // A dynamic session's state lives in the vectors.
        self.dynamic.clear();
        match slot {
            // x0 now holds neither the guess nor the kept solution.
            VectorSlot::InitialGuess { direction } => self.kept[usize::from(direction)] = None,
            VectorSlot::Rhs { direction } => self.live.rhs_replaced(usize::from(direction)),
        }
        let shape = self.resident()?;
        if len != shape.n {
            return Err(ErrorCode::LengthMismatch {
                expected: shape.n,
                got: len,
            });
        }
        *self.slot_state(slot)? = VectorState::Uploading {
            exponent,
            received: 0,
        };
        Ok(Response::Ack)
    }

    fn vector_data(
        &mut self,
        slot: VectorSlot,
        offset: u32,
        mantissas: &[i32],
    ) -> Result<Response, ErrorCode> {
        let VectorState::Uploading { exponent, received } = *self.slot_state(slot)? else {
            return Err(out_of_order(SessionStep::NoVectorUpload));
        };
        // A vector upload only exists while its matrix is resident.
        let shape = self.resident()?;
        let end = chunk_end(received, offset, mantissas.len(), shape.n)?;
        if mantissas
            .iter()
            .any(|&m| i64::from(m).abs() >= MANTISSA_LIMIT)
        {
            return Err(ErrorCode::MantissaOutOfRange);
        }
        let d = direction_index(slot.direction())?;
        let storage = self
            .store
            .directions
            .get_mut(d)
            .ok_or(direction_out_of_range(slot.direction()))?;
        let vector = match slot {
            VectorSlot::Rhs { .. } => &mut *storage.b,
            VectorSlot::InitialGuess { .. } => &mut *storage.x0,
        };
        let dst = vector
            .get_mut(to_usize(offset)..to_usize(end))
            .ok_or(ErrorCode::ChunkTooLong)?;
        for (d, s) in dst.iter_mut().zip(mantissas) {
            *d = *s;
        }
        *self.slot_state(slot)? = if end == shape.n {
            VectorState::Complete { exponent }
        } else {
            VectorState::Uploading {
                exponent,
                received: end,
            }
        };
        Ok(Response::Ack)
    }

    fn solve(&mut self, params: &SolveParams) -> Result<Response, ErrorCode> {
        let directions = usize::from(params.directions);
        if !(1..=MAX_DIRECTIONS).contains(&directions) {
            return Err(ErrorCode::Solve(SolveFailure::BadDirections(
                params.directions,
            )));
        }
        let which: heapless::Vec<usize, MAX_DIRECTIONS> = (0..directions).collect();
        self.dynamic.clear();
        let (report, _) = self.solve_directions(params, &which, [None; MAX_DIRECTIONS], false)?;
        Ok(Response::Solved(report))
    }

    /// Solves the storage directions `which` (1..=3 of them, fused in that order; a live frame
    /// solves only the directions its tool moved) with `params` (whose `directions` is
    /// ignored), each from `r_start[d]` where given ([`cg::System::r_start`]). Every other
    /// direction keeps its solution if `keep_others` (else, as after a `Solve` request, only
    /// the solved directions have one). Returns the report and each direction's [`Outcome`].
    fn solve_directions(
        &mut self,
        params: &SolveParams,
        which: &[usize],
        r_start: [Option<GivenResidual>; MAX_DIRECTIONS],
        keep_others: bool,
    ) -> Result<(SolveReport, [Outcome; MAX_DIRECTIONS]), ErrorCode> {
        let shape = self.loaded()?;
        if !(1..=MAX_DIRECTIONS).contains(&which.len())
            || which.iter().any(|&d| d >= MAX_DIRECTIONS)
        {
            return Err(ErrorCode::Solve(SolveFailure::BadDirections(
                which.len() as u8
            )));
        }
        let n = to_usize(shape.n);
        // Every slice below is within the storage: n ≤ max_n and the matrix's counts ≤ its
        // capacities were checked when it was announced. Should that ever not hold, refuse.
        let too_large = ErrorCode::DimensionTooLarge {
            requested: shape.n,
            capacity: self.info.max_n,
        };
        // All checks first, so that a refused solve changes nothing.
        let mut b_exponents = [0i32; MAX_DIRECTIONS];
        let mut x_exponents = [0i32; MAX_DIRECTIONS];
        for &d in which {
            b_exponents[d] = self.rhs[d].exponent(SessionStep::NoRhs)?;
            x_exponents[d] = match params.start {
                Start::Zero => 0,
                Start::Previous => {
                    self.solution[d].ok_or(out_of_order(SessionStep::NoPreviousSolution))?
                }
                Start::Uploaded => self.guess[d].exponent(SessionStep::NoInitialGuess)?,
                // Never refused: with fewer solutions kept the prediction is of lower order.
                Start::Predicted => self.solution[d].unwrap_or(0),
            };
        }
        let plan = self.plan.ok_or(out_of_order(SessionStep::NoMatrix))?;
        let Parts {
            matrix,
            work,
            directions: vectors,
        } = self.store.parts(shape, Words::Resident, &plan)?;
        let mut systems: heapless::Vec<System<'_>, MAX_DIRECTIONS> = heapless::Vec::new();
        for (d, v) in vectors.iter_mut().enumerate() {
            if !which.contains(&d) {
                continue;
            }
            let DirectionStorage { b, x, x0, r } = v;
            let (Some(b), Some(x), Some(x0), Some(r)) =
                (b.get(..n), x.get_mut(..n), x0.get_mut(..n), r.get_mut(..n))
            else {
                return Err(too_large);
            };
            let kept = &mut self.kept[d];
            match (params.start, self.solution[d], *kept) {
                (Start::Uploaded, ..) => x.copy_from_slice(x0),
                (Start::Predicted, None, _) => x.fill(0),
                (Start::Predicted, Some(e1), None) => {
                    x0.copy_from_slice(x);
                    *kept = Some(e1);
                }
                (Start::Predicted, Some(e1), Some(e2)) => {
                    x_exponents[d] = predict::extrapolate(x, e1, x0, e2);
                    *kept = Some(e1);
                }
                _ => {}
            }
            if params.start == Start::Predicted {
                // x0 now holds u(t−1), no longer an uploaded guess.
                self.guess[d] = VectorState::Empty;
            } else {
                *kept = None;
            }
            let _ = systems.push(System {
                b,
                b_exponent: b_exponents[d],
                x,
                x_exponent: x_exponents[d],
                r,
                r_start: r_start[d],
                outcome: Outcome::default(),
            });
        }
        for (d, solution) in self.solution.iter_mut().enumerate() {
            if !keep_others || which.contains(&d) {
                *solution = None;
            }
        }
        if let Ok(started) = self.live.started_mut() {
            started.field_exponent = None;
            started.base = None;
        }
        let report = cg::solve(&matrix, &mut systems, work, params, &self.exec).map_err(|e| {
            self.kept = [None; MAX_DIRECTIONS];
            ErrorCode::Solve(e)
        })?;
        let mut outcomes = [Outcome::default(); MAX_DIRECTIONS];
        for (&d, system) in which.iter().zip(&systems) {
            self.solution[d] = Some(system.x_exponent);
            outcomes[d] = system.outcome;
        }
        Ok((report, outcomes))
    }

    fn read_solution(
        &mut self,
        direction: u8,
        offset: u32,
        len: u16,
    ) -> Result<Response, ErrorCode> {
        let d = direction_index(direction)?;
        let exponent = self
            .solution
            .get(d)
            .copied()
            .flatten()
            .ok_or(out_of_order(SessionStep::NoSolution))?;
        self.vector_chunk(direction, exponent, |v| &*v.x, offset, len)
    }

    /// `ReadVector` (protocol version 13): the right-hand side wherever one is complete; a
    /// dynamic session's velocities (in x0) and residual once it has started, the residual
    /// only after a step that left it (none before the first step, nor after a step that ran
    /// out of its budget).
    fn read_vector(
        &mut self,
        vector: StateVector,
        direction: u8,
        offset: u32,
        len: u16,
    ) -> Result<Response, ErrorCode> {
        let d = direction_index(direction)?;
        let dynamic = |s: &Self| {
            s.dynamic
                .state()
                .copied()
                .ok_or(ErrorCode::Dynamic(DynamicError::NotStarted))
        };
        match vector {
            StateVector::Rhs => {
                let exponent = self.rhs[d].exponent(SessionStep::NoRhs)?;
                self.vector_chunk(direction, exponent, |v| &*v.b, offset, len)
            }
            StateVector::Velocity => {
                let exponent = dynamic(self)?.v[d].e;
                self.vector_chunk(direction, exponent, |v| &*v.x0, offset, len)
            }
            StateVector::Residual => {
                let block =
                    dynamic(self)?.residual[d].ok_or(out_of_order(SessionStep::NoSolution))?;
                self.vector_chunk(direction, block.e, |v| &*v.r, offset, len)
            }
        }
    }

    /// The `Solution` answer of `ReadSolution` and `ReadVector`: at most `len` (and
    /// [`CHUNK_LEN`]) mantissas of one direction's vector from `offset`, below n.
    fn vector_chunk(
        &self,
        direction: u8,
        exponent: i32,
        vector: impl for<'s> Fn(&'s DirectionStorage<'a>) -> &'s [i32],
        offset: u32,
        len: u16,
    ) -> Result<Response, ErrorCode> {
        let shape = self.resident()?;
        if offset >= shape.n {
            return Err(ErrorCode::ChunkTooLong);
        }
        let len = u32::from(len).min(to_u32(CHUNK_LEN));
        let end = offset.saturating_add(len).min(shape.n);
        let values = self
            .store
            .directions
            .get(usize::from(direction))
            .and_then(|v| vector(v).get(to_usize(offset)..to_usize(end)))
            .ok_or(ErrorCode::ChunkTooLong)?;
        let mantissas = heapless::Vec::from_slice(values).map_err(|_| ErrorCode::ChunkTooLong)?;
        Ok(Response::Solution {
            direction,
            offset,
            exponent,
            mantissas,
        })
    }
}

fn direction_out_of_range(direction: u8) -> ErrorCode {
    ErrorCode::DirectionOutOfRange {
        direction,
        max: MAX_DIRECTIONS as u8,
    }
}

/// `direction` as an index into the per-direction state, or `DirectionOutOfRange`.
fn direction_index(direction: u8) -> Result<usize, ErrorCode> {
    let d = usize::from(direction);
    if d < MAX_DIRECTIONS {
        Ok(d)
    } else {
        Err(direction_out_of_range(direction))
    }
}

/// Where an in-order chunk of `len` items at `offset` ends. Every upload (words, value updates,
/// vectors) takes its chunks strictly in order, so the chunk must start at `expected`, where the
/// previous one ended, and must not run past `limit`.
fn chunk_end(expected: u32, offset: u32, len: usize, limit: u32) -> Result<u32, ErrorCode> {
    if offset != expected {
        return Err(ErrorCode::UnexpectedOffset {
            expected,
            got: offset,
        });
    }
    u32::try_from(len)
        .ok()
        .and_then(|len| offset.checked_add(len))
        .filter(|&end| end <= limit)
        .ok_or(ErrorCode::ChunkTooLong)
}

/// Replaces the values of the words `dst` (a value update's chunk: the matrix's, or the
/// stiffness copy's) with `values`, each checked to fit the 21-bit value field; `None` is a
/// chunk beyond the store.
fn replace_values(dst: Option<&mut [u32]>, values: &[i32]) -> Result<(), ErrorCode> {
    if let Some(&bad) = values
        .iter()
        .find(|&&v| !(VALUE_MIN..=VALUE_MAX).contains(&v))
    {
        return Err(ErrorCode::ValueOutOfRange(bad));
    }
    let dst = dst.ok_or(ErrorCode::ChunkTooLong)?;
    for (d, &v) in dst.iter_mut().zip(values) {
        *d = (*d & !VALUE_MASK) | (v as u32 & VALUE_MASK);
    }
    Ok(())
}

mod dynamic_glue;
mod live_glue;

#[cfg(test)]
mod tests;
