//! What opening the session waits for (a router in client mode, or a peer that must answer),
//! said before it waits, and what to do when nothing answers there, said when it fails.
//!
//! zenoh 1.10 opens a `client` session only once it has connected to one of its
//! `connect.endpoints`: with `connect.timeout_ms` 0 (a client's default) it tries once and
//! fails, with -1 it tries until it connects, however long that is. A peer or router
//! waits the same way only with `connect.exit_on_failure: true`; otherwise it goes on and
//! connects in the background.

/// How the native config has the session connect, for the mode it runs in.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Connect {
    /// `peer`, `client` or `router`.
    pub(crate) mode: String,
    endpoints: Vec<String>,
    /// `connect.timeout_ms`: 0 once, -1 without end, else that long.
    timeout_ms: i64,
    exit_on_failure: bool,
}

impl Connect {
    /// Reads `mode` and `connect` of `config`, with zenoh 1.10's defaults for the mode
    /// where the config is silent (each key may hold one value or one a mode).
    pub(crate) fn of(config: &zenoh::Config) -> Connect {
        let json = |key: &str| {
            config
                .get_json(key)
                .ok()
                .and_then(|text| serde_json::from_str::<serde_json::Value>(&text).ok())
        };
        let mode = json("mode")
            .and_then(|v| v.as_str().map(str::to_owned))
            .unwrap_or_else(|| "peer".into());
        let of_mode = |key: &str| {
            json(key).and_then(|v| match v {
                serde_json::Value::Object(mut modes) => modes.remove(&mode),
                serde_json::Value::Null => None,
                v => Some(v),
            })
        };
        let client = mode == "client";
        Connect {
            endpoints: of_mode("connect/endpoints")
                .and_then(|v| serde_json::from_value(v).ok())
                .unwrap_or_default(),
            timeout_ms: of_mode("connect/timeout_ms")
                .and_then(|v| v.as_i64())
                .unwrap_or(if client { 0 } else { -1 }),
            exit_on_failure: of_mode("connect/exit_on_failure")
                .and_then(|v| v.as_bool())
                .unwrap_or(client),
            mode,
        }
    }

    /// The line to say before opening, when opening waits until it connects.
    pub(crate) fn waiting(&self) -> Option<String> {
        let waits = !self.endpoints.is_empty()
            && self.timeout_ms != 0
            && (self.mode == "client" || self.exit_on_failure);
        let how_long = if self.timeout_ms < 0 {
            "without end: connect.timeout_ms is -1".to_owned()
        } else {
            format!("up to {} ms: connect.timeout_ms", self.timeout_ms)
        };
        let what = if self.mode == "client" {
            "a router"
        } else {
            "the peer"
        };
        waits.then(|| {
            format!(
                "zenoh_plugin: start-up waits until this {} connects to {what} at {} ({how_long}); a second Ctrl-C exits at once",
                self.mode,
                self.endpoints.join(" or ")
            )
        })
    }
}

/// zenoh's "Unable to connect to any of [Single(tcp/…)]!" (or "… . Timeout!") in plain
/// words, with what would be right; `None` for any other error.
pub(crate) fn unreachable(zenoh_says: &str) -> Option<String> {
    let rest = zenoh_says
        .trim()
        .strip_prefix("Unable to connect to any of [")?;
    let (list, after) = rest.rsplit_once(']')?;
    let endpoints: Vec<&str> = list
        .split([',', '(', ')', '[', ']'])
        .map(str::trim)
        .filter(|s| !s.is_empty() && *s != "Single" && *s != "OneOf")
        .collect();
    let within = if after.contains("Timeout") {
        " within connect.timeout_ms"
    } else {
        ""
    };
    Some(format!(
        "cannot connect to {}{within}: nothing accepted a connection there. Start the process that listens there first (a router, for a client: `config/zenoh_router.yaml` runs one), or have this one wait for it with `connect: {{ timeout_ms: -1 }}` in the native config",
        endpoints.join(" or ")
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn connect(json5: &str) -> Connect {
        let mut config = zenoh::Config::default();
        let value: serde_json::Value = serde_json::from_str(json5).unwrap();
        for (key, v) in value.as_object().unwrap() {
            config.insert_json5(key, &v.to_string()).unwrap();
        }
        Connect::of(&config)
    }

    #[test]
    fn a_client_waits_only_with_a_timeout_and_a_peer_only_when_it_must_connect() {
        let c = connect(r#"{"mode": "client", "connect": {"endpoints": ["tcp/127.0.0.1:7449"]}}"#);
        assert_eq!(c.mode, "client");
        assert_eq!(
            c.waiting(),
            None,
            "a client's default timeout is 0: one try"
        );
        let c = connect(
            r#"{"mode": "client", "connect": {"endpoints": ["tcp/127.0.0.1:7449"], "timeout_ms": -1}}"#,
        );
        assert_eq!(
            c.waiting().as_deref(),
            Some("zenoh_plugin: start-up waits until this client connects to a router at tcp/127.0.0.1:7449 (without end: connect.timeout_ms is -1); a second Ctrl-C exits at once")
        );
        // One value a mode: the client's.
        let c = connect(
            r#"{"mode": "client", "connect": {"endpoints": {"client": ["tcp/10.0.0.1:7447", "tcp/10.0.0.2:7447"]}, "timeout_ms": {"peer": -1, "client": 5000}}}"#,
        );
        assert!(
            c.waiting()
                .unwrap()
                .contains("at tcp/10.0.0.1:7447 or tcp/10.0.0.2:7447 (up to 5000 ms"),
            "{c:?}"
        );
        // A peer connects in the background unless exit_on_failure says it must connect.
        let peer = r#"{"mode": "peer", "connect": {"endpoints": ["tcp/127.0.0.1:7448"]}}"#;
        assert_eq!(connect(peer).waiting(), None);
        let c = connect(
            r#"{"mode": "peer", "connect": {"endpoints": ["tcp/127.0.0.1:7448"], "exit_on_failure": true}}"#,
        );
        assert!(c
            .waiting()
            .unwrap()
            .contains("this peer connects to the peer at tcp/127.0.0.1:7448 (without end"));
        // Nothing to connect to: nothing to wait for.
        assert_eq!(
            connect(r#"{"mode": "client", "connect": {"timeout_ms": -1}}"#).waiting(),
            None
        );
        assert_eq!(Connect::of(&zenoh::Config::default()).mode, "peer");
    }

    #[test]
    fn nothing_answering_reads_as_the_endpoints_and_what_to_do() {
        let said =
            unreachable("Unable to connect to any of [Single(tcp/127.0.0.1:17450)]! ").unwrap();
        assert!(
            said.starts_with("cannot connect to tcp/127.0.0.1:17450: nothing accepted a connection there. Start the process"),
            "{said}"
        );
        let said = unreachable(
            "Unable to connect to any of [Single(tcp/10.0.0.1:7447), OneOf([tcp/10.0.0.2:7447, tcp/10.0.0.3:7447])]. Timeout!",
        )
        .unwrap();
        assert!(
            said.starts_with("cannot connect to tcp/10.0.0.1:7447 or tcp/10.0.0.2:7447 or tcp/10.0.0.3:7447 within connect.timeout_ms: "),
            "{said}"
        );
        assert_eq!(unreachable("Address already in use"), None);
    }
}
