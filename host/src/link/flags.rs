//! The command-line flags that tune the link, shared by every command that talks to a target.

use std::time::Duration;

use super::{LinkConfig, Timeouts, DEFAULT_REQUEST_TIMEOUT};

/// How patiently the host talks to the target (`deform solve`, `deform simulate`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::Args)]
pub struct LinkFlags {
    /// Seconds the link may go without progress (nothing acknowledged by the target) before the
    /// command fails: a noisy line that keeps moving is never given up on, a dead one fails this
    /// long after its last answer (the solve itself has its own --timeout). Also bounds the
    /// handshake.
    #[arg(long, value_name = "SECS", default_value_t = DEFAULT_REQUEST_TIMEOUT.as_secs(),
          value_parser = clap::value_parser!(u64).range(1..))]
    pub link_timeout: u64,

    /// Most milliseconds a frame waits for its reply before it is sent again (the wait adapts
    /// to the target's measured answer time and its variation, at least 20 ms); doubled after
    /// each retry of the same frame with no sign of a damaged line (NAK, corrupt frame) since,
    /// up to 8× this.
    #[arg(long, value_name = "MS", default_value_t = LinkConfig::default().retransmit.as_millis() as u64,
          value_parser = clap::value_parser!(u64).range(1..))]
    pub retransmit_ms: u64,

    /// Retransmissions of one frame in a row with no sign of a damaged line between them (a
    /// target that is not there) before the command fails; on a noisy line the link waits as
    /// long as it makes progress (--link-timeout).
    #[arg(long, value_name = "N", default_value_t = LinkConfig::default().retries)]
    pub retries: u32,
}

impl Default for LinkFlags {
    fn default() -> Self {
        LinkFlags {
            link_timeout: DEFAULT_REQUEST_TIMEOUT.as_secs(),
            retransmit_ms: LinkConfig::default().retransmit.as_millis() as u64,
            retries: LinkConfig::default().retries,
        }
    }
}

impl LinkFlags {
    /// `timeouts` with these flags' settings; the solve timeout stays.
    pub fn apply(&self, timeouts: Timeouts) -> Timeouts {
        let request = Duration::from_secs(self.link_timeout);
        Timeouts {
            request,
            handshake: request,
            retransmit: Duration::from_millis(self.retransmit_ms),
            retries: self.retries,
            ..timeouts
        }
    }
}

#[cfg(test)]
mod tests {
    use clap::Parser;

    use super::*;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        link: LinkFlags,
    }

    #[test]
    fn defaults_match_the_link_defaults_and_flags_override_them() {
        let cli = Cli::parse_from(["x"]);
        assert_eq!(cli.link, LinkFlags::default());
        let t = cli.link.apply(Timeouts::default());
        assert_eq!(t.retries, LinkConfig::default().retries);
        assert_eq!(t.request, DEFAULT_REQUEST_TIMEOUT);
        let cli = Cli::parse_from([
            "x",
            "--link-timeout",
            "3",
            "--retries",
            "40",
            "--retransmit-ms",
            "20",
        ]);
        let t = cli.link.apply(Timeouts::default());
        assert_eq!(t.request, Duration::from_secs(3));
        assert_eq!(t.handshake, Duration::from_secs(3));
        assert_eq!(t.retries, 40);
        assert_eq!(t.retransmit, Duration::from_millis(20));
        assert!(Cli::try_parse_from(["x", "--link-timeout", "0"]).is_err());
    }
}
