//! An application ELF as the loader takes it: one flat image (load address, bytes, entry point,
//! CRC-32), like `objcopy -O binary` but kept in memory.

use std::path::{Path, PathBuf};

use deform_shared::loader::{ImageHeader, CRC32};
use object::elf::{EM_RISCV, PT_LOAD};
use object::read::elf::{ElfFile32, FileHeader, ProgramHeader};
use object::{Endianness, Object};

/// Zero bytes allowed between two segments of one image (alignment padding is a few bytes;
/// more means segments meant for different memories, which a flat image cannot hold sensibly).
pub const MAX_GAP: u32 = 64 * 1024;

#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    #[error("cannot read {}: {source}", path.display())]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("not a 32-bit ELF file: {0}")]
    NotElf32(#[source] object::read::Error),
    #[error("the ELF is for machine {machine}, not RISC-V ({EM_RISCV})")]
    NotRiscV { machine: u16 },
    #[error("the ELF has no loadable segment with contents")]
    NoSegments,
    #[error(
        "segments at {first:#010x} and {second:#010x} are {gap} bytes apart (more than {MAX_GAP}): \
         not one image for the loader"
    )]
    Gap { first: u32, second: u32, gap: u32 },
    #[error("segments at {first:#010x} and {second:#010x} overlap")]
    Overlap { first: u32, second: u32 },
    #[error("the ELF's segment at {address:#010x} runs past the end of the address space")]
    AddressOverflow { address: u32 },
    #[error("the entry point {entry:#010x} is not inside the image {start:#010x}..{end:#010x}")]
    EntryOutside { entry: u32, start: u32, end: u32 },
    #[error("the segment at {address:#010x} says its contents lie outside the file")]
    SegmentOutsideFile { address: u32 },
}

/// A flat image and where it goes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FlashImage {
    pub load_address: u32,
    pub entry: u32,
    pub bytes: Vec<u8>,
    /// The ELF's GNU build id, which the started application reports in its `Hello`.
    pub build_id: Option<Vec<u8>>,
}

impl FlashImage {
    pub fn from_file(path: &Path) -> Result<FlashImage, ImageError> {
        let data = std::fs::read(path).map_err(|source| ImageError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        FlashImage::from_elf(&data)
    }

    /// The contents of the ELF's `PT_LOAD` segments at their *physical* (load) addresses, the
    /// gaps between them zero-filled. `.bss` (memory beyond a segment's file contents) is left
    /// out: the application's start-up code zeroes it.
    pub fn from_elf(data: &[u8]) -> Result<FlashImage, ImageError> {
        let elf = ElfFile32::<Endianness>::parse(data).map_err(ImageError::NotElf32)?;
        let endian = elf.endian();
        let machine = elf.elf_header().e_machine(endian);
        if machine != EM_RISCV {
            return Err(ImageError::NotRiscV { machine });
        }
        let mut segments = Vec::new();
        for header in elf.elf_program_headers() {
            if header.p_type(endian) != PT_LOAD || header.p_filesz(endian) == 0 {
                continue;
            }
            let address = header.p_paddr(endian);
            let contents = header
                .data(endian, data)
                .map_err(|()| ImageError::SegmentOutsideFile { address })?;
            address
                .checked_add(contents.len() as u32)
                .ok_or(ImageError::AddressOverflow { address })?;
            segments.push((address, contents));
        }
        segments.sort_by_key(|&(address, _)| address);
        let &(load_address, _) = segments.first().ok_or(ImageError::NoSegments)?;
        let mut bytes = Vec::new();
        let mut end = load_address;
        for (i, &(address, contents)) in segments.iter().enumerate() {
            if i > 0 {
                let previous = segments[i - 1].0;
                if address < end {
                    return Err(ImageError::Overlap {
                        first: previous,
                        second: address,
                    });
                }
                let gap = address - end;
                if gap > MAX_GAP {
                    return Err(ImageError::Gap {
                        first: previous,
                        second: address,
                        gap,
                    });
                }
                bytes.resize(bytes.len() + gap as usize, 0);
            }
            bytes.extend_from_slice(contents);
            end = address + contents.len() as u32;
        }
        let entry = elf.elf_header().e_entry(endian);
        if !(load_address..end).contains(&entry) {
            return Err(ImageError::EntryOutside {
                entry,
                start: load_address,
                end,
            });
        }
        Ok(FlashImage {
            load_address,
            entry,
            bytes,
            build_id: elf.build_id().ok().flatten().map(<[u8]>::to_vec),
        })
    }

    pub fn crc32(&self) -> u32 {
        CRC32.checksum(&self.bytes)
    }

    pub fn header(&self) -> ImageHeader {
        ImageHeader {
            load_address: self.load_address,
            length: self.bytes.len() as u32,
            entry: self.entry,
            crc32: self.crc32(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn garbage_is_refused_with_a_reason() {
        for bytes in [
            &b"definitely not an ELF file, not at all"[..],
            &[],
            &[0x7F, b'E'],
        ] {
            let err = FlashImage::from_elf(bytes).unwrap_err();
            assert!(matches!(err, ImageError::NotElf32(_)), "{err}");
        }
    }

    /// A minimal little-endian RISC-V ELF32: `segments` as (address, file bytes, memory size),
    /// the entry at the first segment.
    fn elf(segments: &[(u32, &[u8], u32)]) -> Vec<u8> {
        const EHDR: usize = 52;
        const PHDR: usize = 32;
        let mut out = vec![0u8; EHDR];
        out[..7].copy_from_slice(&[0x7F, b'E', b'L', b'F', 1, 1, 1]);
        let header: [(usize, u32, usize); 9] = [
            (16, 2, 2),                     // e_type: EXEC
            (18, u32::from(EM_RISCV), 2),   // e_machine
            (20, 1, 4),                     // e_version
            (24, segments[0].0, 4),         // e_entry
            (28, EHDR as u32, 4),           // e_phoff
            (40, EHDR as u32, 2),           // e_ehsize
            (42, PHDR as u32, 2),           // e_phentsize
            (44, segments.len() as u32, 2), // e_phnum
            (46, 40, 2),                    // e_shentsize
        ];
        for (at, value, size) in header {
            out[at..at + size].copy_from_slice(&value.to_le_bytes()[..size]);
        }
        let mut offset = (EHDR + PHDR * segments.len()) as u32;
        for &(address, bytes, memsz) in segments {
            for value in [
                PT_LOAD,
                offset,
                address,
                address,
                bytes.len() as u32,
                memsz,
                6,
                4,
            ] {
                out.extend_from_slice(&value.to_le_bytes());
            }
            offset += bytes.len() as u32;
        }
        for &(_, bytes, _) in segments {
            out.extend_from_slice(bytes);
        }
        out
    }

    /// `.bss` and the stack (memory size beyond the file's bytes) are not shipped: the start-up
    /// code zeroes `.bss`, and sending its zeros would only lengthen every flash.
    #[test]
    fn memory_past_the_file_contents_is_left_out_of_the_image() {
        let text = [0x13u8, 0, 0, 0, 0x6F, 0, 0, 0];
        let data = [1u8, 2, 3, 4];
        let elf = elf(&[
            (0x4000_0000, &text, text.len() as u32),
            (0x4000_0010, &data, 0x10_0000), // .data followed by 1 MiB of .bss
            (0x4010_0010, &[], 0x1_0000),    // a NOLOAD stack: no file bytes at all
        ]);
        let image = FlashImage::from_elf(&elf).unwrap();
        let mut expected = text.to_vec();
        expected.resize(0x10, 0); // the gap between the segments
        expected.extend_from_slice(&data);
        assert_eq!(image.bytes, expected);
        assert_eq!(image.header().length, 0x14);
        assert_eq!(image.header().crc32, CRC32.checksum(&expected));
    }

    /// Uses the firmware ELF (`cargo xtask firmware`); skipped without it, which only happens
    /// outside `cargo xtask test`.
    #[test]
    fn the_firmware_becomes_one_image_and_damaged_copies_are_refused() {
        let Ok(data) = std::fs::read(deform_hil_sim::firmware_elf()) else {
            eprintln!("no firmware ELF: skipped");
            return;
        };
        let image = FlashImage::from_elf(&data).unwrap();
        assert_eq!(
            (image.load_address, image.entry),
            (0x8000_0000, 0x8000_0000)
        );
        assert!(image.bytes.len() > 1000, "{}", image.bytes.len());
        assert_eq!(image.build_id.as_ref().map(Vec::len), Some(20));
        assert_eq!(image.header().crc32, CRC32.checksum(&image.bytes));

        // e_machine (offset 18) of another architecture.
        let mut x86 = data.clone();
        x86[18..20].copy_from_slice(&62u16.to_le_bytes());
        assert!(matches!(
            FlashImage::from_elf(&x86),
            Err(ImageError::NotRiscV { machine: 62 })
        ));
        // Cut short anywhere: an error, never a panic.
        for len in (0..data.len()).step_by(997) {
            let _ = FlashImage::from_elf(&data[..len]);
        }
    }
}
