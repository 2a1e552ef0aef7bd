//! Writes the fuzz targets' seed corpus (well-formed sessions) to `fuzz/corpus/<target>/`:
//!
//! ```text
//! cargo run -p deform-target-core --features testkit --example fuzz_seeds
//! ```

use std::path::PathBuf;

fn main() -> std::io::Result<()> {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../fuzz/corpus");
    for (target, name, input) in deform_target_core::testkit::fuzz::seeds() {
        let dir = root.join(target);
        std::fs::create_dir_all(&dir)?;
        std::fs::write(dir.join(format!("seed-{name}")), input)?;
        println!("{target}/seed-{name}");
    }
    Ok(())
}
