//! Flashing: putting an application into a target's RAM through the serial loader and starting
//! it, as a soft core on an FPGA receives its program (see [`deform_shared::loader`] for the
//! protocol and `firmware/src/bin/loader.rs` for the loader).
//!
//! [`flash`] uploads one [`FlashImage`] and starts it only after the loader has verified the
//! CRC-32 of the whole image in RAM; a failed verification uploads the image again, up to
//! [`IMAGE_ATTEMPTS`] times. [`flash_and_connect`] then shakes hands with the started
//! application and checks that it is the image just sent (its build id).

pub mod boards;
mod client;
mod image;
pub mod sfl;

use std::time::{Duration, Instant};

use deform_shared::loader::{LoaderError, LoaderRequest, LoaderResponse, LOADER_CHUNK};

pub use client::{LoaderLink, LoaderLinkError, LoaderStats, LoaderTimeouts};
pub use image::{FlashImage, ImageError, MAX_GAP};

use crate::link::{Link, LinkError, Port, Target, Timeouts};

/// Whole-image uploads tried before giving up when the verification keeps failing.
pub const IMAGE_ATTEMPTS: u32 = 3;

#[derive(Debug, thiserror::Error)]
pub enum FlashError {
    #[error(transparent)]
    Image(#[from] ImageError),
    #[error(transparent)]
    Loader(#[from] LoaderLinkError),
    #[error("the loader cannot take this image: {0}")]
    Rejected(LoaderError),
    #[error(
        "the image failed its verification {attempts} times (last: {last}); it was not started"
    )]
    VerifyFailed { attempts: u32, last: LoaderError },
    #[error("the started application did not shake hands: {0}")]
    Application(#[source] LinkError),
    #[error(
        "the application that answered is not the image just flashed: build id {running} \
         instead of {flashed}"
    )]
    WrongApplication { flashed: String, running: String },
}

/// How an upload went.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FlashReport {
    pub image_bytes: usize,
    pub chunks: usize,
    /// Whole-image uploads (1 unless a verification failed).
    pub attempts: u32,
    /// Frames resent after a timeout or a corrupt-frame complaint.
    pub resends: u64,
    /// Bytes put on the wire, frames and retries included.
    pub wire_bytes: u64,
    /// From `Begin` to the loader's `Starting`.
    pub upload_time: Duration,
}

impl FlashReport {
    /// Image bytes per second of upload.
    pub fn throughput(&self) -> f64 {
        self.image_bytes as f64 / self.upload_time.as_secs_f64().max(1e-9)
    }
}

/// How far an upload has got, after every chunk.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FlashProgress {
    pub bytes_sent: usize,
    pub bytes_total: usize,
    pub attempt: u32,
}

/// Uploads `image` through a loader that has shaken hands, has it verified, and starts it.
pub fn flash<P: Port>(
    loader: &mut LoaderLink<P>,
    image: &FlashImage,
    mut progress: impl FnMut(FlashProgress),
) -> Result<FlashReport, FlashError> {
    let info = loader.hello()?;
    let header = image.header();
    header.check(&info).map_err(FlashError::Rejected)?;
    let started = Instant::now();
    let before = loader.stats();
    let mut attempts = 0;
    loop {
        attempts += 1;
        expect_ack(loader, &LoaderRequest::Begin(header))?;
        for (index, chunk) in image.bytes.chunks(LOADER_CHUNK).enumerate() {
            expect_ack(
                loader,
                &LoaderRequest::Chunk {
                    index: index as u32,
                    data: chunk.iter().copied().collect(),
                },
            )?;
            progress(FlashProgress {
                bytes_sent: index * LOADER_CHUNK + chunk.len(),
                bytes_total: image.bytes.len(),
                attempt: attempts,
            });
        }
        match loader.request(&LoaderRequest::Verify) {
            Ok(LoaderResponse::Verified { crc32 }) if crc32 == header.crc32 => break,
            Ok(got) => {
                return Err(LoaderLinkError::Unexpected {
                    request: "Verify",
                    got,
                }
                .into())
            }
            Err(LoaderLinkError::Refused {
                error: last @ LoaderError::ImageCrc { .. },
                ..
            }) if attempts >= IMAGE_ATTEMPTS => {
                return Err(FlashError::VerifyFailed { attempts, last })
            }
            Err(LoaderLinkError::Refused {
                error: LoaderError::ImageCrc { .. },
                ..
            }) => continue,
            Err(e) => return Err(e.into()),
        }
    }
    match loader.request(&LoaderRequest::Start)? {
        LoaderResponse::Starting { entry } if entry == header.entry => {}
        got => {
            return Err(LoaderLinkError::Unexpected {
                request: "Start",
                got,
            }
            .into())
        }
    }
    let after = loader.stats();
    Ok(FlashReport {
        image_bytes: image.bytes.len(),
        chunks: image.bytes.len().div_ceil(LOADER_CHUNK),
        attempts,
        resends: after.resends - before.resends,
        wire_bytes: after.bytes_sent - before.bytes_sent,
        upload_time: started.elapsed(),
    })
}

fn expect_ack<P: Port>(
    loader: &mut LoaderLink<P>,
    request: &LoaderRequest,
) -> Result<(), FlashError> {
    match loader.request(request)? {
        LoaderResponse::Ack => Ok(()),
        got => Err(LoaderLinkError::Unexpected {
            request: client::request_name(request),
            got,
        }
        .into()),
    }
}

/// [`flash`]es `image` over `port`, then shakes hands with the application it started and checks
/// that the application reports the image's build id.
pub fn flash_and_connect<P: Port>(
    port: P,
    image: &FlashImage,
    loader_timeouts: LoaderTimeouts,
    timeouts: Timeouts,
    progress: impl FnMut(FlashProgress),
) -> Result<(Target<P>, FlashReport), FlashError> {
    let mut loader = LoaderLink::new(port, loader_timeouts);
    let report = flash(&mut loader, image, progress)?;
    let target = Target::handshake(Link::new(loader.into_port()), timeouts)
        .map_err(FlashError::Application)?;
    check_build_id(image, &target.info().build_id)?;
    Ok((target, report))
}

/// Refuses an application whose build id is not the image's (when the image has one).
pub fn check_build_id(image: &FlashImage, running: &[u8]) -> Result<(), FlashError> {
    match &image.build_id {
        Some(flashed) if flashed.as_slice() != running => Err(FlashError::WrongApplication {
            flashed: hex(flashed),
            running: hex(running),
        }),
        _ => Ok(()),
    }
}

/// Bytes as lowercase hex, as `readelf -n` prints a build id.
pub fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}
