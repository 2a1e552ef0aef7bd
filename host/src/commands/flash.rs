//! `deform flash`: upload a firmware ELF through the serial loader, have the loader verify the
//! whole image, start it, and confirm that the started firmware is the one sent.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use clap::{Args, ValueEnum};

use crate::board::LogFlags;
use crate::board::{self, BiosChoice, Board, LoaderChoice};
use crate::flash::boards;
use crate::flash::sfl::{detect_bios, SflTimeouts};
use crate::flash::{hex, FlashImage, LoaderTimeouts, IMAGE_ATTEMPTS};
use crate::link::{open_serial, Timeouts};

/// Where the loader runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum FlashTarget {
    /// Boot QEMU (riscv32 `virt`) with the serial loader and flash it. QEMU stops when the
    /// command ends: this checks an image end to end; `deform solve --via-loader` flashes and
    /// then solves in one run.
    Qemu,
    /// Start the simulated LiteX SoC with its ROM and the stock LiteX BIOS and boot the
    /// firmware (built with `cargo xtask firmware --board litex`) through the BIOS's serial
    /// boot (SFL).
    Litex,
}

/// How to talk to what waits on the port.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum FlashProtocol {
    /// Poke the line with a newline: a LiteX BIOS answers with its prompt (or its serial-boot
    /// request), our loader stays silent.
    Auto,
    /// deform's own serial loader (QEMU, or a board booted into it): CRC-32-verified image.
    Deform,
    /// The stock LiteX BIOS's serial boot (SFL, as `litex_term --kernel`): CRC-16 per frame.
    Litex,
}

/// Upload a firmware ELF to a target's RAM through its serial loader and start it.
#[derive(Debug, Clone, Args)]
pub struct FlashArgs {
    /// The firmware ELF (riscv32). Its loadable segments become one image, zero-filled between
    /// segments; .bss is not sent (the firmware zeroes it).
    #[arg(value_name = "FIRMWARE.elf")]
    pub firmware: PathBuf,

    /// Serial device of a board whose loader waits for an image (e.g. /dev/ttyUSB0).
    #[arg(long, value_name = "PATH", conflicts_with = "target")]
    pub port: Option<String>,

    /// Where the loader runs when there is no --port. [default: qemu]
    #[arg(long, value_enum)]
    pub target: Option<FlashTarget>,

    /// The loader's protocol on --port: `deform` (ours), `litex` (the stock LiteX BIOS), or
    /// `auto` to find out.
    #[arg(long, value_enum, default_value_t = FlashProtocol::Auto)]
    pub protocol: FlashProtocol,

    /// Seconds one loader request waits for its answer before it is sent again.
    #[arg(long, value_name = "SECONDS", default_value_t = 2.0, value_parser = parse_seconds)]
    pub request_timeout: f64,

    /// Resends of one request (after a timeout or a corrupted frame) before flashing fails.
    #[arg(long, value_name = "N", default_value_t = 8)]
    pub retries: u32,

    #[command(flatten)]
    pub logs: LogFlags,
}

fn parse_seconds(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(t) if t.is_finite() && t > 0.0 && t <= 3600.0 => Ok(t),
        Ok(_) => Err("must be a number of seconds in (0, 3600]".into()),
        Err(e) => Err(format!("not a number: {e}")),
    }
}

pub fn run(args: &FlashArgs) -> anyhow::Result<()> {
    let image = FlashImage::from_file(&args.firmware)
        .with_context(|| format!("reading {}", args.firmware.display()))?;
    println!(
        "image       {} bytes at {:#010x}, entry {:#010x}, CRC-32 {:#010x}, build id {}",
        image.bytes.len(),
        image.load_address,
        image.entry,
        image.crc32(),
        image.build_id.as_deref().map_or("none".into(), hex)
    );
    let bios = match (&args.port, args.target, args.protocol) {
        (None, Some(FlashTarget::Litex), _) => Some(BiosChoice::Simulated),
        (Some(port), _, FlashProtocol::Litex) => Some(BiosChoice::Port(port.clone())),
        (Some(port), _, FlashProtocol::Auto) => {
            let mut line = open_serial(port)?;
            detect_bios(&mut line, Duration::from_secs(2))
                .with_context(|| format!("probing {port} for a LiteX BIOS"))?
                .then(|| BiosChoice::Port(port.clone()))
        }
        _ => None,
    };
    check_board(&image, bios.as_ref(), args.port.is_some())?;
    if let Some(bios) = bios {
        return flash_litex_bios(args, &bios, &image);
    }
    let choice = match &args.port {
        Some(port) => LoaderChoice::Port(port.clone()),
        None => LoaderChoice::Qemu {
            harts: board::DEFAULT_QEMU_HARTS,
        },
    };
    let loader_timeouts = LoaderTimeouts {
        request: Duration::from_secs_f64(args.request_timeout),
        retries: args.retries,
        ..LoaderTimeouts::default()
    };
    let bar = crate::progress::byte_bar(image.bytes.len() as u64, "flash");
    let mut last_attempt = 1;
    let (board, report) = Board::flash(
        &choice,
        &args.firmware,
        Timeouts::default(),
        loader_timeouts,
        &args.logs.options(),
        |p| {
            if p.attempt != last_attempt {
                last_attempt = p.attempt;
                eprintln!(
                    "the image failed its verification; uploading it again \
                     (attempt {} of {IMAGE_ATTEMPTS})",
                    p.attempt
                );
                bar.reset();
            }
            bar.set_position(p.bytes_sent as u64);
            if p.bytes_sent == p.bytes_total {
                // Gone before the started firmware's first log lines print.
                bar.finish_and_clear();
            }
        },
    )?;
    println!("target      {}", board.describe());
    println!(
        "flashed     {} bytes in {} chunks, {:.0} ms ({:.1} KiB/s; {} bytes on the wire), \
         {} upload(s), {} resent frame(s); CRC verified in target RAM",
        report.image_bytes,
        report.chunks,
        report.upload_time.as_secs_f64() * 1e3,
        report.throughput() / 1024.0,
        report.wire_bytes,
        report.attempts,
        report.resends
    );
    print_running(&board);
    Ok(())
}

/// Checks, before anything is started or sent, that the image lies in the RAM of the board it
/// goes to: the simulated LiteX SoC's or QEMU's; on a port, only that a LiteX BIOS is not sent
/// a QEMU build (the board's RAM is its own; deform's loader checks the range itself).
fn check_board(image: &FlashImage, bios: Option<&BiosChoice>, on_port: bool) -> anyhow::Result<()> {
    let board = match (bios, on_port) {
        (Some(BiosChoice::Simulated), _) => boards::litex_soc(),
        (Some(BiosChoice::Port(_)), _) if boards::built_for(image) == Some(boards::QEMU_VIRT) => {
            boards::litex_soc()
        }
        (None, false) => boards::QEMU_VIRT,
        _ => return Ok(()),
    };
    Ok(boards::check(image, &board)?)
}

/// Boots the image through a stock LiteX BIOS (SFL) and reports as [`run`] does.
fn flash_litex_bios(args: &FlashArgs, bios: &BiosChoice, image: &FlashImage) -> anyhow::Result<()> {
    let sfl_timeouts = SflTimeouts {
        answer: Duration::from_secs_f64(args.request_timeout),
        retries: args.retries,
        ..SflTimeouts::default()
    };
    if matches!(bios, BiosChoice::Simulated) {
        // The simulated SoC takes tens of seconds to start and boot its BIOS before the bar moves.
        eprintln!("starting the simulated LiteX SoC and its BIOS…");
    }
    let bar = crate::progress::byte_bar(image.bytes.len() as u64, "flash");
    let started = std::time::Instant::now();
    let (board, report) = Board::flash_litex_bios(
        bios,
        &args.firmware,
        Timeouts::default(),
        sfl_timeouts,
        &args.logs.options(),
        |sent| bar.set_position(sent as u64),
    )?;
    bar.finish_and_clear();
    println!("target      {}", board.describe());
    println!(
        "flashed     {} bytes in {} SFL frames through the LiteX BIOS, {:.1} s with the boot \
         and handshake ({} bytes on the wire), {} resent frame(s); CRC-16 checked per frame",
        image.bytes.len(),
        report.frames,
        started.elapsed().as_secs_f64(),
        report.wire_bytes,
        report.resends
    );
    print_running(&board);
    Ok(())
}

fn print_running(board: &Board) {
    let info = board.target.info();
    println!(
        "running     deform firmware {} (protocol {}, {} hart(s), build id {})",
        info.firmware_version,
        info.protocol_version,
        info.harts,
        hex(&info.build_id)
    );
    let logs = board::lock(board.logs()).stats();
    if logs.bytes > 0 {
        println!(
            "logs        {} bytes, {} lines decoded",
            logs.bytes, logs.frames
        );
    }
}
