//! TLS to `ssl://` and `mqtts://` brokers (rustls with ring), from AimRT's options: the
//! broker's certificate is checked against the CAs of `truststore` (required, as AimRT's)
//! and against the host of `broker_addr`; `client_cert` and `client_key` together give
//! the client certificate of mutual TLS. Every file is read and checked at start-up, so a
//! wrong path or a file without what it should hold stops start-up with its name.

use std::sync::Arc;

use rustls::{ClientConfig, RootCertStore};

use crate::connection::MqttPluginOptions;

/// The TLS set-up of the options' `ssl://` broker; `Err` names the option and the file.
///
/// ```
/// use aimrt_mqtt::{tls, MqttPluginOptions};
/// let tls_dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/tls");
/// let mut o = MqttPluginOptions::new("ssl://127.0.0.1:8883", "robot_1");
/// o.truststore = format!("{tls_dir}/ca.pem");
/// assert!(tls::client_config(&o).is_ok());
/// o.client_cert = format!("{tls_dir}/client.pem");
/// assert!(tls::client_config(&o).unwrap_err().contains("without client_key"));
/// o.client_key = format!("{tls_dir}/client.key");
/// assert!(tls::client_config(&o).is_ok());
/// ```
pub fn client_config(o: &MqttPluginOptions) -> Result<Arc<ClientConfig>, String> {
    if o.truststore.is_empty() {
        return Err(format!(
            "broker_addr '{}' is a TLS broker: set truststore to a PEM file of the CA certificates that signed the broker's certificate",
            o.broker_addr
        ));
    }
    let mut roots = RootCertStore::empty();
    let truststore = aimrt_pem::certificates("truststore", &o.truststore);
    for cert in truststore.map_err(|e| e.to_string())? {
        roots.add(cert).map_err(|e| {
            format!(
                "truststore '{}': a certificate cannot be used as a CA: {e}",
                o.truststore
            )
        })?;
    }
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let builder = ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| format!("cannot set up TLS: {e}"))?
        .with_root_certificates(roots);
    let config = match (o.client_cert.is_empty(), o.client_key.is_empty()) {
        (true, true) => {
            if !o.client_key_password.is_empty() {
                return Err(
                    "client_key_password is set without client_key: give client_cert and client_key, or leave the password out"
                        .into(),
                );
            }
            builder.with_no_client_auth()
        }
        (false, false) => {
            if !o.client_key_password.is_empty() {
                return Err(format!(
                    "client_key '{}' has a client_key_password: encrypted private keys are not supported; write it decrypted (`openssl pkey -in {} -out key.pem`), keep that file readable by this process only, and leave client_key_password out",
                    o.client_key, o.client_key
                ));
            }
            let (chain, key) = aimrt_pem::certified_key(
                ("client_cert", &o.client_cert),
                ("client_key", &o.client_key),
            )
            .map_err(|e| e.to_string())?;
            builder.with_client_auth_cert(chain, key).map_err(|e| {
                format!(
                    "client_cert '{}' and client_key '{}' do not go together: {e}",
                    o.client_cert, o.client_key
                )
            })?
        }
        (false, true) => {
            return Err(format!(
                "client_cert '{}' is set without client_key: mutual TLS needs both (PEM files)",
                o.client_cert
            ))
        }
        (true, false) => {
            return Err(format!(
                "client_key '{}' is set without client_cert: mutual TLS needs both (PEM files)",
                o.client_key
            ))
        }
    };
    Ok(Arc::new(config))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn options() -> MqttPluginOptions {
        let mut o = MqttPluginOptions::new("ssl://127.0.0.1:8883", "t");
        o.truststore = dir("ca.pem");
        o
    }

    fn dir(file: &str) -> String {
        format!("{}/../../tests/tls/{file}", env!("CARGO_MANIFEST_DIR"))
    }

    #[test]
    fn every_bad_tls_option_is_refused_naming_the_option_and_the_file() {
        // The files' own faults (encrypted keys, broken PEM) are aimrt-pem's tests.
        // (option, value) edits of the options, and what the error says.
        let cases: Vec<(Vec<(&str, String)>, String)> = vec![
            (
                vec![("truststore", String::new())],
                "is a TLS broker: set truststore".into(),
            ),
            (
                vec![("truststore", dir("missing.pem"))],
                format!("truststore '{}' cannot be read", dir("missing.pem")),
            ),
            (
                vec![("truststore", dir("ca.key"))],
                format!("truststore '{}' holds no certificate", dir("ca.key")),
            ),
            (
                vec![("client_key", dir("client.key"))],
                "is set without client_cert".into(),
            ),
            (
                vec![("client_key_password", "secret".into())],
                "client_key_password is set without client_key".into(),
            ),
            (
                vec![
                    ("client_cert", dir("client.pem")),
                    ("client_key", dir("client.pem")),
                ],
                format!("client_key '{}' holds no private key", dir("client.pem")),
            ),
            (
                vec![
                    ("client_cert", dir("client.pem")),
                    ("client_key", dir("broker.key")),
                ],
                "do not go together".into(),
            ),
            (
                vec![
                    ("client_cert", dir("client.pem")),
                    ("client_key", dir("client.key")),
                    ("client_key_password", "secret".into()),
                ],
                "has a client_key_password: encrypted private keys are not supported".into(),
            ),
        ];
        for (edits, expected) in cases {
            let mut o = options();
            for (key, value) in edits {
                *match key {
                    "truststore" => &mut o.truststore,
                    "client_cert" => &mut o.client_cert,
                    "client_key" => &mut o.client_key,
                    _ => &mut o.client_key_password,
                } = value;
            }
            let e = client_config(&o)
                .err()
                .unwrap_or_else(|| panic!("{o:?} was taken"));
            assert!(e.contains(&expected), "{o:?}: {e}\nexpected: {expected}");
        }
    }

    #[test]
    fn a_truststore_and_a_client_certificate_make_a_config_that_presents_it() {
        let mut o = options();
        assert!(!client_config(&o)
            .unwrap()
            .client_auth_cert_resolver
            .has_certs());
        o.client_cert = dir("client.pem");
        o.client_key = dir("client.key");
        assert!(client_config(&o)
            .unwrap()
            .client_auth_cert_resolver
            .has_certs());
    }
}
