//! What the serial driver talks through: a byte link with read timeouts, opened (and
//! reopened after an unplug) by a connector.
//!
//! Real ports come from [`PortConnector`] (the `serialport` crate); the simulator's
//! connector hands out pseudo-terminals with its firmware on the other end; tests use
//! scripted links. The driver above them is the same code.
use std::io::{self, Read, Write};
use std::time::Duration;

use serialport::SerialPort;

/// A byte link to a controller.
pub trait Link: Send {
    /// Writes all of `bytes`.
    fn send(&mut self, bytes: &[u8]) -> io::Result<()>;
    /// Reads what is available, waiting up to `timeout`; `Ok(0)` means nothing came.
    /// An error means the link is broken (unplugged).
    fn receive(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize>;
    /// Drops whatever unread input is buffered (stale replies, line noise).
    fn discard_input(&mut self) -> io::Result<()>;
    /// A second handle that writes to the same link, for out-of-band lines (the laser
    /// keepalive, an emergency `LASER OFF`) sent from another thread while this one
    /// waits for a reply. Links that cannot offer one (scripted test links) say so,
    /// and the driver then sends those lines through the link itself.
    fn out_of_band_writer(&self) -> io::Result<Box<dyn Write + Send>> {
        Err(io::Error::new(
            io::ErrorKind::Unsupported,
            "this link has no out-of-band writer",
        ))
    }
}

/// Opens a link; called again to reconnect.
pub trait Connector: Send {
    /// Opens the link.
    fn connect(&mut self) -> io::Result<Box<dyn Link>>;
    /// Where it connects, for messages (`/dev/ttyUSB0`).
    fn describe(&self) -> String;
}

impl<P: SerialPort + ?Sized> Link for Box<P> {
    fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        self.write_all(bytes)?;
        self.flush()
    }

    fn receive(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize> {
        self.set_timeout(timeout.max(Duration::from_micros(1)))?;
        match self.read(buf) {
            Ok(0) => Err(io::Error::new(
                io::ErrorKind::UnexpectedEof,
                "the port was closed",
            )),
            Ok(n) => Ok(n),
            Err(e) if e.kind() == io::ErrorKind::TimedOut || e.kind() == io::ErrorKind::WouldBlock => Ok(0),
            Err(e) => Err(e),
        }
    }

    fn discard_input(&mut self) -> io::Result<()> {
        self.clear(serialport::ClearBuffer::Input)
            .map_err(io::Error::from)
    }

    fn out_of_band_writer(&self) -> io::Result<Box<dyn Write + Send>> {
        let port = self.try_clone().map_err(io::Error::from)?;
        Ok(Box::new(port))
    }
}

/// A real serial port by path and baud rate (8N1, no flow control).
#[derive(Clone, Debug)]
pub struct PortConnector {
    /// Port path.
    pub path: String,
    /// Baud rate.
    pub baud: u32,
}

impl Connector for PortConnector {
    fn connect(&mut self) -> io::Result<Box<dyn Link>> {
        let port = serialport::new(&self.path, self.baud)
            .timeout(Duration::from_millis(10))
            .open()
            .map_err(|e| {
                // The crate reports a port another process holds (its `TIOCEXCL` or
                // its lock) as "no device"; a path that is there is held, not gone.
                let held =
                    e.kind == serialport::ErrorKind::NoDevice && std::path::Path::new(&self.path).exists();
                let e = io::Error::from(e);
                if held {
                    io::Error::new(io::ErrorKind::ResourceBusy, e)
                } else {
                    e
                }
            })?;
        Ok(Box::new(port))
    }

    fn describe(&self) -> String {
        self.path.clone()
    }
}
