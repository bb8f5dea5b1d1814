//! A CA and certificates made with rcgen for the tests that run TLS.

use std::path::PathBuf;

use cellgate::client::ClientSecurity;
use rcgen::{
    BasicConstraints, CertificateParams, DnType, ExtendedKeyUsagePurpose, IsCa, Issuer, KeyPair,
    KeyUsagePurpose,
};

/// A CA and the certificates of the gateway, a router and the clients, as PEM files in a
/// temporary directory: `<name>.pem` and `<name>-key.pem`.
pub struct Pki {
    dir: tempfile::TempDir,
}

fn ca_params(cn: &str) -> CertificateParams {
    let mut p = CertificateParams::new(Vec::<String>::new()).unwrap();
    p.distinguished_name.push(DnType::CommonName, cn);
    p.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    p.key_usages = vec![
        KeyUsagePurpose::KeyCertSign,
        KeyUsagePurpose::CrlSign,
        KeyUsagePurpose::DigitalSignature,
    ];
    p
}

impl Pki {
    /// Signed by the CA: the gateway `cellgate-gw` and the router `router` (both for
    /// 127.0.0.1 and localhost), the clients `dash`, `mes`, `op`, `adm` and `nobody` (in no
    /// role). `forged-dash` has the common name `dash` but is signed by another CA.
    pub fn new() -> Pki {
        let pki = Pki {
            dir: tempfile::tempdir().unwrap(),
        };
        let ca_key = KeyPair::generate().unwrap();
        let ca = ca_params("cellgate test CA");
        std::fs::write(pki.path("ca.pem"), ca.self_signed(&ca_key).unwrap().pem()).unwrap();
        let issuer = Issuer::new(ca, ca_key);
        let hosts = || vec!["127.0.0.1".to_string(), "localhost".to_string()];
        for (name, cn, sans) in [
            ("gateway", "cellgate-gw", hosts()),
            ("router", "router", hosts()),
            ("dash", "dash", vec![]),
            ("mes", "mes", vec![]),
            ("op", "op", vec![]),
            ("adm", "adm", vec![]),
            ("nobody", "nobody", vec![]),
        ] {
            pki.leaf(&issuer, name, cn, sans);
        }
        let other_key = KeyPair::generate().unwrap();
        let other = Issuer::new(ca_params("some other CA"), other_key);
        pki.leaf(&other, "forged-dash", "dash", vec![]);
        pki
    }

    pub fn leaf(&self, issuer: &Issuer<'_, KeyPair>, name: &str, cn: &str, sans: Vec<String>) {
        let key = KeyPair::generate().unwrap();
        let mut p = CertificateParams::new(sans).unwrap();
        p.distinguished_name.push(DnType::CommonName, cn);
        p.extended_key_usages = vec![
            ExtendedKeyUsagePurpose::ServerAuth,
            ExtendedKeyUsagePurpose::ClientAuth,
        ];
        let cert = p.signed_by(&key, issuer).unwrap();
        std::fs::write(self.path(&format!("{name}.pem")), cert.pem()).unwrap();
        std::fs::write(self.path(&format!("{name}-key.pem")), key.serialize_pem()).unwrap();
    }

    pub fn path(&self, file: &str) -> PathBuf {
        self.dir.path().join(file)
    }

    pub fn ca(&self) -> PathBuf {
        self.path("ca.pem")
    }

    pub fn cert(&self, name: &str) -> PathBuf {
        self.path(&format!("{name}.pem"))
    }

    pub fn key(&self, name: &str) -> PathBuf {
        self.path(&format!("{name}-key.pem"))
    }

    /// What a client holding `name`'s certificate gives `Client::connect`.
    pub fn client(&self, name: &str) -> ClientSecurity {
        ClientSecurity {
            ca: Some(self.ca()),
            certificate: Some(self.cert(name)),
            private_key: Some(self.key(name)),
            credentials: None,
        }
    }
}
