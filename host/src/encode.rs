//! K as MVU instruction words: Q-format selection and tiling (thesis 4.1.2).
//! (Owned by the model work; the type below is the contract the link code relies on.)

use deform_shared::matrix::TileHeader;

/// A matrix ready to stream to the target: tiles in order and their words back to back.
#[derive(Debug, Clone, PartialEq)]
pub struct EncodedMatrix {
    pub n: u32,
    /// Fractional bits of every word's value field: value = raw · 2^-frac_bits.
    pub frac_bits: u8,
    pub tiles: Vec<TileHeader>,
    pub words: Vec<u32>,
}
