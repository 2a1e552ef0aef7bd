//! # deform-shared
//!
//! The one schema crate that both ends of the deform link compile: the host (with the `std`
//! feature) and the RISC-V firmware (no_std). Everything that has to agree bit for bit between
//! the two lives here, so that it cannot drift:
//!
//! - [`word`]: the thesis's 32-bit MVU instruction word (EM, ER, 9-bit column, 21-bit value);
//! - [`qformat`]: fixed-point scaling of matrix values and block-floating-point vectors;
//! - [`protocol`]: the request and response messages;
//! - [`frame`]: how a message travels on the wire (postcard, CRC-32, COBS, `0x00` delimiter);
//! - [`transport`]: sequence numbers, window, ACK/NAK and the target's uplink frames;
//! - [`chunk`]: the fixed-width encoding of chunk payloads;
//! - [`field`]: the live loop's compact field frames (node selection, difference coding);
//! - [`dynamics`]: target-resident dynamic frames (the step's right-hand side formed on the target);
//! - [`loader`]: the serial loader's protocol (flashing an application over the UART);
//! - [`matrix`]: the tiled layout of a matrix as instruction words, and its validation.
#![cfg_attr(not(any(feature = "std", test)), no_std)]
#![forbid(unsafe_code)]

pub mod chunk;
pub mod dynamics;
pub mod field;
pub mod frame;
pub mod live;
pub mod loader;
pub mod matrix;
pub mod protocol;
pub mod qformat;
pub mod transport;
pub mod word;
