//! The live loop's compact field frames (protocol version 10): which nodes a field frame
//! carries ([`FieldSelection`]) and how their quantised components travel ([`FieldChunk`]).
//!
//! Each component is an `i16` q, the displacement being q·2^exponent with one exponent per
//! frame. On the wire a chunk does not send q itself but its difference from the same component
//! of the previous node in the chunk (the first node against 0), wrapped to `i16`; postcard
//! writes every `i16` as a zigzag varint. A smooth field changes little from one transmitted
//! node to the next, so most differences take one or two bytes instead of two, and the wrapping
//! keeps the transform exact: decoding adds the differences back (wrapping) and gets q bit for
//! bit. The worst case (alternating ±32767) costs three bytes per component, and
//! [`FIELD_NODES`] is small enough that even that chunk fits a frame.

use core::fmt;

use heapless::Vec;
use serde::de::{SeqAccess, Visitor};
use serde::ser::SerializeSeq;
use serde::{Deserialize, Deserializer, Serialize, Serializer};

use crate::live::LiveError;

/// Nodes per [`FieldChunk`]: fixed, so the host knows every chunk's offset in advance and
/// pipelines the requests. 56 nodes of three components at the worst case of three varint
/// bytes each is 504 bytes, which with the frame's header stays below `MAX_FRAME_LEN` (tested
/// with room to spare); a smooth field's chunk takes about 40 % of that (≈ 1.2 bytes per
/// component).
pub const FIELD_NODES: usize = 56;

/// Components per [`FieldChunk`].
pub const FIELD_COMPONENTS: usize = 3 * FIELD_NODES;

/// A chunk of the last frame's displacement field: the selection's nodes `offset`,
/// `offset + stride`, … (at most [`FIELD_NODES`], see [`FieldSelection::chunk`]), three
/// components each, the displacement being q·2^`exponent`. The exponent is the same for every
/// chunk of a frame.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct FieldChunk {
    /// Position in the selection of the first node carried (not a node index, unless the
    /// selection is every node).
    pub offset: u32,
    pub exponent: i8,
    /// Hart 0's cycles for building this chunk; the first chunk after a frame also finds the
    /// frame's exponent (a pass over all 3n components).
    pub cycles: u32,
    /// (Version 11.) `cycles` minus hart 0's retired instructions for building this chunk (see
    /// [`crate::live::FrameReport::stall_cycles`]).
    pub stall_cycles: u32,
    /// q per component, node by node: x, y, z of the first node, then the next.
    #[serde(with = "self::delta")]
    pub values: Vec<i16, FIELD_COMPONENTS>,
}

impl FieldChunk {
    /// The displacements it carries, node by node.
    pub fn displacements(&self) -> impl Iterator<Item = [f64; 3]> + '_ {
        let scale = crate::qformat::pow2(i32::from(self.exponent));
        self.values
            .chunks_exact(3)
            .map(move |c| [0, 1, 2].map(|d| f64::from(c[d]) * scale))
    }
}

/// The wire form of [`FieldChunk::values`]: a postcard sequence of `i16` differences.
mod delta {
    use super::*;

    /// The difference of component `i` from the same component of the previous node.
    fn difference(values: &[i16], i: usize) -> i16 {
        let previous = i.checked_sub(3).map_or(0, |p| values[p]);
        values[i].wrapping_sub(previous)
    }

    pub fn serialize<S: Serializer>(
        values: &Vec<i16, FIELD_COMPONENTS>,
        serializer: S,
    ) -> Result<S::Ok, S::Error> {
        let mut seq = serializer.serialize_seq(Some(values.len()))?;
        for i in 0..values.len() {
            seq.serialize_element(&difference(values, i))?;
        }
        seq.end()
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(
        deserializer: D,
    ) -> Result<Vec<i16, FIELD_COMPONENTS>, D::Error> {
        deserializer.deserialize_seq(DeltaVisitor)
    }

    struct DeltaVisitor;

    impl<'de> Visitor<'de> for DeltaVisitor {
        type Value = Vec<i16, FIELD_COMPONENTS>;

        fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
            write!(
                f,
                "whole nodes of i16 differences, at most {FIELD_COMPONENTS}"
            )
        }

        fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Self::Value, A::Error> {
            let mut values: Self::Value = Vec::new();
            while let Some(d) = seq.next_element::<i16>()? {
                let i = values.len();
                let previous = i.checked_sub(3).map_or(0, |p| values[p]);
                values
                    .push(previous.wrapping_add(d))
                    .map_err(|_| serde::de::Error::invalid_length(i + 1, &self))?;
            }
            if values.len() % 3 != 0 {
                return Err(serde::de::Error::invalid_length(values.len(), &self));
            }
            Ok(values)
        }
    }
}

/// Which nodes a field frame carries: every `stride`-th node of the sequence S, S being all n
/// nodes or, with a grid, the nodes on the surface of that nx × ny × nz box (node index
/// i + nx·(j + ny·k), as the host numbers them), both in node order.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FieldSelection {
    n: u32,
    stride: u16,
    surface: Option<[u32; 3]>,
}

impl FieldSelection {
    /// Checks a `ReadField`'s selection against the resident matrix's n nodes.
    pub fn new(n: u32, stride: u16, surface: Option<[u16; 3]>) -> Result<Self, LiveError> {
        if stride == 0 {
            return Err(LiveError::BadStride);
        }
        if let Some(grid) = surface {
            let nodes = grid.iter().map(|&d| u64::from(d)).product::<u64>();
            if nodes != u64::from(n) {
                return Err(LiveError::BadGrid { grid, nodes: n });
            }
        }
        Ok(FieldSelection {
            n,
            stride,
            surface: surface.map(|g| g.map(u32::from)),
        })
    }

    /// Nodes in S.
    pub fn len(&self) -> u32 {
        match self.surface {
            None => self.n,
            Some(g) => self.n - g.iter().map(|&d| d.saturating_sub(2)).product::<u32>(),
        }
    }

    /// Whether S is empty (no nodes at all).
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    pub fn stride(&self) -> usize {
        usize::from(self.stride)
    }

    /// Nodes a whole field frame carries: every stride-th of S.
    pub fn transmitted(&self) -> u32 {
        self.len().div_ceil(u32::from(self.stride))
    }

    /// The offsets of a whole field frame's chunks.
    pub fn chunk_offsets(&self) -> impl Iterator<Item = u32> {
        let step = FIELD_NODES * self.stride();
        (0..self.len()).step_by(step)
    }

    /// The node indices chunk `offset` carries: S[offset], S[offset + stride], …
    pub fn chunk(&self, offset: u32) -> impl Iterator<Item = u32> {
        let nodes = SelectedNodes {
            selection: *self,
            cursor: 0,
        };
        nodes
            .skip(offset as usize)
            .step_by(self.stride())
            .take(FIELD_NODES)
    }

    /// The first node of S at index `p` or after it.
    fn next_from(&self, p: u32) -> Option<u32> {
        if p >= self.n {
            return None;
        }
        let Some([nx, ny, nz]) = self.surface else {
            return Some(p);
        };
        let (i, row) = (p % nx, p / nx);
        let (j, k) = (row % ny, row / ny);
        let inner = |c: u32, len: u32| c > 0 && c + 1 < len;
        if inner(i, nx) && inner(j, ny) && inner(k, nz) {
            // Inside the box: the row's next surface node is its last.
            Some(p - i + nx - 1)
        } else {
            Some(p)
        }
    }

    /// For a node `p` of S: where its row of the grid ends (all nodes are one row) and how
    /// many nodes of S lie from `p` to there.
    fn rest_of_row(&self, p: u32) -> (u32, u32) {
        let Some([nx, ny, nz]) = self.surface else {
            return (self.n, self.n - p);
        };
        let (i, row) = (p % nx, p / nx);
        let (j, k) = (row % ny, row / ny);
        let inner = |c: u32, len: u32| c > 0 && c + 1 < len;
        let end = p - i + nx;
        if inner(j, ny) && inner(k, nz) && nx > 2 {
            // An inner row: only its two ends are on the surface.
            (end, if i == 0 { 2 } else { 1 })
        } else {
            (end, end - p)
        }
    }
}

/// S in node order.
struct SelectedNodes {
    selection: FieldSelection,
    cursor: u32,
}

impl Iterator for SelectedNodes {
    type Item = u32;

    fn next(&mut self) -> Option<u32> {
        let p = self.selection.next_from(self.cursor)?;
        self.cursor = p + 1;
        Some(p)
    }

    /// Skips whole rows of the grid at a time: a chunk's start costs the rows before it, not
    /// the nodes (each chunk of a frame skips to its offset).
    fn nth(&mut self, mut skip: usize) -> Option<u32> {
        loop {
            let p = self.selection.next_from(self.cursor)?;
            let (end, in_row) = self.selection.rest_of_row(p);
            if skip < in_row as usize {
                if in_row == end - p {
                    // A run of consecutive nodes (every node, or a boundary row): jump.
                    self.cursor = p + skip as u32;
                } else {
                    // An inner row: its two ends are stepped.
                    self.cursor = p;
                    for _ in 0..skip {
                        self.next()?;
                    }
                }
                return self.next();
            }
            skip -= in_row as usize;
            self.cursor = end;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame;
    use crate::protocol::{Response, MAX_FRAME_LEN};
    use crate::transport::Uplink;

    fn on_the_line(chunk: &FieldChunk) -> (usize, FieldChunk) {
        let reply = Uplink::Reply {
            seq: u16::MAX,
            body: Response::Field(chunk.clone()),
        };
        let mut buf = [0u8; MAX_FRAME_LEN];
        let n = frame::encode(&reply, &mut buf).unwrap();
        let back: Uplink = frame::decode(&mut buf[..n - 1]).unwrap();
        let Uplink::Reply {
            body: Response::Field(back),
            ..
        } = back
        else {
            panic!("{back:?}")
        };
        (n, back)
    }

    fn chunk(values: impl IntoIterator<Item = i16>) -> FieldChunk {
        FieldChunk {
            offset: u32::MAX,
            exponent: i8::MIN,
            cycles: u32::MAX,
            stall_cycles: u32::MAX,
            values: values.into_iter().collect(),
        }
    }

    #[test]
    fn the_worst_case_chunk_fits_a_frame_and_round_trips() {
        let worst =
            chunk((0..FIELD_COMPONENTS).map(
                |i| {
                    if (i / 3) % 2 == 0 {
                        i16::MAX
                    } else {
                        i16::MIN
                    }
                },
            ));
        let (n, back) = on_the_line(&worst);
        assert!(n + 16 <= MAX_FRAME_LEN, "{n}: leave room for new fields");
        assert_eq!(back, worst);
    }

    #[test]
    fn a_smooth_field_takes_under_two_bytes_per_component_with_its_framing() {
        // A ramp of 100 q per node and component: every difference is one or two bytes.
        let smooth = chunk((0..FIELD_COMPONENTS as i16).map(|i| 1000 + 50 * (i / 3) - 7 * (i % 3)));
        let (n, back) = on_the_line(&smooth);
        assert_eq!(back, smooth);
        assert!((n as f64) / (FIELD_COMPONENTS as f64) < 1.2, "{n}");
    }

    #[test]
    fn every_value_decodes_with_its_scale() {
        let c = FieldChunk {
            offset: 0,
            exponent: -4,
            cycles: 0,
            stall_cycles: 0,
            values: [1i16, -2, i16::MAX, i16::MIN, 0, 300].into_iter().collect(),
        };
        let (_, back) = on_the_line(&c);
        let got: std::vec::Vec<[f64; 3]> = back.displacements().collect();
        assert_eq!(
            got,
            [
                [0.0625, -0.125, 32767.0 / 16.0],
                [-2048.0, 0.0, 300.0 / 16.0]
            ]
        );
    }

    #[test]
    fn malformed_values_are_refused() {
        #[derive(Debug, Serialize, Deserialize)]
        struct Values(#[serde(with = "super::delta")] Vec<i16, FIELD_COMPONENTS>);
        let de = |b: &[u8]| postcard::from_bytes::<Values>(b);
        // Two components: not a whole node.
        assert!(de(&[2, 1, 1]).is_err());
        // A varint past i16 (zigzag 65536).
        assert!(de(&[3, 0x80, 0x80, 0x04, 0, 0]).is_err());
        // Truncated.
        assert!(de(&[3, 1, 1]).is_err());
        // More than a chunk holds.
        let mut long = vec![0xAA, 0x01];
        long.extend([0u8; FIELD_COMPONENTS + 3]);
        assert!(de(&long).is_err());
        assert_eq!(
            de(&[3, 3, 1, 0xFF, 0xFF, 0x03]).unwrap().0,
            [-2, -1, i16::MIN]
        );
    }

    #[test]
    fn the_surface_of_a_box_is_its_outer_nodes() {
        let s = FieldSelection::new(4 * 3 * 5, 1, Some([4, 3, 5])).unwrap();
        let want: std::vec::Vec<u32> = (0..60)
            .filter(|&p| {
                let (i, j, k) = (p % 4, (p / 4) % 3, p / 12);
                i == 0 || i == 3 || j == 0 || j == 2 || k == 0 || k == 4
            })
            .collect();
        assert_eq!(s.len() as usize, want.len());
        assert_eq!(s.len(), 60 - 2 * 3);
        assert_eq!(s.chunk(0).collect::<std::vec::Vec<_>>(), want);
        for skip in 0..want.len() + 2 {
            let mut nodes = SelectedNodes {
                selection: s,
                cursor: 0,
            };
            assert_eq!(nodes.nth(skip), want.get(skip).copied(), "{skip}");
            assert_eq!(nodes.next(), want.get(skip + 1).copied(), "{skip}");
        }
        let every_third = FieldSelection::new(60, 3, Some([4, 3, 5])).unwrap();
        let got: std::vec::Vec<u32> = every_third.chunk(2).collect();
        let want3: std::vec::Vec<u32> = want.iter().copied().skip(2).step_by(3).collect();
        assert_eq!(got, want3);
        assert_eq!(every_third.transmitted(), 54u32.div_ceil(3));
        // A flat grid is all surface.
        assert_eq!(
            FieldSelection::new(12, 1, Some([4, 3, 1])).unwrap().len(),
            12
        );
    }

    #[test]
    fn chunks_cover_the_selection_once() {
        for (n, stride, grid) in [(729, 1, None), (729, 4, None), (729, 2, Some([9, 9, 9]))] {
            let s = FieldSelection::new(n, stride, grid).unwrap();
            let all: std::vec::Vec<u32> = s.chunk_offsets().flat_map(|o| s.chunk(o)).collect();
            assert_eq!(all.len() as u32, s.transmitted());
            assert!(all.windows(2).all(|w| w[0] < w[1]));
        }
    }

    #[test]
    fn bad_selections_are_refused() {
        assert_eq!(FieldSelection::new(10, 0, None), Err(LiveError::BadStride));
        assert_eq!(
            FieldSelection::new(729, 1, Some([9, 9, 8])),
            Err(LiveError::BadGrid {
                grid: [9, 9, 8],
                nodes: 729
            })
        );
        assert!(FieldSelection::new(0, 1, Some([0, 9, 9])).is_ok());
        assert!(FieldSelection::new(u32::MAX, 1, Some([u16::MAX; 3])).is_err());
    }
}
