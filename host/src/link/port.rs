use std::io::{self, Read, Write};
use std::time::Duration;

use serialport::SerialPort;

use super::LinkError;

/// The target's UART speed. A pty ignores it; a USB-serial board needs it.
pub const BAUD_RATE: u32 = 115_200;

/// A read that only ran out of time (or was interrupted): no data yet, not a failure of the
/// port. The frame reader and the LiteX BIOS client both wait on.
pub fn is_timeout(e: &io::Error) -> bool {
    matches!(
        e.kind(),
        io::ErrorKind::TimedOut | io::ErrorKind::WouldBlock | io::ErrorKind::Interrupted
    )
}

/// A byte stream to a target whose reads and writes can be bounded in time.
///
/// [`Link`](super::Link) sets the timeout before every read and write so that the overall
/// deadline of a request holds whatever the peer does.
pub trait Port: Read + Write + Send {
    /// Bounds the next reads and writes: one that makes no progress for `timeout` fails with
    /// [`io::ErrorKind::TimedOut`] or [`io::ErrorKind::WouldBlock`].
    fn set_timeout(&mut self, timeout: Duration) -> io::Result<()>;
}

impl Port for Box<dyn SerialPort> {
    fn set_timeout(&mut self, timeout: Duration) -> io::Result<()> {
        SerialPort::set_timeout(self.as_mut(), timeout).map_err(io::Error::from)
    }
}

#[cfg(unix)]
impl Port for std::os::unix::net::UnixStream {
    fn set_timeout(&mut self, timeout: Duration) -> io::Result<()> {
        // A zero timeout means "block forever" to the socket API.
        let timeout = Some(timeout.max(Duration::from_millis(1)));
        self.set_read_timeout(timeout)?;
        self.set_write_timeout(timeout)
    }
}

/// Opens a serial port (or QEMU's pty) in raw mode at [`BAUD_RATE`].
///
/// Only the data lines are used: a pty has no modem lines, and asking for them fails, so this
/// neither sets nor reads DTR/RTS.
pub fn open_serial(path: &str) -> Result<Box<dyn SerialPort>, LinkError> {
    serialport::new(path, BAUD_RATE)
        .timeout(Duration::from_millis(100))
        .open()
        .map_err(|source| LinkError::Open {
            path: path.to_string(),
            source,
        })
}
