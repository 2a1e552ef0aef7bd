//! Fixed-width encoding of chunk payloads (instruction words, mantissas, raw values).
//!
//! postcard writes a `u32`/`i32` as a varint: 1–5 bytes, and an instruction word — whose EM/ER
//! flags and column sit in the top bits — usually takes 5. A chunk of words is therefore written
//! here as postcard writes any sequence, a varint element count, but with every element as its
//! 4 little-endian bytes (postcard writes `[u8; 4]` as four raw bytes). That keeps the wire at
//! 4 bytes per nonzero plus the frame's fixed overhead, which is what the issue's ≤ 4.2
//! bytes-per-nonzero goal needs. serde's `with` attribute applies it to a field, so the message
//! types keep their plain `heapless::Vec<u32 | i32, N>` fields.

use core::fmt;
use core::marker::PhantomData;

use heapless::Vec;
use serde::de::{SeqAccess, Visitor};
use serde::ser::SerializeSeq;
use serde::{Deserializer, Serializer};

/// A 4-byte element of a chunk.
pub trait Element: Copy {
    fn to_le(self) -> [u8; 4];
    fn from_le(bytes: [u8; 4]) -> Self;
}

impl Element for u32 {
    fn to_le(self) -> [u8; 4] {
        self.to_le_bytes()
    }
    fn from_le(bytes: [u8; 4]) -> Self {
        u32::from_le_bytes(bytes)
    }
}

impl Element for i32 {
    fn to_le(self) -> [u8; 4] {
        self.to_le_bytes()
    }
    fn from_le(bytes: [u8; 4]) -> Self {
        i32::from_le_bytes(bytes)
    }
}

pub fn serialize<S: Serializer, T: Element, const N: usize>(
    chunk: &Vec<T, N>,
    serializer: S,
) -> Result<S::Ok, S::Error> {
    let mut seq = serializer.serialize_seq(Some(chunk.len()))?;
    for &element in chunk {
        seq.serialize_element(&element.to_le())?;
    }
    seq.end()
}

pub fn deserialize<'de, D: Deserializer<'de>, T: Element, const N: usize>(
    deserializer: D,
) -> Result<Vec<T, N>, D::Error> {
    deserializer.deserialize_seq(ChunkVisitor::<T, N>(PhantomData))
}

struct ChunkVisitor<T, const N: usize>(PhantomData<T>);

impl<'de, T: Element, const N: usize> Visitor<'de> for ChunkVisitor<T, N> {
    type Value = Vec<T, N>;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "at most {N} four-byte elements")
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Self::Value, A::Error> {
        let mut chunk = Vec::new();
        while let Some(bytes) = seq.next_element::<[u8; 4]>()? {
            chunk
                .push(T::from_le(bytes))
                .map_err(|_| serde::de::Error::invalid_length(N + 1, &self))?;
        }
        Ok(chunk)
    }
}

#[cfg(test)]
mod tests {
    use serde::{Deserialize, Serialize};

    use super::*;

    #[derive(Debug, PartialEq, Serialize, Deserialize)]
    struct Words(#[serde(with = "crate::chunk")] Vec<u32, 4>);

    #[derive(Debug, PartialEq, Serialize, Deserialize)]
    struct Signed(#[serde(with = "crate::chunk")] Vec<i32, 4>);

    fn to_vec<T: Serialize>(value: &T) -> std::vec::Vec<u8> {
        let mut buf = [0u8; 64];
        postcard::to_slice(value, &mut buf).unwrap().to_vec()
    }

    #[test]
    fn elements_take_four_bytes_after_a_count() {
        let words = Words(Vec::from_slice(&[0xC000_0001, 7]).unwrap());
        let bytes = to_vec(&words);
        assert_eq!(bytes, [2, 1, 0, 0, 0xC0, 7, 0, 0, 0]);
        assert_eq!(postcard::from_bytes::<Words>(&bytes).unwrap(), words);
        let signed = Signed(Vec::from_slice(&[-1, i32::MIN, 5]).unwrap());
        let bytes = to_vec(&signed);
        assert_eq!(bytes.len(), 1 + 12);
        assert_eq!(postcard::from_bytes::<Signed>(&bytes).unwrap(), signed);
    }

    #[test]
    fn too_many_or_truncated_elements_are_refused() {
        let mut five = vec![5u8];
        five.extend([1u8; 20]);
        assert!(postcard::from_bytes::<Words>(&five).is_err());
        assert!(postcard::from_bytes::<Words>(&[2, 1, 2, 3, 4, 5]).is_err());
        assert!(postcard::from_bytes::<Words>(&[0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0x0F]).is_err());
    }
}
