//! The firmware's static storage: the matrix store and the vectors, lent to the session.

use core::cell::UnsafeCell;
use core::sync::atomic::{AtomicUsize, Ordering};

use crate::board::{Board, Bsp};
use deform_shared::matrix::TileHeader;
use deform_shared::protocol::MAX_DIRECTIONS;
use deform_target_core::kernel::{Lanes, Sums};
use deform_target_core::session::{DirectionStorage, Storage};

/// Instruction words the matrix store holds (the board's [`Bsp::WORD_CAPACITY`]).
pub const WORD_CAPACITY: usize = Board::WORD_CAPACITY;
/// Tile headers the matrix store holds.
pub const TILE_CAPACITY: usize = Board::TILE_CAPACITY;
/// Largest dimension. Per direction four vectors of `4·MAX_N` bytes, the interleaved search
/// directions `16·MAX_N`, K·p `12·MAX_N`.
pub const MAX_N: usize = Board::MAX_N;
/// Rows of private partial sums for MVUs whose row ranges overlap (`12·MAX_N` bytes): the
/// overlapping scheme (thesis 4.1.1) may use up to n of them beyond the rows themselves.
pub const PARTIAL_ROWS: usize = MAX_N;

/// Values of the live loop's response columns (the board's [`Bsp::RESPONSE_VALUES`]), and as
/// many `i16` residuals of them.
pub const RESPONSE_VALUES: usize = Board::RESPONSE_VALUES;

/// Words of a dynamic session's stiffness copy (the board's [`Bsp::STIFFNESS_WORDS`]).
pub const STIFFNESS_WORDS: usize = Board::STIFFNESS_WORDS;

/// Everything the session works in. All zero at boot, so it lands in `.bss`.
///
/// In declaration order (`repr(C)`), so that p and Kp follow the directions' vectors at
/// chosen offsets modulo 4 KiB, the VexRiscv's direct-mapped data cache (every vector is a
/// multiple of 4 KiB): with r at 0, x is at 2 KiB ([`DirectionBuffers`]), p at 3 KiB and Kp
/// at 0. Pass XP's p, x and r stay a quarter of the cache apart, element by element; and one
/// direction's vectors of up to 512 nodes (p, x and r 2 KiB, Kp 4 KiB: 8 bytes a row) keep
/// lines for the next pass. The MVU phase's pᵀKp reads p and Kp row by row, p at half Kp's
/// stride, so each line p shares with Kp it reads before Kp does, and Kp's lines stay cached
/// except the quarter under p's second half. Pass R then reads those lines of Kp before r,
/// at half Kp's stride, takes them over; and pass XP finds every line of r still cached,
/// since p and x lie in the other half from r's first 2 KiB (p's second half reaching r's
/// lines only after r has been read there).
#[repr(C)]
pub struct Buffers {
    words: [u32; WORD_CAPACITY],
    tiles: [TileHeader; TILE_CAPACITY],
    directions: [DirectionBuffers; MAX_DIRECTIONS],
    skew_p: [u8; SKEW_P],
    p: [Lanes; MAX_N],
    skew_kp: [u8; SKEW_KP],
    kp: [Sums; MAX_N],
    partial: [Sums; PARTIAL_ROWS],
    responses: [i32; RESPONSE_VALUES],
    residuals: [i16; RESPONSE_VALUES],
    stiffness: [u32; STIFFNESS_WORDS],
}

/// The vectors of one direction of a fused solve.
///
/// Each vector is a multiple of 4 KiB, so without the skews x, r and p would start at the same
/// offset modulo 4 KiB, and element i of each would fall in the same line of the VexRiscv's
/// 4 KiB direct-mapped data cache: pass XP, which reads x, r and p element by element, would
/// evict each with the next. The skews put b, x, x0 and r a quarter of the cache apart (p,
/// which follows the directions in [`Buffers`], has a skew of its own).
#[repr(C)]
pub struct DirectionBuffers {
    b: [i32; MAX_N],
    skew_x: [u8; CACHE_SKEW],
    x: [i32; MAX_N],
    skew_x0: [u8; CACHE_SKEW],
    x0: [i32; MAX_N],
    skew_r: [u8; CACHE_SKEW],
    r: [i32; MAX_N],
    skew_end: [u8; CACHE_SKEW],
}

/// A quarter of the VexRiscv's 4 KiB data cache ([`DirectionBuffers`]).
const CACHE_SKEW: usize = 1024;

/// p's skew after the directions: p three quarters of the cache after r (modulo 4 KiB),
/// where a 2 KiB p (one direction's 4 bytes a node, 512 nodes) leaves pass R's r alone.
const SKEW_P: usize = 2 * CACHE_SKEW;
/// Kp's skew after p: Kp at r's offset modulo 4 KiB (see [`Buffers`]).
const SKEW_KP: usize = CACHE_SKEW;

const NO_TILE: TileHeader = TileHeader {
    row_base: 0,
    col_base: 0,
    rows: 0,
    words: 0,
    mvu: 0,
    mirrored: false,
};

impl DirectionBuffers {
    const ZERO: DirectionBuffers = DirectionBuffers {
        b: [0; MAX_N],
        skew_x: [0; CACHE_SKEW],
        x: [0; MAX_N],
        skew_x0: [0; CACHE_SKEW],
        x0: [0; MAX_N],
        skew_r: [0; CACHE_SKEW],
        r: [0; MAX_N],
        skew_end: [0; CACHE_SKEW],
    };

    fn storage(&mut self) -> DirectionStorage<'_> {
        DirectionStorage {
            b: &mut self.b,
            x: &mut self.x,
            x0: &mut self.x0,
            r: &mut self.r,
        }
    }
}

impl Buffers {
    const ZERO: Buffers = Buffers {
        words: [0; WORD_CAPACITY],
        tiles: [NO_TILE; TILE_CAPACITY],
        directions: [DirectionBuffers::ZERO; MAX_DIRECTIONS],
        skew_p: [0; SKEW_P],
        p: [[0; 4]; MAX_N],
        skew_kp: [0; SKEW_KP],
        kp: [[0; MAX_DIRECTIONS]; MAX_N],
        partial: [[0; MAX_DIRECTIONS]; PARTIAL_ROWS],
        responses: [0; RESPONSE_VALUES],
        residuals: [0; RESPONSE_VALUES],
        stiffness: [0; STIFFNESS_WORDS],
    };

    /// Lends all buffers to a session; p and Kp are `vectors` instead where the board's
    /// hardware MVUs hold them in their own memory (see `board::Mvus`).
    pub fn storage(
        &mut self,
        vectors: Option<(&'static mut [Lanes], &'static mut [Sums])>,
    ) -> Storage<'_> {
        let [d0, d1, d2] = &mut self.directions;
        let (p, kp) = match vectors {
            Some((p, kp)) => (p, kp),
            None => (&mut self.p[..], &mut self.kp[..]),
        };
        Storage {
            words: &mut self.words,
            tiles: &mut self.tiles,
            directions: [d0.storage(), d1.storage(), d2.storage()],
            p,
            kp,
            partial: &mut self.partial,
            responses: &mut self.responses,
            residuals: &mut self.residuals,
            stiffness: &mut self.stiffness,
        }
    }
}

/// A `static` whose contents can be borrowed mutably exactly once, for the whole program.
///
/// This is the one place the firmware needs `unsafe` for memory: it turns a `static` into a
/// `&'static mut` without `static mut`, guarded by an atomic flag so that a second `take` (from
/// any hart) gets `None` instead of an aliasing reference.
pub struct TakeOnce<T> {
    taken: AtomicUsize,
    value: UnsafeCell<T>,
}

// SAFETY: `value` is only reached through the single `&mut` that `take` hands out, so sharing
// the `TakeOnce` itself between harts shares nothing but the atomic flag; moving that `&mut T`
// to another hart needs `T: Send`.
unsafe impl<T: Send> Sync for TakeOnce<T> {}

impl<T> TakeOnce<T> {
    pub const fn new(value: T) -> Self {
        Self {
            taken: AtomicUsize::new(0),
            value: UnsafeCell::new(value),
        }
    }

    /// The contents, the first time; `None` ever after.
    // A `&mut` from a `&` is this type's purpose; the flag makes it unique.
    #[allow(clippy::mut_from_ref)]
    pub fn take(&'static self) -> Option<&'static mut T> {
        if !crate::atomic::set_flag(&self.taken, Ordering::AcqRel) {
            return None;
        }
        // SAFETY: the flag was set here, which happens exactly once, so no other reference
        // to `value` exists or will ever be created; it lives as long as the static.
        Some(unsafe { &mut *self.value.get() })
    }
}

/// The storage, taken once by `main`.
pub static BUFFERS: TakeOnce<Buffers> = TakeOnce::new(Buffers::ZERO);
