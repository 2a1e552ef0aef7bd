//! Puts the linker scripts where the linker finds them and gives each binary its own:
//!
//! - `deform-firmware` (the application): `memory.x`, riscv-rt's `link.x`, `build-id.x` (the GNU
//!   build id note in the image, see src/build_id.rs) and defmt's `defmt.x` (its string table).
//! - `deform-loader` (the serial loader, src/bin/loader.rs): `loader-memory.x` and `link.x`.
//!
//! riscv-rt 0.18's `link.x` does not include the memory layout itself: it must come first.

use std::{env, fs, path::PathBuf};

const SCRIPTS: &[(&str, &[u8])] = &[
    ("memory.x", include_bytes!("memory.x")),
    ("loader-memory.x", include_bytes!("loader-memory.x")),
    ("build-id.x", include_bytes!("build-id.x")),
];

fn main() {
    let out = PathBuf::from(env::var_os("OUT_DIR").expect("cargo sets OUT_DIR"));
    for (name, text) in SCRIPTS {
        fs::write(out.join(name), text).expect("write a linker script");
        println!("cargo:rerun-if-changed={name}");
    }
    println!("cargo:rustc-link-search={}", out.display());
    for arg in [
        "-Tmemory.x",
        "-Tlink.x",
        "-Tbuild-id.x",
        "-Tdefmt.x",
        "--build-id=sha1",
    ] {
        println!("cargo:rustc-link-arg-bin=deform-firmware={arg}");
    }
    for arg in ["-Tloader-memory.x", "-Tlink.x"] {
        println!("cargo:rustc-link-arg-bin=deform-loader={arg}");
    }
    println!("cargo:rerun-if-changed=build.rs");
}
