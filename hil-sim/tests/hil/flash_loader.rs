//! Flashing through the serial loader on QEMU: QEMU boots the loader (`-kernel deform-loader`),
//! the host uploads the firmware ELF over the pty exactly as `deform flash` does, and the started
//! application must then solve as a directly booted one. Needs the loader and the firmware
//! (`cargo xtask firmware`) and QEMU.

use crate::support;

use std::io::{self, Read, Write};

use std::time::Duration;

use deform_hil_sim::{firmware_elf, loader_elf, Qemu, QemuConfig};
use deform_host::flash::{
    flash_and_connect, FlashError, FlashImage, LoaderLink, LoaderLinkError, LoaderTimeouts,
};
use deform_host::link::{open_serial, Port};
use deform_shared::frame;
use deform_shared::loader::{
    decode_frame, ImageHeader, LoaderError, LoaderRequest, LoaderResponse, LOADER_CHUNK,
    LOADER_FRAME_LEN,
};
use deform_shared::protocol::{SolveParams, Start};

use support::*;

fn boot_loader() -> Qemu {
    boot_loader_with(1)
}

fn boot_loader_with(harts: u8) -> Qemu {
    Qemu::start(&QemuConfig::new(loader_elf()).harts(harts))
        .unwrap_or_else(|e| panic!("cannot boot the loader: {e}"))
}

fn firmware_image() -> FlashImage {
    FlashImage::from_file(&firmware_elf()).expect("the firmware ELF makes an image")
}

fn loader_timeouts() -> LoaderTimeouts {
    LoaderTimeouts {
        handshake: Duration::from_secs(20),
        ..LoaderTimeouts::default()
    }
}

fn params() -> SolveParams {
    SolveParams {
        max_iterations: 5000,
        tolerance: 1e-10,
        start: Start::Zero,
        directions: 1,
        cycle_budget: 0,
    }
}

/// A port that damages chosen chunk frames on their way to the loader, the first time each is
/// sent: `flip` chunks get one bit flipped in their encoded frame (the frame CRC catches it and
/// the loader complains), `rewrite` chunks get one image byte changed and are framed again with
/// a good CRC (as if the host's copy were bad: only the whole-image CRC can catch that).
struct Saboteur<P> {
    inner: P,
    flip: Vec<u32>,
    rewrite: Vec<u32>,
    flipped: usize,
    rewritten: usize,
}

impl<P: Port> Saboteur<P> {
    fn damage(&mut self, bytes: &[u8]) -> Vec<u8> {
        let (lead, body) = match bytes.first() {
            Some(0) => bytes.split_at(1),
            _ => bytes.split_at(0),
        };
        let Some((_delimiter, frame_bytes)) = body.split_last() else {
            return bytes.to_vec();
        };
        let mut scratch = frame_bytes.to_vec();
        let Ok(mut envelope) = decode_frame::<LoaderRequest>(&mut scratch) else {
            return bytes.to_vec();
        };
        let LoaderRequest::Chunk { index, data } = &mut envelope.body else {
            return bytes.to_vec();
        };
        let mut out = lead.to_vec();
        if let Some(i) = self.flip.iter().position(|c| c == index) {
            self.flip.remove(i);
            self.flipped += 1;
            let mut damaged = body.to_vec();
            let k = damaged.len() / 2;
            damaged[k] ^= 0x04;
            if damaged[k] == 0 {
                damaged[k] = 0x55; // never a delimiter: the frame stays one frame
            }
            out.extend(damaged);
            return out;
        }
        if let Some(i) = self.rewrite.iter().position(|c| c == index) {
            self.rewrite.remove(i);
            self.rewritten += 1;
            data[7] ^= 0xFF;
            let mut buf = [0u8; LOADER_FRAME_LEN];
            let n = frame::encode(&envelope, &mut buf).unwrap();
            out.extend_from_slice(&buf[..n]);
            return out;
        }
        bytes.to_vec()
    }
}

impl<P: Port> Read for Saboteur<P> {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        self.inner.read(buf)
    }
}

impl<P: Port> Write for Saboteur<P> {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        let out = self.damage(buf);
        self.inner.write_all(&out)?;
        Ok(buf.len())
    }

    fn flush(&mut self) -> io::Result<()> {
        self.inner.flush()
    }
}

impl<P: Port> Port for Saboteur<P> {
    fn set_timeout(&mut self, timeout: Duration) -> io::Result<()> {
        self.inner.set_timeout(timeout)
    }
}

fn solve_banded(target: &mut deform_host::link::Target<impl Port>) {
    let matrix = banded_spd(120, 2);
    target.upload_matrix(&matrix).unwrap();
    let rhs: Vec<f64> = (0..120).map(|i| ((i % 7) as f64 - 3.0) * 0.25).collect();
    let (report, x) = target.solve_for(&rhs, params()).unwrap();
    assert!(report.converged, "{report:?}");
    let err = max_relative_error(&x, &cholesky_solve(&decode_dense(&matrix), &rhs));
    assert!(
        err < 1e-5,
        "max relative error {err:e} against the f64 reference"
    );
}

/// With two harts: the second waits in the loader and follows the first into the application,
/// which must not disturb it.
#[test]
fn flash_then_solve_matches_the_f64_reference() {
    let mut qemu = boot_loader_with(2);
    let image = firmware_image();
    let port = open_serial(qemu.pty_path().to_str().unwrap()).unwrap();
    let (mut target, report) =
        flash_and_connect(port, &image, loader_timeouts(), timeouts(), |_| {})
            .unwrap_or_else(|e| panic!("flash failed: {e}\nQEMU stderr:\n{}", qemu.stderr()));
    eprintln!(
        "flashed {} bytes in {} chunks: {:.0} ms, {:.1} KiB/s, {} wire bytes, {} resends",
        report.image_bytes,
        report.chunks,
        report.upload_time.as_secs_f64() * 1e3,
        report.throughput() / 1024.0,
        report.wire_bytes,
        report.resends
    );
    assert_eq!((report.attempts, report.resends), (1, 0), "{report:?}");
    assert_eq!(
        target.info().build_id.as_slice(),
        image.build_id.as_deref().unwrap()
    );
    solve_banded(&mut target);
    assert_alive(&mut qemu);
}

#[test]
fn corrupted_uploads_are_detected_and_retried_and_the_image_still_starts() {
    let mut qemu = boot_loader();
    let image = firmware_image();
    let chunks = image.bytes.len().div_ceil(LOADER_CHUNK) as u32;
    assert!(chunks > 10, "{chunks}");
    let port = Saboteur {
        inner: open_serial(qemu.pty_path().to_str().unwrap()).unwrap(),
        flip: vec![1, 5, chunks - 1],
        rewrite: vec![3],
        flipped: 0,
        rewritten: 0,
    };
    let (mut target, report) =
        flash_and_connect(port, &image, loader_timeouts(), timeouts(), |_| {})
            .unwrap_or_else(|e| panic!("flash failed: {e}\nQEMU stderr:\n{}", qemu.stderr()));
    // Chunk 3 was stored wrong once: the verification failed and the whole image went again.
    // The flipped frames were each resent at once.
    assert_eq!(report.attempts, 2, "{report:?}");
    assert!(report.resends >= 3, "{report:?}");
    solve_banded(&mut target);
    assert_alive(&mut qemu);
}

#[test]
fn the_loader_refuses_bad_images_and_malformed_frames_and_never_starts_an_unverified_image() {
    let mut qemu = boot_loader();
    let port = open_serial(qemu.pty_path().to_str().unwrap()).unwrap();
    let mut loader = LoaderLink::new(port, loader_timeouts());
    let info = loader.hello().unwrap();
    assert!(info.loader_start >= 0x8100_0000, "{info:?}");
    let refused =
        |loader: &mut LoaderLink<_>, request: LoaderRequest| match loader.request(&request) {
            Err(LoaderLinkError::Refused { error, .. }) => error,
            other => panic!("{request:?} was not refused: {other:?}"),
        };
    let good = ImageHeader {
        load_address: 0x8000_0000,
        length: 3 * LOADER_CHUNK as u32 - 5,
        entry: 0x8000_0000,
        crc32: 0,
    };
    let over_loader = ImageHeader {
        load_address: info.loader_start - 16,
        entry: info.loader_start - 16,
        ..good
    };
    assert!(matches!(
        refused(&mut loader, LoaderRequest::Begin(over_loader)),
        LoaderError::OverlapsLoader { .. }
    ));
    let below_ram = ImageHeader {
        load_address: 0x1000,
        entry: 0x1000,
        ..good
    };
    assert!(matches!(
        refused(&mut loader, LoaderRequest::Begin(below_ram)),
        LoaderError::OutOfRange { .. }
    ));
    assert_eq!(
        refused(&mut loader, LoaderRequest::Verify),
        LoaderError::NoImage
    );

    // An image whose header CRC is wrong: every chunk goes in, the verification fails, and Start
    // is refused.
    let bytes: Vec<u8> = (0..good.length).map(|i| (i * 7) as u8).collect();
    let header = ImageHeader {
        crc32: deform_shared::loader::CRC32.checksum(&bytes) ^ 1,
        ..good
    };
    assert_eq!(
        loader.request(&LoaderRequest::Begin(header)).unwrap(),
        LoaderResponse::Ack
    );
    assert_eq!(
        refused(&mut loader, LoaderRequest::Start),
        LoaderError::NotVerified
    );
    for (index, chunk) in bytes.chunks(LOADER_CHUNK).enumerate() {
        let request = LoaderRequest::Chunk {
            index: index as u32,
            data: chunk.iter().copied().collect(),
        };
        assert_eq!(loader.request(&request).unwrap(), LoaderResponse::Ack);
    }
    assert!(matches!(
        refused(&mut loader, LoaderRequest::Verify),
        LoaderError::ImageCrc { .. }
    ));
    assert_eq!(
        refused(&mut loader, LoaderRequest::Start),
        LoaderError::NotVerified
    );

    // Line noise and an overlong frame: each answered, nothing started, the loader still talks.
    let mut noise = Noise::new(0x0010_ADE2);
    loader.send_raw(&noise.bytes(3000)).unwrap();
    loader.send_raw(&[0x42; 2 * LOADER_FRAME_LEN]).unwrap();
    loader.send_raw(&[0]).unwrap();
    let info_again = loader.hello().unwrap();
    assert_eq!(info_again, info);
    assert!(loader.stats().requests > 0);
    assert_alive(&mut qemu);
}

#[test]
fn flashing_a_target_that_runs_the_application_says_so() {
    let mut qemu = boot();
    let port = open_serial(qemu.pty_path().to_str().unwrap()).unwrap();
    let mut loader = LoaderLink::new(
        port,
        LoaderTimeouts {
            handshake: Duration::from_secs(6),
            ..LoaderTimeouts::default()
        },
    );
    let err = loader.hello().unwrap_err();
    assert!(
        matches!(err, LoaderLinkError::NotTheLoader { .. }),
        "{err:?}"
    );
    assert!(
        err.to_string().contains("reset it into the loader"),
        "{err}"
    );
    let flash_err: FlashError = err.into();
    assert!(flash_err.to_string().contains("not as the loader"));
    assert_alive(&mut qemu);
}
