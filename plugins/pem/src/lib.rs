//! The TLS files of a plugin's options, read and checked at start-up: PEM certificates,
//! PEM private keys (PKCS#8, SEC1 or PKCS#1, not encrypted), and whether a certificate
//! and a key go together. Every error names the option and the file, so a wrong path or a
//! file without what it should hold stops start-up with words a user can act on.
//!
//! ```
//! let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/tls");
//! let ca = format!("{dir}/ca.pem");
//! assert_eq!(aimrt_pem::certificates("truststore", &ca).unwrap().len(), 1);
//! let e = aimrt_pem::certificates("truststore", &format!("{dir}/ca.key")).unwrap_err();
//! assert!(e.to_string().starts_with("truststore '"), "{e}");
//! assert!(e.to_string().contains("holds no certificate"), "{e}");
//! ```

use std::sync::Arc;

pub use rustls::pki_types::{CertificateDer, PrivateKeyDer};

/// What is wrong with the TLS file of an option.
#[derive(Debug, thiserror::Error)]
pub enum PemError {
    /// The file cannot be read.
    #[error("{option} '{path}' cannot be read: {source}")]
    Unreadable {
        /// The option that names the file.
        option: String,
        /// The file.
        path: String,
        /// What reading it said.
        source: std::io::Error,
    },
    /// The file is not PEM text.
    #[error("{option} '{path}' is not a valid PEM file: {why}")]
    NotPem {
        /// The option that names the file.
        option: String,
        /// The file.
        path: String,
        /// What was wrong.
        why: String,
    },
    /// The file holds no certificate.
    #[error("{option} '{path}' holds no certificate: it must be a PEM file with '-----BEGIN CERTIFICATE-----' blocks")]
    NoCertificate {
        /// The option that names the file.
        option: String,
        /// The file.
        path: String,
    },
    /// The file holds no private key.
    #[error("{option} '{path}' holds no private key: it must be a PEM file with a 'PRIVATE KEY', 'EC PRIVATE KEY' or 'RSA PRIVATE KEY' block")]
    NoKey {
        /// The option that names the file.
        option: String,
        /// The file.
        path: String,
    },
    /// The key is encrypted.
    #[error("{option} '{path}' is encrypted: encrypted private keys are not supported; write it decrypted (`openssl pkey -in {path} -out key.pem`) and keep that file readable by this process only")]
    Encrypted {
        /// The option that names the file.
        option: String,
        /// The file.
        path: String,
    },
    /// The certificate's public key is not the private key's.
    #[error("{cert_option} '{cert_path}' and {key_option} '{key_path}' do not go together: {why}")]
    Mismatch {
        /// The option that names the certificate.
        cert_option: String,
        /// The certificate's file.
        cert_path: String,
        /// The option that names the key.
        key_option: String,
        /// The key's file.
        key_path: String,
        /// What was wrong.
        why: String,
    },
}

/// The most a TLS file may hold: a system's whole CA bundle is a few hundred KiB.
pub const MAX_PEM_BYTES: u64 = 16 << 20;

/// The file of option `option` at `path`: a regular file of at most [`MAX_PEM_BYTES`]
/// ([`aimrt_plugin_api::read_regular_file`]: a FIFO or a device is refused, not waited on).
fn read(option: &str, path: &str) -> Result<Vec<u8>, PemError> {
    aimrt_plugin_api::read_regular_file(std::path::Path::new(path), MAX_PEM_BYTES).map_err(
        |source| PemError::Unreadable {
            option: option.to_owned(),
            path: path.to_owned(),
            source,
        },
    )
}

fn not_pem(option: &str, path: &str, why: impl ToString) -> PemError {
    PemError::NotPem {
        option: option.to_owned(),
        path: path.to_owned(),
        why: why.to_string(),
    }
}

/// Every PEM certificate of the file of option `option` at `path`; at least one.
pub fn certificates(option: &str, path: &str) -> Result<Vec<CertificateDer<'static>>, PemError> {
    let text = read(option, path)?;
    let certs = rustls_pemfile::certs(&mut text.as_slice())
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| not_pem(option, path, e))?;
    if certs.is_empty() {
        return Err(PemError::NoCertificate {
            option: option.to_owned(),
            path: path.to_owned(),
        });
    }
    Ok(certs)
}

/// The private key of the file of option `option` at `path`: PKCS#8, SEC1 (EC) or PKCS#1
/// (RSA), not encrypted.
pub fn private_key(option: &str, path: &str) -> Result<PrivateKeyDer<'static>, PemError> {
    let text = read(option, path)?;
    // PKCS#8's encrypted block, or the legacy OpenSSL header of an encrypted PEM block.
    let has = |marker: &[u8]| text.windows(marker.len()).any(|w| w == marker);
    if has(b"-----BEGIN ENCRYPTED PRIVATE KEY-----") || has(b"Proc-Type: 4,ENCRYPTED") {
        return Err(PemError::Encrypted {
            option: option.to_owned(),
            path: path.to_owned(),
        });
    }
    rustls_pemfile::private_key(&mut text.as_slice())
        .map_err(|e| not_pem(option, path, e))?
        .ok_or_else(|| PemError::NoKey {
            option: option.to_owned(),
            path: path.to_owned(),
        })
}

/// The certificate chain of option `cert_option` and the private key of option
/// `key_option`, checked to go together (the chain's first certificate is the key's).
pub fn certified_key(
    (cert_option, cert_path): (&str, &str),
    (key_option, key_path): (&str, &str),
) -> Result<(Vec<CertificateDer<'static>>, PrivateKeyDer<'static>), PemError> {
    let chain = certificates(cert_option, cert_path)?;
    let key = private_key(key_option, key_path)?;
    let mismatch = |why: String| PemError::Mismatch {
        cert_option: cert_option.to_owned(),
        cert_path: cert_path.to_owned(),
        key_option: key_option.to_owned(),
        key_path: key_path.to_owned(),
        why,
    };
    let provider = rustls::crypto::ring::default_provider();
    let signing = provider
        .key_provider
        .load_private_key(key.clone_key())
        .map_err(|e| mismatch(format!("the key cannot sign: {e}")))?;
    rustls::sign::CertifiedKey::new(chain.clone(), Arc::clone(&signing))
        .keys_match()
        .map_err(|e| mismatch(e.to_string()))?;
    Ok((chain, key))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dir(file: &str) -> String {
        format!("{}/../../tests/tls/{file}", env!("CARGO_MANIFEST_DIR"))
    }

    #[test]
    fn every_bad_file_is_refused_naming_the_option_and_the_file() {
        let scratch = std::env::temp_dir().join(format!("aimrt-pem-{}", std::process::id()));
        std::fs::create_dir_all(&scratch).unwrap();
        let write = |name: &str, text: &str| {
            let path = scratch.join(name);
            std::fs::write(&path, text).unwrap();
            path.display().to_string()
        };
        // An encrypted key in PKCS#8's form and in OpenSSL's legacy one; a broken block.
        let encrypted = write(
            "encrypted.key",
            "-----BEGIN ENCRYPTED PRIVATE KEY-----\nMIIB\n-----END ENCRYPTED PRIVATE KEY-----\n",
        );
        let legacy = write(
            "legacy.key",
            "-----BEGIN EC PRIVATE KEY-----\nProc-Type: 4,ENCRYPTED\nDEK-Info: AES-128-CBC,00\n\nAAAA\n-----END EC PRIVATE KEY-----\n",
        );
        let broken = write("broken.pem", "-----BEGIN CERTIFICATE-----\nAAAA\n");
        // Sparse: 17 MiB long, no data written.
        let huge = scratch.join("huge.pem");
        std::fs::File::create(&huge)
            .and_then(|f| f.set_len(MAX_PEM_BYTES + (1 << 20)))
            .unwrap();
        let huge = huge.display().to_string();
        let said = |r: Result<(), PemError>| r.unwrap_err().to_string();
        let cert = |p: &str| certificates("ca", p).map(drop);
        let key = |p: &str| private_key("key", p).map(drop);
        let pair = |c: &str, k: &str| certified_key(("cert", c), ("key", k)).map(drop);
        let missing = dir("missing.pem");
        for (got, expected) in [
            (
                said(cert(&missing)),
                format!("ca '{missing}' cannot be read: "),
            ),
            (
                said(cert("/dev/zero")),
                "ca '/dev/zero' cannot be read: it is not a regular file".to_owned(),
            ),
            (
                said(key(&scratch.display().to_string())),
                format!(
                    "key '{}' cannot be read: it is not a regular file",
                    scratch.display()
                ),
            ),
            (
                said(cert(&huge)),
                format!("ca '{huge}' cannot be read: it holds more than 16777216 bytes"),
            ),
            (
                said(cert(&dir("ca.key"))),
                format!("ca '{}' holds no certificate", dir("ca.key")),
            ),
            (
                said(cert(&broken)),
                format!("ca '{broken}' is not a valid PEM file"),
            ),
            (
                said(key(&dir("broker.pem"))),
                format!("key '{}' holds no private key", dir("broker.pem")),
            ),
            (
                said(key(&encrypted)),
                format!("key '{encrypted}' is encrypted: encrypted private keys are not supported"),
            ),
            (said(key(&legacy)), format!("key '{legacy}' is encrypted")),
            (
                said(pair(&dir("broker.pem"), &dir("client.key"))),
                format!(
                    "cert '{}' and key '{}' do not go together",
                    dir("broker.pem"),
                    dir("client.key")
                ),
            ),
        ] {
            assert!(got.starts_with(&expected), "{got}\nexpected: {expected}");
        }
        let _ = std::fs::remove_dir_all(&scratch);
    }

    #[test]
    fn the_test_files_read_and_each_certificate_goes_with_its_key() {
        for name in ["broker", "client", "ca"] {
            let (chain, _) = certified_key(
                ("cert", &dir(&format!("{name}.pem"))),
                ("key", &dir(&format!("{name}.key"))),
            )
            .unwrap();
            assert_eq!(chain.len(), 1, "{name}");
        }
    }
}
