//! Certificates made at run time for the TLS tests (so that no key is ever committed): a CA
//! and one server certificate it signed for 127.0.0.1 and localhost, as PEM.

use rcgen::{BasicConstraints, CertificateParams, CertifiedIssuer, DnType, IsCa, KeyPair, KeyUsagePurpose};

/// A test CA and a server certificate it signed, as PEM text.
pub struct TestPki {
    /// The CA's certificate.
    pub ca: String,
    /// The server's certificate.
    pub cert: String,
    /// The server's private key.
    pub key: String,
}

impl TestPki {
    /// A fresh CA and server certificate (for 127.0.0.1 and localhost).
    pub fn new() -> TestPki {
        let mut ca = CertificateParams::new(Vec::<String>::new()).expect("CA parameters");
        ca.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
        ca.distinguished_name.push(DnType::CommonName, "TROVE test CA");
        ca.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign];
        let issuer = CertifiedIssuer::self_signed(ca, KeyPair::generate().expect("a CA key")).expect("the CA");
        let key = KeyPair::generate().expect("a server key");
        let cert = CertificateParams::new(vec!["127.0.0.1".to_string(), "localhost".to_string()])
            .expect("server parameters")
            .signed_by(&key, &issuer)
            .expect("the server certificate");
        TestPki { ca: issuer.pem(), cert: cert.pem(), key: key.serialize_pem() }
    }
}

impl Default for TestPki {
    fn default() -> TestPki {
        TestPki::new()
    }
}
