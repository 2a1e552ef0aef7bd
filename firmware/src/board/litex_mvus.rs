//! The MVU array of `gateware/` on a LiteX SoC (thesis 4.2.1, Fig. 4-8): the hardware MVU phase.
//!
//! - **Found** from the SoC's csr.json at build time (build.rs: the `mvus_*` registers, the
//!   `mvus` memory region and its layout constants) and from its capacity registers at boot
//!   (MVUs, rows, words and tiles per MVU), so one firmware build runs on an SoC with any number
//!   of MVUs, none included (then it runs the software kernel, as on an SoC without the array).
//! - **Vectors**: p and Kp are windows of the array's memory region, laid out exactly as the
//!   solver's `[Lanes]` and `[Sums]` (gateware/deform_gateware/mvu_array.py): 16 bytes a node
//!   of p, which the solver keeps for every direction count on a board with an MVU backend
//!   (elsewhere one direction's p is 4 bytes a node). They are lent to
//!   the solver as its p and Kp ([`probe`]), so an MVU phase copies no vector. The region is
//!   uncached I/O on this VexRiscv (bit 31 set), so the CPU never reads a stale Kp.
//! - **Loading** ([`MvuBackend::load`]): each resident matrix is laid out by
//!   `deform_target_core::mvu_program` and written through the bus (words, tiles, lengths, row
//!   owners, shared rows); one that does not fit is refused with a log line, and its phases run
//!   in software.
//! - **A phase** ([`MvuBackend::run`]): write the direction count and `start`, wait for the end
//!   ([`wait`]), read pᵀKp and the OR of |Kp| into the solver's slot; Kp is already where the
//!   solver reads it.

use core::sync::atomic::{compiler_fence, AtomicU32, AtomicUsize, Ordering};

use deform_shared::protocol::MAX_DIRECTIONS;
use deform_target_core::cg::Matrix;
use deform_target_core::kernel::{Lanes, Sums};
use deform_target_core::mvu_backend::{MvuBackend, MvuOut};
use deform_target_core::mvu_program::{build, Capacity, ProgramError, ProgramSink, TileEntry};

use super::litex_vexriscv::{read32, write32};
use super::Mvus;

/// The addresses generated from csr.json.
use super::litex_vexriscv::csr::mvus as regs;

/// The array's state as the firmware knows it: one 16-byte block, so that a phase, which finds
/// it evicted from the data cache by the SVU's passes, misses on one line only.
#[repr(C, align(16))]
pub struct LitexMvus {
    /// The loaded matrix's n, 0 when no program is loaded (then the Kp window is plain). One
    /// word where a flag beside it cost a phase a second load.
    n: AtomicU32,
    /// The array's own counts (since reset) when the matrix was loaded: its phases, their
    /// clocks (start to the end of the reduction) and MVU 0's fetch stalls. What they grew by
    /// is logged when the matrix is dropped, beside which the solver's counters show what the
    /// CPU spent around them (modulo 2^32). A phase reads none of them.
    at_load: [AtomicU32; 3],
}

static ARRAY: LitexMvus = LitexMvus {
    n: AtomicU32::new(0),
    at_load: [AtomicU32::new(0), AtomicU32::new(0), AtomicU32::new(0)],
};

/// The array's counts since reset: phases, their clocks, MVU 0's fetch stalls.
fn counts() -> [u32; 3] {
    [regs::PHASES, regs::CYCLES, regs::STALLS].map(read32)
}

/// Set once the vectors have been handed out.
static TAKEN: AtomicUsize = AtomicUsize::new(0);

fn p_window() -> usize {
    regs::BASE + regs::P_OFFSET
}

fn kp_window() -> usize {
    regs::BASE + regs::KP_OFFSET
}

/// The MVU array, if the SoC has one with at least one MVU; the first call only.
pub fn probe() -> Option<Mvus> {
    if !regs::PRESENT || read32(regs::COUNT) == 0 {
        return None;
    }
    if crate::atomic::set_flag(&TAKEN, Ordering::AcqRel) {
        let nodes = read32(regs::NODES) as usize;
        write32(regs::KP_PLAIN, 1);
        // SAFETY: the p and Kp windows are `nodes` rows of memory in the array's region
        // (16-byte `Lanes` and 24-byte `Sums` each, aligned: the region is 16 MiB-aligned),
        // which nothing else in the firmware addresses; the `TAKEN` flag makes these the only
        // references to them. Reads return what was last written (the bus does read-modify-
        // write of whole entries), except that an MVU phase writes Kp — only while `run` waits
        // for it, with the solver's Kp handed to it and compiler fences on either side, like a
        // DMA transfer into a buffer.
        let (p, kp) = unsafe {
            (
                core::slice::from_raw_parts_mut(p_window() as *mut Lanes, nodes),
                core::slice::from_raw_parts_mut(kp_window() as *mut Sums, nodes),
            )
        };
        Some(Mvus {
            backend: &ARRAY,
            p,
            kp,
        })
    } else {
        None
    }
}

/// Writes a program into the array's memories through the bus.
struct Bus;

fn unit(mvu: usize) -> usize {
    regs::BASE + regs::UNIT_OFFSET + mvu * regs::UNIT_STRIDE
}

impl ProgramSink for Bus {
    fn word(&mut self, mvu: usize, index: usize, word: u32, flags: u8) {
        let at = unit(mvu) + regs::UNIT_WORDS + 8 * index;
        write32(at, word);
        write32(at + 4, u32::from(flags));
    }

    /// The first word is held by the array until the second completes the entry.
    fn tile(&mut self, mvu: usize, index: usize, e: TileEntry) {
        let at = unit(mvu) + regs::UNIT_TILES + 8 * index;
        write32(at, e.row_base | (e.col_base << 16));
        write32(at + 4, e.mirror_col_base | (u32::from(e.mirrored) << 31));
    }

    fn length(&mut self, mvu: usize, words: usize) {
        write32(unit(mvu) + regs::UNIT_LENGTH, words as u32);
    }

    fn owner(&mut self, row: usize, owner: u8) {
        write32(regs::BASE + regs::OWNER_OFFSET + 4 * row, u32::from(owner));
    }

    fn shared(&mut self, index: usize, row: usize, contributors: u8, owner: u8) {
        let entry = row as u32 | u32::from(contributors) << 16 | u32::from(owner) << 24;
        write32(regs::BASE + regs::SHARED_OFFSET + 4 * index, entry);
    }
}

/// A value of `words` CSR words, most significant word first (LiteX's CSR ordering).
fn read_wide(addr: usize, words: usize) -> u128 {
    (0..words).fold(0u128, |v, k| v << 32 | u128::from(read32(addr + 4 * k)))
}

fn why(e: &ProgramError) -> &'static str {
    match e {
        ProgramError::NoSuchMvu { .. } => "a tile names an MVU the array lacks",
        ProgramError::DimensionTooLarge { .. } => "n exceeds the array's rows",
        ProgramError::TooManyWords { .. } => "an MVU's words exceed its word memory",
        ProgramError::TooManyTiles { .. } => "an MVU's tiles exceed its tile table",
        ProgramError::RowUncovered { .. } => "a row no tile writes",
        ProgramError::Inconsistent => "inconsistent tiles",
    }
}

impl MvuBackend for LitexMvus {
    fn mvus(&self) -> usize {
        read32(regs::COUNT) as usize
    }

    fn unload(&self) {
        // A load and a store: this VexRiscv has no AMOs (firmware/src/atomic.rs).
        let loaded = self.n.load(Ordering::Relaxed) != 0;
        self.n.store(0, Ordering::Relaxed);
        write32(regs::KP_PLAIN, 1);
        let now = counts();
        let [phases, cycles, stalls] =
            core::array::from_fn(|k| now[k].wrapping_sub(self.at_load[k].load(Ordering::Relaxed)));
        if loaded && phases > 0 {
            defmt::info!(
                "MVU array: {=u32} phases, {=u32} cycles in the MVUs, {=u32} of them with MVU 0's fetch stalled",
                phases,
                cycles,
                stalls
            );
        }
    }

    fn load(&self, a: &Matrix<'_>, scratch: &mut [Sums]) -> bool {
        self.unload();
        let capacity = Capacity {
            mvus: self.mvus(),
            nodes: read32(regs::NODES) as usize,
            words: read32(regs::WORDS) as usize,
            tiles: read32(regs::TILES) as usize,
        };
        match build(a.tiles, a.words, a.n, &capacity, scratch, &mut Bus) {
            Ok(program) => {
                write32(regs::N, a.n as u32);
                write32(regs::SHARED_ROWS, program.shared_rows as u32);
                write32(regs::KP_PLAIN, 0);
                for (at, now) in self.at_load.iter().zip(counts()) {
                    at.store(now, Ordering::Relaxed);
                }
                self.n.store(a.n as u32, Ordering::Relaxed);
                defmt::info!(
                    "hardware MVUs hold the matrix: {=usize} words on {=usize} MVU(s), {=usize} shared rows",
                    a.words.len(),
                    capacity.mvus,
                    program.shared_rows
                );
                true
            }
            Err(e) => {
                defmt::warn!(
                    "hardware MVUs cannot hold the matrix ({=str}): the MVU phase runs in software",
                    why(&e)
                );
                false
            }
        }
    }

    /// Also sets the array's direction count for the solve, so that a phase's `run` writes
    /// only `start` (one CSR write less on the phase's path).
    fn begin_solve(&self, n: usize, p: *const Lanes, kp: *mut Sums, directions: usize) -> bool {
        let ours = p as usize == p_window() && kp as usize == kp_window();
        let taken = n != 0
            && self.n.load(Ordering::Relaxed) as usize == n
            && ours
            && (1..=MAX_DIRECTIONS).contains(&directions);
        if taken {
            write32(regs::DIRECTIONS, directions as u32);
        }
        taken
    }

    /// Starts the phase at once: the instructions before `start` fall in the phase's span, and
    /// each cold cache line costs some 20 clocks, so `run` is one write (`begin_solve` set the
    /// direction count) and a call, inlined into the solver's phase (the solver calls this
    /// driver directly, not through a vtable: see `deform_target_core::mvu_backend::NoMvus`).
    #[inline(always)]
    fn run(&self, directions: usize, (p_kp, kp_or): MvuOut<'_>) {
        // Every store to p before the start.
        compiler_fence(Ordering::SeqCst);
        write32(regs::START, 1);
        Self::finish(directions, p_kp, kp_or);
    }
}

impl LitexMvus {
    /// [`read_out`](Self::read_out) twice: the first pass, while the array runs, reads the
    /// registers' old values and so fetches its instructions; the second waits for the end and
    /// finds them in the instruction cache. (Waiting holds the bus: code first reached after
    /// the wait would be fetched only then, some 20 clocks a line.)
    #[inline(never)]
    fn finish(
        directions: usize,
        p_kp: &mut [i128; MAX_DIRECTIONS],
        kp_or: &mut [u64; MAX_DIRECTIONS],
    ) {
        Self::read_out(directions, p_kp, kp_or, false);
        Self::read_out(directions, p_kp, kp_or, true);
    }

    /// pᵀKp and the OR of |Kp| into the solver's slot, after waiting for the phase's end if
    /// `end`. The same instructions in both passes (not inlined, no branch but the wait's), so
    /// that the first pass warms all of the second's. Each direction's registers are read
    /// before its results are stored: a load behind a store waits for the store's
    /// write-through to RAM.
    #[inline(never)]
    fn read_out(
        directions: usize,
        p_kp: &mut [i128; MAX_DIRECTIONS],
        kp_or: &mut [u64; MAX_DIRECTIONS],
        end: bool,
    ) {
        if end {
            wait();
            // Every load of Kp after the end.
            compiler_fence(Ordering::SeqCst);
        }
        for d in 0..MAX_DIRECTIONS {
            if d == directions {
                break;
            }
            let (s, or) = (read_wide(regs::P_KP[d], 4), read_wide(regs::KP_OR[d], 2));
            (p_kp[d], kp_or[d]) = (s as i128, or as u64);
        }
    }
}

/// Waits for the phase that `start` began. The array's region withholds its acknowledge while a
/// phase runs, so one read there returns when the phase ends, where polling `busy` took a CSR
/// read and a branch every 8 clocks (over 100 polls a phase on 4 MVUs, 400 on one). `busy`
/// is still read once: the read may reach the array before the write of `start` has raised
/// `busy`, and then returns at once. (A phase is far shorter than the bus's timeout of 10⁶
/// clocks: an MVU holds at most `WORDS` words.)
fn wait() {
    read32(p_window());
    while read32(regs::BUSY) != 0 {}
}
