//! Bearer tokens: who may call a farm's services.
//!
//! A farm has two secrets, so that a client's token cannot register a worker and a worker's
//! cannot submit jobs: the *client token* guards the coordinator's `Coordinator` service,
//! the *worker token* its `Membership` service and every worker's `Worker` service (the
//! coordinator presents it on its `Cast` streams, so that whoever reaches a worker's port can
//! neither cast nor read data). Each is optional: a service without one checks nothing.
//! Tokens travel as `authorization: Bearer <token>` metadata, which only TLS keeps secret on
//! the wire.

use std::fmt;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use tonic::metadata::{AsciiMetadataValue, MetadataMap};
use tonic::service::Interceptor;
use tonic::{Request, Status};

/// The metadata key a token travels under.
pub const AUTHORIZATION: &str = "authorization";

/// Why a token cannot be used; each message names the file.
#[derive(Debug, thiserror::Error)]
pub enum TokenError {
    /// The file cannot be read.
    #[error("cannot read the token file {}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// The file holds nothing but a newline: an empty token would admit anyone who sends one.
    #[error("the token file {} is empty: it must hold the token, on one line", path.display())]
    Empty {
        /// The file.
        path: PathBuf,
    },
    /// Characters an HTTP/2 header cannot carry.
    #[error("the token in {} has characters other than visible ASCII (letters, digits, punctuation)", path.display())]
    NotAscii {
        /// The file.
        path: PathBuf,
    },
}

/// A shared secret. Its `Debug` form never shows it.
#[derive(Clone)]
pub struct Token {
    /// `Bearer <token>`, as sent.
    header: AsciiMetadataValue,
}

impl fmt::Debug for Token {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("Token(..)")
    }
}

impl Token {
    /// The token held in `path`, without its trailing newline (`\n` or `\r\n`).
    pub fn from_file(path: &Path) -> Result<Token, TokenError> {
        let text = std::fs::read_to_string(path).map_err(|source| TokenError::Read { path: path.into(), source })?;
        Token::new(text.trim_end_matches(['\n', '\r'])).map_err(|e| match e {
            TokenError::Empty { .. } => TokenError::Empty { path: path.into() },
            _ => TokenError::NotAscii { path: path.into() },
        })
    }

    /// A token from its text: at least one character, all visible ASCII (an HTTP/2 header
    /// carries nothing else, and a space would make the `Bearer` form ambiguous).
    pub fn new(secret: &str) -> Result<Token, TokenError> {
        let path = PathBuf::new();
        if secret.is_empty() {
            return Err(TokenError::Empty { path });
        }
        if !secret.bytes().all(|b| b.is_ascii_graphic()) {
            return Err(TokenError::NotAscii { path });
        }
        let header = format!("Bearer {secret}").parse().map_err(|_| TokenError::NotAscii { path })?;
        Ok(Token { header })
    }

    /// Whether `metadata` carries this token.
    fn admits(&self, metadata: &MetadataMap) -> Result<(), Status> {
        let Some(sent) = metadata.get(AUTHORIZATION) else {
            return Err(Status::unauthenticated(
                "no bearer token: this service requires `authorization: Bearer <token>` metadata",
            ));
        };
        if constant_time_eq(sent.as_bytes(), self.header.as_bytes()) {
            Ok(())
        } else {
            Err(Status::unauthenticated("the bearer token is not the one this service accepts"))
        }
    }
}

/// Equality whose time depends on the lengths only, never on where the bytes first differ,
/// so that a caller cannot find a token byte by byte from response times.
fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    if a.len() != b.len() {
        return false;
    }
    let diff = a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y));
    // Keep the compiler from ending the fold early on a non-zero accumulator.
    std::hint::black_box(diff) == 0
}

/// A server-side interceptor: refuses, with `UNAUTHENTICATED`, every request that does not
/// carry the token; admits every request when there is none.
#[derive(Clone, Debug, Default)]
pub struct RequireToken(Option<Arc<Token>>);

impl RequireToken {
    /// Checks `token`, or nothing when `None`.
    pub fn new(token: Option<Token>) -> RequireToken {
        RequireToken(token.map(Arc::new))
    }
}

impl Interceptor for RequireToken {
    fn call(&mut self, request: Request<()>) -> Result<Request<()>, Status> {
        match &self.0 {
            Some(token) => token.admits(request.metadata()).map(|()| request),
            None => Ok(request),
        }
    }
}

/// A client-side interceptor: puts the token, if any, on every request.
#[derive(Clone, Debug, Default)]
pub struct AttachToken(Option<Arc<Token>>);

impl AttachToken {
    /// Sends `token`, or nothing when `None`.
    pub fn new(token: Option<Token>) -> AttachToken {
        AttachToken(token.map(Arc::new))
    }

    /// Whether requests carry a token.
    pub fn is_set(&self) -> bool {
        self.0.is_some()
    }
}

impl Interceptor for AttachToken {
    fn call(&mut self, mut request: Request<()>) -> Result<Request<()>, Status> {
        if let Some(token) = &self.0 {
            request.metadata_mut().insert(AUTHORIZATION, token.header.clone());
        }
        Ok(request)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn with(header: Option<&str>) -> Request<()> {
        let mut request = Request::new(());
        if let Some(h) = header {
            request.metadata_mut().insert(AUTHORIZATION, h.parse().unwrap());
        }
        request
    }

    #[test]
    fn only_the_token_passes_and_no_token_passes_everything() {
        let mut check = RequireToken::new(Some(Token::new("s3cret").unwrap()));
        assert!(check.call(with(Some("Bearer s3cret"))).is_ok());
        for bad in [None, Some("Bearer s3cre"), Some("Bearer s3cret2"), Some("s3cret"), Some("Basic s3cret")] {
            let refused = check.call(with(bad)).unwrap_err();
            assert_eq!(refused.code(), tonic::Code::Unauthenticated, "{bad:?}");
        }
        let mut open = RequireToken::new(None);
        assert!(open.call(with(None)).is_ok());
        let mut attach = AttachToken::new(Some(Token::new("s3cret").unwrap()));
        let sent = attach.call(Request::new(())).unwrap();
        assert!(check.call(sent).is_ok());
    }

    #[test]
    fn token_files_lose_their_newline_and_empty_ones_are_refused() {
        let dir = std::env::temp_dir().join(format!("trove-auth-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("token");
        std::fs::write(&file, "abc-123\r\n").unwrap();
        let token = Token::from_file(&file).unwrap();
        assert_eq!(token.header.to_str().unwrap(), "Bearer abc-123");
        assert_eq!(format!("{token:?}"), "Token(..)", "a token's Debug form hides it");
        std::fs::write(&file, "\n").unwrap();
        let empty = Token::from_file(&file).unwrap_err();
        assert!(matches!(empty, TokenError::Empty { .. }));
        assert!(empty.to_string().contains(&file.display().to_string()), "{empty}");
        std::fs::write(&file, "two words\n").unwrap();
        assert!(matches!(Token::from_file(&file), Err(TokenError::NotAscii { .. })));
        let missing = Token::from_file(&dir.join("absent")).unwrap_err();
        assert!(missing.to_string().contains("absent"), "{missing}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn equality_is_exact() {
        assert!(constant_time_eq(b"abc", b"abc"));
        assert!(!constant_time_eq(b"abc", b"abd"));
        assert!(!constant_time_eq(b"abc", b"abcd"));
        assert!(constant_time_eq(b"", b""));
    }
}
