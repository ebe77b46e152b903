//! What the farm's binaries (`trove`, `trove-worker`) share at their edge.

use std::io::IsTerminal;

/// Why a byte count was refused; each message names the text given.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum BytesError {
    /// A unit other than B, KiB, MiB or GiB.
    #[error("`{text}`: unknown unit `{unit}`; expected bytes, or a number followed by KiB, MiB or GiB")]
    UnknownUnit {
        /// The text given.
        text: String,
        /// The unit in it.
        unit: String,
    },
    /// No number, or not one.
    #[error("`{0}`: expected a number of bytes, optionally followed by KiB, MiB or GiB")]
    NotANumber(String),
    /// More than `u64` bytes.
    #[error("`{0}`: too large")]
    TooLarge(String),
    /// Zero: a budget holds at least one byte.
    #[error("`{0}`: a memory budget must be at least one byte")]
    Zero(String),
}

/// A byte count: a plain number of bytes, or a number (decimals allowed) followed by
/// `B`, `KiB`, `MiB` or `GiB` (any case, optional space). Fractions of a byte round down.
pub fn parse_bytes(text: &str) -> Result<u64, BytesError> {
    let t = text.trim();
    let split = t.find(|c: char| !(c.is_ascii_digit() || c == '.')).unwrap_or(t.len());
    let (number, unit) = (&t[..split], t[split..].trim());
    let scale: u64 = match unit.to_ascii_lowercase().as_str() {
        "" | "b" => 1,
        "kib" => 1 << 10,
        "mib" => 1 << 20,
        "gib" => 1 << 30,
        _ => return Err(BytesError::UnknownUnit { text: text.to_string(), unit: unit.to_string() }),
    };
    let bad = || BytesError::NotANumber(text.to_string());
    let too_large = || BytesError::TooLarge(text.to_string());
    if number.is_empty() || number.matches('.').count() > 1 {
        return Err(bad());
    }
    let bytes = if number.contains('.') {
        let v: f64 = number.parse().map_err(|_| bad())?;
        let b = v * scale as f64;
        if !b.is_finite() || b >= u64::MAX as f64 {
            return Err(too_large());
        }
        b.floor() as u64
    } else {
        let v: u64 = number.parse().map_err(|_| too_large())?;
        v.checked_mul(scale).ok_or_else(too_large)?
    };
    if bytes == 0 {
        return Err(BytesError::Zero(text.to_string()));
    }
    Ok(bytes)
}

/// Logs to stderr through `tracing`, filtered by `RUST_LOG` (default `warn`), with colour
/// only when stderr is a terminal and `NO_COLOR` is unset or empty (no-color.org: only a
/// non-empty value asks for no colour).
pub fn init_logging() {
    let no_colour = std::env::var_os("NO_COLOR").is_some_and(|v| !v.is_empty());
    let colour = std::io::stderr().is_terminal() && !no_colour;
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into()))
        .with_writer(std::io::stderr)
        .with_ansi(colour)
        .init();
}

/// Resolves on Ctrl-C or, on Unix, SIGTERM (what Kubernetes sends a pod it stops).
pub async fn shutdown_signal() {
    let interrupt = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let terminate = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let terminate = std::future::pending::<()>();
    tokio::select! {
        () = interrupt => {}
        () = terminate => {}
    }
}

#[cfg(test)]
mod tests {
    use super::parse_bytes;

    #[test]
    fn byte_counts_take_binary_suffixes() {
        assert_eq!(parse_bytes("4096"), Ok(4096));
        assert_eq!(parse_bytes("64KiB"), Ok(64 << 10));
        assert_eq!(parse_bytes("3 MiB"), Ok(3 << 20));
        assert_eq!(parse_bytes("1.5GiB"), Ok(3 << 29));
        assert_eq!(parse_bytes("2gib"), Ok(2 << 30));
        assert_eq!(parse_bytes("100B"), Ok(100));
        for bad in ["", "MiB", "12 MB", "1.2.3KiB", "-5", "0", "99999999999999999999", "20000000000GiB", "1e3"] {
            assert!(parse_bytes(bad).is_err(), "{bad}");
        }
        assert!(matches!(parse_bytes("12 MB"), Err(super::BytesError::UnknownUnit { .. })));
        assert_eq!(parse_bytes("0"), Err(super::BytesError::Zero("0".into())));
    }
}
