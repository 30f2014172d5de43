//! The process's log output, one setup for every subcommand: `tracing`'s text format on stderr,
//! filtered by `RUST_LOG` (default `info`), coloured only when stderr is a terminal and
//! `NO_COLOR` is unset or empty (<https://no-color.org>), so a log redirected to a file or a
//! collector carries no escape codes. The server's per-request line is `api::access_log`.

use std::ffi::OsString;
use std::io::IsTerminal;

/// Installs the global subscriber. Call once, first thing in `main`.
pub fn init() {
    let ansi = use_colour(std::io::stderr().is_terminal(), std::env::var_os("NO_COLOR"));
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()))
        .with_writer(std::io::stderr)
        .with_ansi(ansi)
        .init();
}

/// Whether log lines get ANSI colours: only on a terminal, and never when `NO_COLOR` is set to
/// a non-empty value.
pub fn use_colour(stderr_is_terminal: bool, no_color: Option<OsString>) -> bool {
    stderr_is_terminal && no_color.is_none_or(|v| v.is_empty())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn colour_only_on_a_terminal_without_no_color() {
        assert!(use_colour(true, None));
        assert!(use_colour(true, Some("".into())), "an empty NO_COLOR does not count (no-color.org)");
        assert!(!use_colour(true, Some("1".into())));
        assert!(!use_colour(false, None), "a file or pipe gets no escape codes");
    }
}
