//! TLS material, read and checked once at start: a server's certificate and key, and the CA
//! certificate a client verifies its server against. TLS runs through rustls (ring as its
//! crypto provider); files are PEM, as `openssl` writes them (README, "Security").
//!
//! Both are checked as they are read, so that a wrong file is refused at start with its name
//! rather than at the first connection with a handshake error.

use std::fmt;
use std::path::{Path, PathBuf};

use tonic::transport::{Certificate, ClientTlsConfig, Endpoint, Identity, Server, ServerTlsConfig};

/// Why TLS material cannot be used; each message names the file.
#[derive(Debug, thiserror::Error)]
pub enum TlsError {
    /// A file cannot be read.
    #[error("cannot read {what} {}", path.display())]
    Read {
        /// What the file should hold.
        what: &'static str,
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// A file holds no PEM block of the expected kind.
    #[error("{} is not {what} in PEM form: expected a `-----BEGIN {label}-----` block", path.display())]
    NotPem {
        /// What the file should hold.
        what: &'static str,
        /// The PEM label looked for.
        label: &'static str,
        /// The file.
        path: PathBuf,
    },
    /// rustls refused the material (a malformed certificate, a key that does not parse).
    #[error("{what} ({}) is unusable: {message}", path.display())]
    Invalid {
        /// What was refused.
        what: &'static str,
        /// The file (or files) it came from.
        path: PathBuf,
        /// rustls' reason.
        message: String,
    },
}

fn read(path: &Path, what: &'static str) -> Result<Vec<u8>, TlsError> {
    std::fs::read(path).map_err(|source| TlsError::Read { what, path: path.into(), source })
}

fn require_pem(bytes: &[u8], label: &'static str, what: &'static str, path: &Path) -> Result<(), TlsError> {
    let text = String::from_utf8_lossy(bytes);
    let found = match label {
        // PKCS#8, PKCS#1 ("RSA PRIVATE KEY") and SEC1 ("EC PRIVATE KEY") keys.
        "PRIVATE KEY" => text.lines().any(|l| l.starts_with("-----BEGIN") && l.ends_with("PRIVATE KEY-----")),
        _ => text.contains(&format!("-----BEGIN {label}-----")),
    };
    if found {
        Ok(())
    } else {
        Err(TlsError::NotPem { what, label, path: path.into() })
    }
}

/// A server's TLS identity: its certificate chain and private key. `Debug` shows the
/// certificate's file, never the key.
#[derive(Clone)]
pub struct ServerTls {
    config: ServerTlsConfig,
    cert_path: PathBuf,
}

impl fmt::Debug for ServerTls {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("ServerTls").field("cert", &self.cert_path).finish_non_exhaustive()
    }
}

impl ServerTls {
    /// Reads the certificate chain at `cert` and the private key at `key` (PEM).
    pub fn from_files(cert: &Path, key: &Path) -> Result<ServerTls, TlsError> {
        let cert_pem = read(cert, "a certificate")?;
        let key_pem = read(key, "a private key")?;
        require_pem(&cert_pem, "CERTIFICATE", "a certificate", cert)?;
        require_pem(&key_pem, "PRIVATE KEY", "a private key", key)?;
        ServerTls::build(&cert_pem, &key_pem, cert)
    }

    /// An identity from PEM text already in memory (tests make theirs at run time).
    pub fn from_pem(cert_pem: &[u8], key_pem: &[u8]) -> Result<ServerTls, TlsError> {
        let here = Path::new("<memory>");
        require_pem(cert_pem, "CERTIFICATE", "a certificate", here)?;
        require_pem(key_pem, "PRIVATE KEY", "a private key", here)?;
        ServerTls::build(cert_pem, key_pem, here)
    }

    fn build(cert_pem: &[u8], key_pem: &[u8], cert_path: &Path) -> Result<ServerTls, TlsError> {
        let config = ServerTlsConfig::new().identity(Identity::from_pem(cert_pem, key_pem));
        // Building an acceptor parses both; done here, so a bad file is refused at start.
        Server::builder().tls_config(config.clone()).map_err(|e| TlsError::Invalid {
            what: "the certificate and key",
            path: cert_path.into(),
            message: crate::connect::error_chain(&e),
        })?;
        Ok(ServerTls { config, cert_path: cert_path.into() })
    }

    /// The configuration a `tonic` server takes.
    pub fn config(&self) -> ServerTlsConfig {
        self.config.clone()
    }
}

/// The CA certificate (or bundle) a client trusts: its server's certificate must chain to it.
#[derive(Clone, Debug)]
pub struct CaCert {
    cert: Certificate,
}

impl CaCert {
    /// Reads the CA certificate at `path` (PEM; several concatenated are a bundle).
    pub fn from_file(path: &Path) -> Result<CaCert, TlsError> {
        let pem = read(path, "a CA certificate")?;
        CaCert::build(&pem, path)
    }

    /// A CA certificate from PEM text already in memory.
    pub fn from_pem(pem: &[u8]) -> Result<CaCert, TlsError> {
        CaCert::build(pem, Path::new("<memory>"))
    }

    fn build(pem: &[u8], path: &Path) -> Result<CaCert, TlsError> {
        require_pem(pem, "CERTIFICATE", "a CA certificate", path)?;
        let cert = Certificate::from_pem(pem);
        // Building a connector parses the certificate; done here, so a bad file is refused
        // at start.
        Endpoint::from_static("https://localhost")
            .tls_config(ClientTlsConfig::new().ca_certificate(cert.clone()))
            .map_err(|e| TlsError::Invalid {
                what: "the CA certificate",
                path: path.into(),
                message: crate::connect::error_chain(&e),
            })?;
        Ok(CaCert { cert })
    }

    /// The client configuration that trusts this CA only.
    pub fn client_config(&self) -> ClientTlsConfig {
        ClientTlsConfig::new().ca_certificate(self.cert.clone())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn files_that_are_not_pem_are_refused_naming_them() {
        let dir = std::env::temp_dir().join(format!("trove-tls-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let junk = dir.join("junk.pem");
        std::fs::write(&junk, "not a certificate\n").unwrap();
        let e = CaCert::from_file(&junk).unwrap_err();
        assert!(matches!(e, TlsError::NotPem { .. }), "{e}");
        assert!(e.to_string().contains("junk.pem"), "{e}");
        let e = ServerTls::from_files(&junk, &dir.join("missing.key")).unwrap_err();
        assert!(matches!(e, TlsError::Read { .. }) && e.to_string().contains("missing.key"), "{e}");
        // A key file that holds a certificate's block is not a key.
        std::fs::write(&junk, "-----BEGIN CERTIFICATE-----\nAAAA\n-----END CERTIFICATE-----\n").unwrap();
        let e = ServerTls::from_files(&junk, &junk).unwrap_err();
        assert!(matches!(e, TlsError::NotPem { label: "PRIVATE KEY", .. }), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
