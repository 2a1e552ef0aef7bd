//! The MVU instruction word of thesis ch. 4.2.1.
//!
//! ```text
//!  31   30   29 ........ 21   20 ............................ 0
//! [EM] [ER] [ column, 9 bit ] [ value, 21-bit two's complement ]
//! ```
//!
//! EM marks the last word of a matrix (for us: of a tile, see [`crate::matrix`]), ER the last
//! word of a row. A row with no nonzero in a tile is still written, as one word with value 0 and
//! ER set, so that the MVU's row counter advances exactly once per ER.

/// Bit 31: end of matrix.
pub const EM_BIT: u32 = 1 << 31;
/// Bit 30: end of row.
pub const ER_BIT: u32 = 1 << 30;
/// Width of the column field, bits 29..21.
pub const COLUMN_BITS: u32 = 9;
/// Width of the value field, bits 20..0.
pub const VALUE_BITS: u32 = 21;
/// Number of columns one word can address: a tile's column window.
pub const COLUMN_WINDOW: u32 = 1 << COLUMN_BITS;
/// Largest encodable value (raw, before fractional scaling).
pub const VALUE_MAX: i32 = (1 << (VALUE_BITS - 1)) - 1;
/// Smallest encodable value (raw).
pub const VALUE_MIN: i32 = -(1 << (VALUE_BITS - 1));

/// Where the column field starts: bit 21.
pub const COLUMN_SHIFT: u32 = VALUE_BITS;
const COLUMN_MASK: u32 = (COLUMN_WINDOW - 1) << COLUMN_SHIFT;
/// Bits 20..0, the value field: what a values-only update replaces (protocol version 2).
pub const VALUE_MASK: u32 = (1 << VALUE_BITS) - 1;

/// Why a word could not be encoded. Encoders never truncate silently.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum WordError {
    #[error("column {0} does not fit the 9-bit column field (0..=511)")]
    ColumnOutOfRange(u32),
    #[error("raw value {0} does not fit the 21-bit value field ({VALUE_MIN}..={VALUE_MAX})")]
    ValueOutOfRange(i64),
}

/// One 32-bit MVU instruction.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[repr(transparent)]
pub struct Word(pub u32);

impl Word {
    /// Encodes a word, checking both fields.
    pub fn new(
        column: u32,
        raw_value: i64,
        end_of_row: bool,
        end_of_matrix: bool,
    ) -> Result<Self, WordError> {
        if column >= COLUMN_WINDOW {
            return Err(WordError::ColumnOutOfRange(column));
        }
        if raw_value < VALUE_MIN as i64 || raw_value > VALUE_MAX as i64 {
            return Err(WordError::ValueOutOfRange(raw_value));
        }
        let mut bits = (column << COLUMN_SHIFT) | (raw_value as u32 & VALUE_MASK);
        if end_of_row {
            bits |= ER_BIT;
        }
        if end_of_matrix {
            bits |= EM_BIT;
        }
        Ok(Word(bits))
    }

    /// The word that stands for an empty row: value 0, column 0, ER set.
    pub const fn empty_row(end_of_matrix: bool) -> Self {
        Word(ER_BIT | if end_of_matrix { EM_BIT } else { 0 })
    }

    pub const fn bits(self) -> u32 {
        self.0
    }
    pub const fn end_of_matrix(self) -> bool {
        self.0 & EM_BIT != 0
    }
    pub const fn end_of_row(self) -> bool {
        self.0 & ER_BIT != 0
    }
    pub const fn column(self) -> u32 {
        (self.0 & COLUMN_MASK) >> COLUMN_SHIFT
    }
    /// The raw value, sign-extended from 21 bits.
    pub const fn raw_value(self) -> i32 {
        ((self.0 << (32 - VALUE_BITS)) as i32) >> (32 - VALUE_BITS)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn round_trips(col in 0u32..512, v in VALUE_MIN..=VALUE_MAX, er: bool, em: bool) {
            let w = Word::new(col, v as i64, er, em).unwrap();
            prop_assert_eq!(w.column(), col);
            prop_assert_eq!(w.raw_value(), v);
            prop_assert_eq!(w.end_of_row(), er);
            prop_assert_eq!(w.end_of_matrix(), em);
            prop_assert_eq!(Word(w.bits()), w);
        }

        #[test]
        fn any_bits_decode_and_reencode(bits: u32) {
            let w = Word(bits);
            let again = Word::new(w.column(), w.raw_value() as i64, w.end_of_row(), w.end_of_matrix()).unwrap();
            prop_assert_eq!(again, w);
        }

        #[test]
        fn rejects_wide_columns(col in 512u32..) {
            prop_assert_eq!(Word::new(col, 0, false, false), Err(WordError::ColumnOutOfRange(col)));
        }

        #[test]
        fn rejects_wide_values(v in prop_oneof![i64::MIN..(VALUE_MIN as i64), (VALUE_MAX as i64 + 1)..]) {
            prop_assert_eq!(Word::new(0, v, false, false), Err(WordError::ValueOutOfRange(v)));
        }
    }

    #[test]
    fn field_positions_match_the_thesis() {
        let w = Word::new(0x1FF, -1, true, true).unwrap();
        assert_eq!(w.bits(), 0xFFFF_FFFF);
        let w = Word::new(1, 1, false, false).unwrap();
        assert_eq!(w.bits(), (1 << 21) | 1);
        assert_eq!(
            Word::new(0, VALUE_MIN as i64, false, false).unwrap().bits(),
            1 << 20
        );
    }

    #[test]
    fn empty_row_is_a_zero_valued_end_of_row() {
        let w = Word::empty_row(false);
        assert!(w.end_of_row() && !w.end_of_matrix());
        assert_eq!((w.column(), w.raw_value()), (0, 0));
        assert!(Word::empty_row(true).end_of_matrix());
    }
}
