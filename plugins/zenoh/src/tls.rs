//! zenoh's TLS links (`tls/<host>:<port>` endpoints): the files of the native config's
//! `transport.link.tls`, read and checked before the session opens, so a wrong path, a
//! file without what it should hold, a certificate without its key or a TLS endpoint
//! without the files it needs stops start-up naming the key and the file. zenoh itself
//! says only "Invalid TLS certificate file", without which, when it creates the listener,
//! and nothing at all for the files of a connection it makes in the background.
//!
//! zenoh 1.10 reads the files itself when the session opens; relative paths start at the
//! working directory. Keys given inline (`…_base64`) are zenoh's to check.

use crate::connect::Connect;

/// `transport.link.tls` of a native config, as far as the files go.
#[derive(Debug, Default)]
struct TlsFiles {
    root_ca_certificate: Option<String>,
    listen_certificate: Option<String>,
    listen_private_key: Option<String>,
    connect_certificate: Option<String>,
    connect_private_key: Option<String>,
    enable_mtls: bool,
    /// Some `…_base64` key is set: zenoh has material these files do not show.
    inline: bool,
}

const KEY: &str = "transport.link.tls";

impl TlsFiles {
    fn of(config: &zenoh::Config) -> TlsFiles {
        let json = |key: &str| {
            config
                .get_json(&format!("transport/link/tls/{key}"))
                .ok()
                .and_then(|text| serde_json::from_str::<serde_json::Value>(&text).ok())
        };
        let path = |key: &str| json(key).and_then(|v| v.as_str().map(str::to_owned));
        let inline = [
            "root_ca_certificate_base64",
            "listen_certificate_base64",
            "listen_private_key_base64",
            "connect_certificate_base64",
            "connect_private_key_base64",
        ]
        .iter()
        .any(|key| json(key).is_some_and(|v| !v.is_null()));
        TlsFiles {
            root_ca_certificate: path("root_ca_certificate"),
            listen_certificate: path("listen_certificate"),
            listen_private_key: path("listen_private_key"),
            connect_certificate: path("connect_certificate"),
            connect_private_key: path("connect_private_key"),
            enable_mtls: json("enable_mtls").and_then(|v| v.as_bool()) == Some(true),
            inline,
        }
    }
}

/// Checks the TLS files of `config`, whose endpoints are `connect`'s: every file given
/// reads as what it should hold, each certificate goes with its key, and a `tls/` endpoint
/// has the files it needs (a listener its certificate and key; with `enable_mtls` a
/// listener the CA that signs its clients and a connection its own certificate and key).
pub(crate) fn check(config: &zenoh::Config, connect: &Connect) -> Result<(), String> {
    let f = TlsFiles::of(config);
    let named = |key: &str| format!("{KEY}.{key}");
    if let Some(ca) = &f.root_ca_certificate {
        aimrt_pem::certificates(&named("root_ca_certificate"), ca).map_err(|e| e.to_string())?;
    }
    let pair = |cert: &Option<String>, key: &Option<String>, side: &str| -> Result<bool, String> {
        let (c, k) = (
            named(&format!("{side}_certificate")),
            named(&format!("{side}_private_key")),
        );
        match (cert, key) {
            (Some(cert), Some(key)) => aimrt_pem::certified_key((&c, cert), (&k, key))
                .map(|_| true)
                .map_err(|e| e.to_string()),
            (Some(_), None) => Err(format!("{c} is set without {k}: give both (PEM files)")),
            (None, Some(_)) => Err(format!("{k} is set without {c}: give both (PEM files)")),
            (None, None) => Ok(false),
        }
    };
    let listen_files = pair(&f.listen_certificate, &f.listen_private_key, "listen")?;
    let connect_files = pair(&f.connect_certificate, &f.connect_private_key, "connect")?;
    if f.inline {
        return Ok(());
    }
    // An endpoint with its own settings after '#' may carry its own files.
    let own = |e: &&String| e.starts_with("tls/") && !e.contains('#');
    if let Some(e) = connect.listen.iter().find(own) {
        if !listen_files {
            return Err(format!(
                "listen endpoint '{e}' is TLS: set {} and {} to this process's certificate and its private key (PEM files)",
                named("listen_certificate"),
                named("listen_private_key")
            ));
        }
        if f.enable_mtls && f.root_ca_certificate.is_none() {
            return Err(format!(
                "listen endpoint '{e}' is TLS with {}: set {} to the CA certificates that signed the certificates of the processes that connect",
                named("enable_mtls"),
                named("root_ca_certificate")
            ));
        }
    }
    if let Some(e) = connect.endpoints.iter().find(own) {
        if f.enable_mtls && !connect_files {
            return Err(format!(
                "connect endpoint '{e}' is TLS with {}: set {} and {} to this process's certificate and its private key (PEM files)",
                named("enable_mtls"),
                named("connect_certificate"),
                named("connect_private_key")
            ));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tls(file: &str) -> String {
        format!("{}/../../tests/tls/{file}", env!("CARGO_MANIFEST_DIR"))
    }

    /// `check` of a peer listening and connecting on TLS with `link` as its
    /// `transport.link.tls` (JSON).
    fn checked(link: &str) -> Result<(), String> {
        let text = format!(
            r#"{{"mode": "peer", "listen": {{"endpoints": ["tls/127.0.0.1:7447"]}}, "connect": {{"endpoints": ["tls/127.0.0.1:7448"]}}, "transport": {{"link": {{"tls": {link}}}}}}}"#
        );
        let config = zenoh::Config::from_json5(&text).unwrap();
        check(&config, &Connect::of(&config))
    }

    fn files(pairs: &[(&str, &str)]) -> String {
        let fields: Vec<String> = pairs
            .iter()
            .map(|(k, v)| {
                if *v == "true" {
                    format!(r#""{k}": true"#)
                } else {
                    format!(r#""{k}": "{}""#, tls(v))
                }
            })
            .collect();
        format!("{{{}}}", fields.join(", "))
    }

    const MTLS: [(&str, &str); 6] = [
        ("root_ca_certificate", "ca.pem"),
        ("listen_certificate", "peer.pem"),
        ("listen_private_key", "peer.key"),
        ("connect_certificate", "peer.pem"),
        ("connect_private_key", "peer.key"),
        ("enable_mtls", "true"),
    ];

    #[test]
    fn a_complete_set_passes_and_every_fault_names_the_key_and_the_file() {
        assert_eq!(checked(&files(&MTLS)), Ok(()));
        // Without mutual TLS, a listener needs its pair alone.
        assert_eq!(checked(&files(&MTLS[1..3])), Ok(()));
        let with = |key: &str, value: Option<&str>| {
            let mut set: Vec<(&str, &str)> =
                MTLS.iter().filter(|(k, _)| *k != key).copied().collect();
            if let Some(v) = value {
                set.push((key, v));
            }
            checked(&files(&set)).unwrap_err()
        };
        for (got, expected) in [
            (
                with("root_ca_certificate", Some("missing.pem")),
                format!("transport.link.tls.root_ca_certificate '{}' cannot be read", tls("missing.pem")),
            ),
            (
                with("root_ca_certificate", Some("ca.key")),
                format!("transport.link.tls.root_ca_certificate '{}' holds no certificate", tls("ca.key")),
            ),
            (
                with("listen_private_key", Some("client.key")),
                format!(
                    "transport.link.tls.listen_certificate '{}' and transport.link.tls.listen_private_key '{}' do not go together",
                    tls("peer.pem"),
                    tls("client.key")
                ),
            ),
            (
                with("connect_private_key", Some("peer.pem")),
                format!("transport.link.tls.connect_private_key '{}' holds no private key", tls("peer.pem")),
            ),
            (
                with("connect_private_key", None),
                "transport.link.tls.connect_certificate is set without transport.link.tls.connect_private_key".into(),
            ),
            (
                with("listen_certificate", None),
                "transport.link.tls.listen_private_key is set without transport.link.tls.listen_certificate".into(),
            ),
            (
                with("root_ca_certificate", None),
                "listen endpoint 'tls/127.0.0.1:7447' is TLS with transport.link.tls.enable_mtls: set transport.link.tls.root_ca_certificate".into(),
            ),
        ] {
            assert!(got.starts_with(&expected), "{got}\nexpected: {expected}");
        }
        let bare = checked("{}").unwrap_err();
        assert_eq!(bare, "listen endpoint 'tls/127.0.0.1:7447' is TLS: set transport.link.tls.listen_certificate and transport.link.tls.listen_private_key to this process's certificate and its private key (PEM files)");
        let no_client_pair = checked(&files(&[MTLS[0], MTLS[1], MTLS[2], MTLS[5]])).unwrap_err();
        assert!(
            no_client_pair.starts_with("connect endpoint 'tls/127.0.0.1:7448' is TLS with transport.link.tls.enable_mtls: set transport.link.tls.connect_certificate and"),
            "{no_client_pair}"
        );
    }

    /// `config/zenoh_native_tls_{a,b}.json5` load, listen on TLS and have every file
    /// they name (relative to the repository root, where the examples run).
    #[test]
    fn the_example_tls_configs_pass_the_checks() {
        let root = concat!(env!("CARGO_MANIFEST_DIR"), "/../..");
        for side in ["a", "b"] {
            let path = format!("{root}/config/zenoh_native_tls_{side}.json5");
            let text = std::fs::read_to_string(&path).unwrap();
            let text = text.replace("\"./tests/tls/", &format!("\"{root}/tests/tls/"));
            let config = zenoh::Config::from_json5(&text).unwrap();
            let connect = Connect::of(&config);
            assert!(
                connect.listen.iter().all(|e| e.starts_with("tls/")),
                "{path}"
            );
            assert_eq!(connect.check(), Ok(()), "{path}");
            assert_eq!(check(&config, &connect), Ok(()), "{path}");
            assert!(TlsFiles::of(&config).enable_mtls, "{path}");
        }
    }

    #[test]
    fn inline_keys_and_tcp_endpoints_need_no_files() {
        // zenoh's inline form: its own to check.
        assert_eq!(
            checked(
                r#"{"listen_private_key_base64": "AAAA", "listen_certificate_base64": "AAAA"}"#
            ),
            Ok(())
        );
        let config = zenoh::Config::from_json5(
            r#"{"mode": "peer", "listen": {"endpoints": ["tcp/127.0.0.1:7447"]}}"#,
        )
        .unwrap();
        assert_eq!(check(&config, &Connect::of(&config)), Ok(()));
    }
}
