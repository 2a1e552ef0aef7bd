//! How a matrix is laid out in the memories of hardware MVUs (`gateware/`, thesis 4.2.1):
//! the program each MVU runs, and the tables that tell the MVU array where each row of Kp lives.
//!
//! # What a hardware MVU holds
//!
//! - **Word memory**: its tiles' instruction words back to back, in tile order (the EM bit ends
//!   each tile), each with four **write-back flags** beside it (bits 32..35 of a 36-bit entry,
//!   the width of an ECP5 block RAM; meaningful on ER words only, see [`flags`]).
//! - **Tile table**: per tile `row_base`, `col_base`, `n − 1 − col_base` (where a mirrored
//!   tile's columns count down from, kept so that the MVU need not subtract when it moves to a
//!   tile) and whether it is mirrored ([`TileEntry`]); the MVU moves to the next entry at each
//!   EM word.
//! - **Kp memory**: one row of sums (three directions, 64 bits each) per row of K. At each ER
//!   word the MVU *writes back* its row sum: stored where the flag says this is the MVU's first
//!   contribution to that row in the phase, added to what is there otherwise. A mirrored tile's
//!   ER word writes back twice: the own row, then the mirror row n − 1 − i.
//! - **pᵀKp and max |Kp|**: pᵀKp is linear in Kp, so each write-back adds p[row]·sum to the
//!   MVU's pᵀKp exactly, whoever else adds to that row. max |Kp| (an OR of magnitudes, as in
//!   [`crate::kernel::p_kp_and_max`]) needs the finished row: the *last* flag marks the
//!   write-back after which a row that only this MVU writes is complete.
//!
//! # Rows that several MVUs write (thesis 4.1.1)
//!
//! Each row has an **owner**: the MVU whose Kp memory holds the row's value as the CPU (and the
//! SVU) read it. A row written by one MVU is owned by it. A row written by several is a
//! **shared row**: after all MVUs finish, the array adds the contributors' sums into the
//! owner's memory and ORs the total into max |Kp| (the shared-rows list: row, contributor mask,
//! owner). Row partitions (4.1.2) have no shared rows; overlapping ones have a few at the
//! boundaries.
//!
//! The layout depends only on the tiles, never on p, so it is built once per upload (and again
//! after a values-only update), not per iteration. Nothing here touches hardware: the firmware
//! streams the program into its MVUs' memories through a [`ProgramSink`], and the gateware's
//! unit tests get the very same program from it.

use deform_shared::matrix::TileHeader;
use deform_shared::protocol::MAX_HARTS;
use deform_shared::word::ER_BIT;

use crate::kernel::Sums;

/// The write-back flags beside an ER word (bits 32..35 of a word-memory entry).
pub mod flags {
    /// The own row's sum is stored, not added: the MVU's first write-back to that row.
    pub const FIRST_OWN: u8 = 1 << 0;
    /// The own row is complete after this write-back (only this MVU writes it).
    pub const LAST_OWN: u8 = 1 << 1;
    /// As [`FIRST_OWN`], for the mirror row of a mirrored tile.
    pub const FIRST_MIRROR: u8 = 1 << 2;
    /// As [`LAST_OWN`], for the mirror row.
    pub const LAST_MIRROR: u8 = 1 << 3;
}

/// One entry of an MVU's tile table.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct TileEntry {
    pub row_base: u32,
    pub col_base: u32,
    /// n − 1 − col_base: a mirrored word of column c reads p[mirror_col_base − c].
    pub mirror_col_base: u32,
    pub mirrored: bool,
}

/// What the MVU array holds (its capacity registers).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Capacity {
    /// MVUs in the array.
    pub mvus: usize,
    /// Rows of p and Kp (the largest n).
    pub nodes: usize,
    /// Words per MVU.
    pub words: usize,
    /// Tiles per MVU.
    pub tiles: usize,
}

/// Why a matrix does not fit the hardware MVUs (the software kernel then runs the MVU phase).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ProgramError {
    /// A tile names an MVU the array lacks.
    NoSuchMvu { mvu: u8, mvus: usize },
    /// n exceeds the rows of p and Kp.
    DimensionTooLarge { n: usize, nodes: usize },
    /// An MVU's tiles hold more words than its word memory.
    TooManyWords {
        mvu: usize,
        words: usize,
        capacity: usize,
    },
    /// An MVU has more tiles than its tile table.
    TooManyTiles {
        mvu: usize,
        tiles: usize,
        capacity: usize,
    },
    /// No tile writes this row, so its Kp would keep whatever was in the owner's memory (the
    /// software kernel zeroes it).
    RowUncovered { row: usize },
    /// The scratch space has fewer than n rows, or the words fewer than the tiles say.
    Inconsistent,
}

/// Where a program goes: the firmware writes it into the MVU array's memories, a test keeps it.
pub trait ProgramSink {
    /// Entry `index` of MVU `mvu`'s word memory: an instruction word and its [`flags`].
    fn word(&mut self, mvu: usize, index: usize, word: u32, flags: u8);
    /// Entry `index` of MVU `mvu`'s tile table.
    fn tile(&mut self, mvu: usize, index: usize, entry: TileEntry);
    /// MVU `mvu` runs `words` words per phase (0: it sits the phase out).
    fn length(&mut self, mvu: usize, words: usize);
    /// Row `row`'s Kp lives in MVU `owner`'s Kp memory.
    fn owner(&mut self, row: usize, owner: u8);
    /// Entry `index` of the shared-rows list: `row`, the MVUs that write it (bit m for MVU m),
    /// and its owner.
    fn shared(&mut self, index: usize, row: usize, contributors: u8, owner: u8);
}

/// What [`build`] wrote.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Program {
    /// Words and tiles per MVU.
    pub words: [usize; MAX_HARTS],
    pub tiles: [usize; MAX_HARTS],
    /// Entries of the shared-rows list.
    pub shared_rows: usize,
}

/// The contributor mask of a row (bit m: MVU m writes it), kept in `scratch[row][0]`.
const MASK: usize = 0;
/// Per MVU in turn: the index of its last write-back to the row (−1: none), `scratch[row][1]`.
const LAST: usize = 1;
/// Per MVU in turn: whether it has written the row back yet, `scratch[row][2]`.
const SEEN: usize = 2;

/// Lays validated `tiles` (their `words` back to back) of dimension `n` out for the MVU array
/// `capacity`, into `sink`. Everything is checked before anything is written, so a refused
/// matrix writes nothing. `scratch` needs n rows.
pub fn build(
    tiles: &[TileHeader],
    words: &[u32],
    n: usize,
    capacity: &Capacity,
    scratch: &mut [Sums],
    sink: &mut impl ProgramSink,
) -> Result<Program, ProgramError> {
    if n > capacity.nodes {
        return Err(ProgramError::DimensionTooLarge {
            n,
            nodes: capacity.nodes,
        });
    }
    let rows = scratch.get_mut(..n).ok_or(ProgramError::Inconsistent)?;
    let mut program = Program::default();
    for t in tiles {
        let m = usize::from(t.mvu);
        if m >= capacity.mvus.min(MAX_HARTS) {
            return Err(ProgramError::NoSuchMvu {
                mvu: t.mvu,
                mvus: capacity.mvus,
            });
        }
        program.words[m] += t.words as usize;
        program.tiles[m] += 1;
    }
    rows.iter_mut().for_each(|r| r[MASK] = 0);
    for_each_row_end(tiles, words, n, None, |t, own, mirror| {
        rows[own][MASK] |= 1 << t.mvu;
        if let Some(m) = mirror {
            rows[m][MASK] |= 1 << t.mvu;
        }
    })?;
    for m in 0..capacity.mvus.min(MAX_HARTS) {
        if program.words[m] > capacity.words {
            return Err(ProgramError::TooManyWords {
                mvu: m,
                words: program.words[m],
                capacity: capacity.words,
            });
        }
        if program.tiles[m] > capacity.tiles {
            return Err(ProgramError::TooManyTiles {
                mvu: m,
                tiles: program.tiles[m],
                capacity: capacity.tiles,
            });
        }
    }
    if let Some(row) = rows.iter().position(|r| r[MASK] == 0) {
        return Err(ProgramError::RowUncovered { row });
    }
    for (row, r) in rows.iter().enumerate() {
        let mask = r[MASK] as u8;
        let owner = mask.trailing_zeros() as u8;
        sink.owner(row, owner);
        if mask.count_ones() > 1 {
            sink.shared(program.shared_rows, row, mask, owner);
            program.shared_rows += 1;
        }
    }
    for m in 0..capacity.mvus.min(MAX_HARTS) {
        emit_mvu(tiles, words, n, m, rows, sink)?;
        sink.length(m, program.words[m]);
    }
    Ok(program)
}

/// MVU m's tiles and words with their flags.
fn emit_mvu(
    tiles: &[TileHeader],
    words: &[u32],
    n: usize,
    m: usize,
    rows: &mut [Sums],
    sink: &mut impl ProgramSink,
) -> Result<(), ProgramError> {
    rows.iter_mut().for_each(|r| (r[LAST], r[SEEN]) = (-1, 0));
    let mut k = 0i64;
    for_each_row_end(tiles, words, n, Some(m), |_, own, mirror| {
        for row in core::iter::once(own).chain(mirror) {
            rows[row][LAST] = k;
            k += 1;
        }
    })?;
    // Each write-back's flags: first if the row was not seen yet, last if it is this MVU's
    // final one to a row that no other MVU writes.
    let mut k = 0i64;
    let mut write_back = |row: usize, first: u8, last: u8| -> u8 {
        let r = &mut rows[row];
        let mut f = 0;
        if r[SEEN] == 0 {
            f |= first;
            r[SEEN] = 1;
        }
        if r[LAST] == k && (r[MASK] as u8).count_ones() == 1 {
            f |= last;
        }
        k += 1;
        f
    };
    let (mut index, mut tile_index, mut start) = (0usize, 0usize, 0usize);
    for t in tiles {
        let end = start + t.words as usize;
        let tile_words = words.get(start..end).ok_or(ProgramError::Inconsistent)?;
        start = end;
        if usize::from(t.mvu) != m {
            continue;
        }
        let entry = TileEntry {
            row_base: t.row_base,
            col_base: t.col_base,
            mirror_col_base: n as u32 - 1 - t.col_base,
            mirrored: t.mirrored,
        };
        sink.tile(m, tile_index, entry);
        tile_index += 1;
        let mut own = t.row_base as usize;
        for &w in tile_words {
            let mut f = 0;
            if w >= ER_BIT {
                f |= write_back(own, flags::FIRST_OWN, flags::LAST_OWN);
                if t.mirrored {
                    f |= write_back(n - 1 - own, flags::FIRST_MIRROR, flags::LAST_MIRROR);
                }
                own += 1;
            }
            sink.word(m, index, w, f);
            index += 1;
        }
    }
    Ok(())
}

/// Calls `f(tile, own row, mirror row)` for every ER word of the tiles (of MVU `only`, if
/// given), in order.
fn for_each_row_end(
    tiles: &[TileHeader],
    words: &[u32],
    n: usize,
    only: Option<usize>,
    mut f: impl FnMut(&TileHeader, usize, Option<usize>),
) -> Result<(), ProgramError> {
    let mut start = 0usize;
    for t in tiles {
        let end = start + t.words as usize;
        let tile_words = words.get(start..end).ok_or(ProgramError::Inconsistent)?;
        start = end;
        if only.is_some_and(|m| m != usize::from(t.mvu)) {
            continue;
        }
        let mut own = t.row_base as usize;
        for &w in tile_words {
            if w >= ER_BIT {
                if own >= n {
                    return Err(ProgramError::Inconsistent);
                }
                f(t, own, t.mirrored.then(|| n - 1 - own));
                own += 1;
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests;
