//! How every connection of the farm is made, on both sides: TLS when the URL says
//! `https://` (the server verified against a given CA), a bearer token on every request,
//! and HTTP/2 keepalive, so that a peer that vanished without closing its connection (a
//! pulled cable, a frozen VM) is noticed in [`KEEPALIVE_TIMEOUT`] rather than by TCP's
//! timeouts, which take many minutes.

use std::time::Duration;

use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Channel, Endpoint, Server};

use crate::auth::{AttachToken, Token};
use crate::tls::{CaCert, ServerTls};

/// How often an idle connection is pinged.
pub const KEEPALIVE_INTERVAL: Duration = Duration::from_secs(5);

/// How long a ping may go unanswered before the connection counts as dead.
pub const KEEPALIVE_TIMEOUT: Duration = Duration::from_secs(20);

/// A channel whose every request carries the connector's token (if any).
pub type AuthChannel = InterceptedService<Channel, AttachToken>;

/// Why a connection cannot be made.
#[derive(Debug, thiserror::Error)]
pub enum ConnectError {
    /// The URL does not parse.
    #[error("`{url}` is not a usable URL: {message}")]
    BadUrl {
        /// The URL.
        url: String,
        /// Why.
        message: String,
    },
    /// `https://` without a CA to verify the server with.
    #[error("`{url}` is https:// but no CA certificate was given to verify its server with (--tls-ca FILE)")]
    NoCa {
        /// The URL.
        url: String,
    },
    /// A CA given for a plaintext URL: the caller asked for TLS and would not get it.
    #[error("a CA certificate was given (--tls-ca) but `{url}` is not https://, so the connection would not use TLS")]
    CaWithoutTls {
        /// The URL.
        url: String,
    },
    /// The server cannot be reached, or the TLS handshake failed.
    #[error("cannot reach {url}: {message}")]
    Unreachable {
        /// The URL.
        url: String,
        /// Why, with its causes.
        message: String,
    },
}

/// An error and its causes on one line: tonic's transport errors say little at the top.
pub fn error_chain(e: &dyn std::error::Error) -> String {
    let mut text = e.to_string();
    let mut source = e.source();
    while let Some(s) = source {
        let next = s.to_string();
        if !text.contains(&next) {
            text.push_str(": ");
            text.push_str(&next);
        }
        source = s.source();
    }
    text
}

/// How one side of the farm reaches another: the CA it trusts (TLS) and the token it
/// presents. The default is plaintext without a token.
#[derive(Clone, Debug, Default)]
pub struct Connector {
    ca: Option<CaCert>,
    token: AttachToken,
}

impl Connector {
    /// Verifies servers against `ca` (so `https://` URLs work) and presents `token`.
    pub fn new(ca: Option<CaCert>, token: Option<Token>) -> Connector {
        Connector { ca, token: AttachToken::new(token) }
    }

    /// Whether it has a CA, i.e. speaks TLS.
    pub fn uses_tls(&self) -> bool {
        self.ca.is_some()
    }

    /// Whether it presents a token.
    pub fn sends_token(&self) -> bool {
        self.token.is_set()
    }

    /// The URL of a `host:port`: `https://` when this connector has a CA, else `http://`.
    pub fn url_for(&self, address: &str) -> String {
        let scheme = if self.uses_tls() { "https" } else { "http" };
        format!("{scheme}://{address}")
    }

    /// An endpoint for `url` with TLS (for `https://`) and keepalive set; the caller adds
    /// its deadlines.
    pub fn endpoint(&self, url: &str) -> Result<Endpoint, ConnectError> {
        let bad = |e: tonic::transport::Error| ConnectError::BadUrl { url: url.to_string(), message: error_chain(&e) };
        let endpoint = Endpoint::from_shared(url.to_string())
            .map_err(bad)?
            .tcp_nodelay(true)
            .http2_keep_alive_interval(KEEPALIVE_INTERVAL)
            .keep_alive_timeout(KEEPALIVE_TIMEOUT)
            .keep_alive_while_idle(true);
        let https = endpoint.uri().scheme_str() == Some("https");
        match (&self.ca, https) {
            (Some(ca), true) => endpoint.tls_config(ca.client_config()).map_err(bad),
            (None, true) => Err(ConnectError::NoCa { url: url.to_string() }),
            (Some(_), false) => Err(ConnectError::CaWithoutTls { url: url.to_string() }),
            (None, false) => Ok(endpoint),
        }
    }

    /// `channel` with this connector's token on every request.
    pub fn authorize(&self, channel: Channel) -> AuthChannel {
        InterceptedService::new(channel, self.token.clone())
    }

    /// Connects to `endpoint` now (failing if it cannot), with this connector's token.
    pub async fn connect(&self, endpoint: Endpoint) -> Result<AuthChannel, ConnectError> {
        let url = endpoint.uri().to_string();
        let channel = endpoint.connect().await.map_err(|e| ConnectError::Unreachable {
            url: url.trim_end_matches('/').to_string(),
            message: error_chain(&e),
        })?;
        Ok(self.authorize(channel))
    }
}

/// The connections a server accepts on `listener`, with `TCP_NODELAY` set. Tonic sets it
/// only on listeners it binds itself; ours are bound by the caller (so that a test can listen
/// on port 0). Without it a worker's answer, or the tail of a batch, can wait in the kernel
/// for the peer's delayed acknowledgement: measured on the farm's Table-1 job, batches took
/// 17.6 ms from dispatch to answer on average, of which 1.4 ms was casting.
pub fn incoming(listener: tokio::net::TcpListener) -> tonic::transport::server::TcpIncoming {
    tonic::transport::server::TcpIncoming::from(listener).with_nodelay(Some(true))
}

/// A server builder with keepalive set and, when `tls` is given, TLS.
pub fn server(tls: Option<&ServerTls>) -> Result<Server, tonic::transport::Error> {
    let builder = Server::builder()
        .http2_keepalive_interval(Some(KEEPALIVE_INTERVAL))
        .http2_keepalive_timeout(Some(KEEPALIVE_TIMEOUT));
    match tls {
        Some(tls) => builder.tls_config(tls.config()),
        None => Ok(builder),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn accepted_connections_send_at_once() {
        use tokio_stream::StreamExt;
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
        rt.block_on(async {
            let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
            let address = listener.local_addr().unwrap();
            let mut accepted = incoming(listener);
            let _client = tokio::net::TcpStream::connect(address).await.unwrap();
            let server_side = accepted.next().await.unwrap().unwrap();
            assert!(server_side.nodelay().unwrap(), "an accepted connection must not wait for Nagle's algorithm");
        });
    }

    #[test]
    fn the_scheme_and_the_ca_must_agree() {
        let plain = Connector::default();
        assert!(plain.endpoint("http://127.0.0.1:1").is_ok());
        assert!(matches!(plain.endpoint("https://127.0.0.1:1"), Err(ConnectError::NoCa { .. })));
        assert!(matches!(plain.endpoint("no url"), Err(ConnectError::BadUrl { .. })));
        assert_eq!(plain.url_for("10.0.0.1:7001"), "http://10.0.0.1:7001");
    }
}
