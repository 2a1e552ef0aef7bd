//! Which board an image was built for, by where it loads: the firmware is linked for one board's
//! RAM (`cargo xtask firmware`: QEMU's riscv32 `virt` at 0x8000_0000; `--board litex`: the LiteX
//! SoC's main RAM at 0x4000_0000). Flashing a build for the other board failed only after
//! seconds of CRC errors (the LiteX BIOS writes what lies outside its RAM nowhere); the image's
//! range is checked against the board's RAM before anything is started or sent.

use super::FlashImage;

/// Where one board's firmware may lie, and how to build for it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BoardRam {
    pub name: &'static str,
    /// `start..end`, the RAM an image may occupy.
    pub start: u64,
    pub end: u64,
    /// The command that builds the firmware for this board.
    pub build: &'static str,
}

/// QEMU's riscv32 `virt` board as the firmware is linked for it
/// (firmware/boards/qemu-virt/memory.x: 16 MiB at 0x8000_0000).
pub const QEMU_VIRT: BoardRam = BoardRam {
    name: "QEMU's riscv32 virt board",
    start: 0x8000_0000,
    end: 0x8100_0000,
    build: "cargo xtask firmware",
};

/// The committed LiteX SoC's map, which the LiteX firmware is built against.
const LITEX_CSR_JSON: &str = include_str!("../../../firmware/boards/litex-vexriscv/csr.json");

/// The LiteX VexRiscv SoC's main RAM, from the committed csr.json (`memories.main_ram`).
pub fn litex_soc() -> BoardRam {
    let json: serde_json::Value = serde_json::from_str(LITEX_CSR_JSON).unwrap_or_default();
    let ram = &json["memories"]["main_ram"];
    // The committed file is checked by hil-sim against every generated SoC; these are its values.
    let start = ram["base"].as_u64().unwrap_or(0x4000_0000);
    let size = ram["size"].as_u64().unwrap_or(0x20_0000);
    BoardRam {
        name: "the LiteX VexRiscv SoC",
        start,
        end: start + size,
        build: "cargo xtask firmware --board litex",
    }
}

/// The board whose RAM the image lies in, if it is one of ours.
pub fn built_for(image: &FlashImage) -> Option<BoardRam> {
    [QEMU_VIRT, litex_soc()]
        .into_iter()
        .find(|board| fits(image, board))
}

fn fits(image: &FlashImage, board: &BoardRam) -> bool {
    let start = u64::from(image.load_address);
    start >= board.start && start + image.bytes.len() as u64 <= board.end
}

/// An image that does not lie in the board's RAM.
#[derive(Debug, thiserror::Error)]
#[error(
    "the image occupies {start:#010x}..{end:#010x}, outside {}'s RAM ({:#010x}..{:#010x}): \
     {built_for}; build it for {} with `{}`",
    board.name, board.start, board.end, board.name, board.build
)]
pub struct WrongBoard {
    pub start: u64,
    pub end: u64,
    pub board: BoardRam,
    /// Which board it was built for, as a phrase.
    pub built_for: String,
}

/// Checks that `image` lies in `board`'s RAM, naming the board it was built for if not.
pub fn check(image: &FlashImage, board: &BoardRam) -> Result<(), WrongBoard> {
    if fits(image, board) {
        return Ok(());
    }
    let start = u64::from(image.load_address);
    Err(WrongBoard {
        start,
        end: start + image.bytes.len() as u64,
        board: *board,
        built_for: match built_for(image) {
            Some(other) => format!("it was built for {}", other.name),
            None => "it was built for neither of deform's boards".into(),
        },
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image(load_address: u32, len: usize) -> FlashImage {
        FlashImage {
            load_address,
            entry: load_address,
            bytes: vec![0; len],
            build_id: None,
        }
    }

    #[test]
    fn an_image_is_checked_against_the_boards_ram_and_its_own_board_named() {
        let litex = litex_soc();
        assert_eq!((litex.start, litex.end), (0x4000_0000, 0x4020_0000));
        let qemu_build = image(0x8000_0000, 150_000);
        assert_eq!(built_for(&qemu_build), Some(QEMU_VIRT));
        check(&qemu_build, &QEMU_VIRT).unwrap();
        let e = check(&qemu_build, &litex).unwrap_err().to_string();
        assert!(
            e.contains("0x80000000..0x800249f0")
                && e.contains("outside the LiteX VexRiscv SoC's RAM (0x40000000..0x40200000)")
                && e.contains("built for QEMU's riscv32 virt board")
                && e.contains("`cargo xtask firmware --board litex`"),
            "{e}"
        );
        let litex_build = image(0x4000_0000, 150_000);
        check(&litex_build, &litex).unwrap();
        let e = check(&litex_build, &QEMU_VIRT).unwrap_err().to_string();
        assert!(e.contains("built for the LiteX VexRiscv SoC"), "{e}");
        // Too large for the SoC's 2 MiB, and somewhere else entirely.
        let e = check(&image(0x4000_0000, 3 << 20), &litex)
            .unwrap_err()
            .to_string();
        assert!(e.contains("neither of deform's boards"), "{e}");
        assert!(built_for(&image(0x1000, 16)).is_none());
    }
}
