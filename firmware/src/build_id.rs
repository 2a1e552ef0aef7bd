//! The firmware's GNU build id, reported in `Hello` so that the host can tell whether an ELF is
//! the one running.
//!
//! Why the GNU build id: the linker (`--build-id=sha1`, see build.rs) hashes the whole output
//! ELF, and defmt's string table *is* part of that ELF (one symbol per log string, in `.symtab`),
//! so any change to the log strings, their indices or the code changes the id. The host reads
//! the same note from an ELF file with the `object` crate. A hash of only the defmt table would
//! have to be computed after linking and patched into the image, which no standard tool does.
//!
//! `build-id.x` places the note (`.note.gnu.build-id`) in the loaded image between
//! `__build_id_note_start` and `__build_id_note_end`.

use deform_shared::protocol::BUILD_ID_MAX;
use heapless::Vec;

extern "C" {
    static __build_id_note_start: u8;
    static __build_id_note_end: u8;
}

/// The ELF note header: name size, descriptor size, type (3 = NT_GNU_BUILD_ID), then the name
/// `"GNU\0"` padded to 4 bytes, then the descriptor (the id).
const NOTE_HEADER: usize = 16;
const NT_GNU_BUILD_ID: u32 = 3;

/// The build id, or an empty one if the image has no well-formed note.
pub fn build_id() -> Vec<u8, BUILD_ID_MAX> {
    // SAFETY: both symbols come from build-id.x and delimit the note section in the loaded
    // image (start ≤ end); its bytes are never written, so reading them as a slice is sound.
    let note = unsafe {
        let start = core::ptr::addr_of!(__build_id_note_start);
        let end = core::ptr::addr_of!(__build_id_note_end);
        core::slice::from_raw_parts(start, (end as usize).saturating_sub(start as usize))
    };
    parse_note(note).unwrap_or_default()
}

fn parse_note(note: &[u8]) -> Option<Vec<u8, BUILD_ID_MAX>> {
    let word = |at: usize| -> Option<u32> {
        Some(u32::from_le_bytes(note.get(at..at + 4)?.try_into().ok()?))
    };
    let (name_size, desc_size, kind) = (word(0)?, word(4)?, word(8)?);
    if name_size != 4 || kind != NT_GNU_BUILD_ID || note.get(12..16)? != b"GNU\0" {
        return None;
    }
    let desc = note.get(NOTE_HEADER..NOTE_HEADER + desc_size as usize)?;
    Vec::from_slice(desc).ok()
}
