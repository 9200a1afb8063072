//! What opening the session waits for (a router in client mode, or a peer that must answer),
//! said before it waits; endpoints no wait can mend, refused before it; and why nothing
//! answered, said when it fails.
//!
//! zenoh 1.10 opens a `client` session only once it has connected to one of its
//! `connect.endpoints`: with `connect.timeout_ms` 0 (a client's default) it tries once and
//! fails, with -1 it tries until it connects, however long that is. A peer or router
//! waits the same way only with `connect.exit_on_failure: true`; otherwise it goes on and
//! connects in the background.

use std::net::{TcpStream, ToSocketAddrs};
use std::time::Duration;

/// How the native config has the session listen and connect, for the mode it runs in.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Connect {
    /// `peer`, `client` or `router`.
    pub(crate) mode: String,
    listen: Vec<String>,
    endpoints: Vec<String>,
    /// `connect.timeout_ms`: 0 once, -1 without end, else that long.
    timeout_ms: i64,
    exit_on_failure: bool,
}

impl Connect {
    /// Reads `mode`, `listen` and `connect` of `config`, with zenoh 1.10's defaults for
    /// the mode where the config is silent (each key may hold one value or one a mode).
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
        let list = |key: &str| -> Vec<String> {
            of_mode(key)
                .and_then(|v| serde_json::from_value(v).ok())
                .unwrap_or_default()
        };
        let client = mode == "client";
        Connect {
            listen: list("listen/endpoints"),
            endpoints: list("connect/endpoints"),
            timeout_ms: of_mode("connect/timeout_ms")
                .and_then(|v| v.as_i64())
                .unwrap_or(if client { 0 } else { -1 }),
            exit_on_failure: of_mode("connect/exit_on_failure")
                .and_then(|v| v.as_bool())
                .unwrap_or(client),
            mode,
        }
    }

    /// An endpoint no wait can mend: a protocol this build lacks, or an address without a
    /// port (zenoh says only "invalid socket address", or waits forever for it).
    pub(crate) fn check(&self) -> Result<(), String> {
        let listen = self.listen.iter().map(|e| ("listen", e));
        let connect = self.endpoints.iter().map(|e| ("connect", e));
        for (key, endpoint) in listen.chain(connect) {
            if let Err(why) = address_of(endpoint, key == "listen") {
                return Err(format!("{key} endpoint '{endpoint}' {why}"));
            }
        }
        Ok(())
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

    /// zenoh's "Unable to connect to any of [Single(tcp/…)]!" (or "… . Timeout!") as why
    /// each endpoint did not answer (a name that does not resolve, or what a TCP
    /// connection to it says now), with what would be right; `None` for any other error.
    pub(crate) fn unreachable(&self, zenoh_says: &str) -> Option<String> {
        let after = zenoh_says
            .trim()
            .strip_prefix("Unable to connect to any of [")
            .filter(|_| !self.endpoints.is_empty())?;
        let within = if after.contains("Timeout") {
            " within connect.timeout_ms"
        } else {
            ""
        };
        let (mut unresolved, mut absent) = (false, false);
        let reasons: Vec<String> = self
            .endpoints
            .iter()
            .map(|endpoint| match address_of(endpoint, false) {
                Ok(address) => match why_no_answer(address) {
                    Answer::Unresolved(why) => {
                        unresolved = true;
                        format!("{endpoint}: the name does not resolve ({why})")
                    }
                    Answer::Refused(why) => {
                        absent = true;
                        format!("{endpoint}: {why}")
                    }
                    Answer::Answers => format!(
                        "{endpoint}: it takes a connection now, but did not answer as zenoh"
                    ),
                },
                Err(why) => format!("{endpoint} {why}"),
            })
            .collect();
        // Where every endpoint answered, what each says is the advice.
        let advice = if unresolved {
            ". Check the host names in the native config's connect.endpoints"
        } else if absent {
            ". Start the process that listens there first (a router, for a client: `config/zenoh_router.yaml` runs one), or have this one wait for it with `connect: { timeout_ms: -1 }` in the native config"
        } else {
            ""
        };
        Some(format!(
            "cannot connect{within}: {}{advice}",
            reasons.join("; ")
        ))
    }
}

/// Where an endpoint is: `host:port` of a `tcp/` endpoint, or the socket file of a
/// `unixsock-stream/` one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Address<'a> {
    Tcp(&'a str),
    Unix(&'a str),
}

/// The protocols this build links, as a user writes an endpoint of each.
const PROTOCOLS: &str = "tcp/<host>:<port> or unixsock-stream/<socket file>";

/// The address of endpoint `endpoint` (metadata and config after `?` or `#` aside), or what
/// is wrong with it. Port 0 is for listening only.
fn address_of(endpoint: &str, listen: bool) -> Result<Address<'_>, String> {
    let bare = endpoint.split(['?', '#']).next().unwrap_or(endpoint);
    let (protocol, address) = bare.split_once('/').unwrap_or((bare, ""));
    match protocol {
        "tcp" => {}
        "tls" => {
            return Err(format!(
                "uses protocol 'tls', which this build leaves out: zenoh 1.10.2's TLS link reads and writes one TLS stream from two tasks at once (zenoh issue #2557), and under load its links stall; write {PROTOCOLS}, and encrypt below zenoh (a VPN such as WireGuard; docs/zenoh.md#tls)"
            ))
        }
        // zenoh itself refuses an endpoint without an address.
        "unixsock-stream" => return Ok(Address::Unix(address)),
        _ => {
            return Err(format!(
                "uses protocol '{protocol}': this build has zenoh's TCP and unix-socket transports alone; write {PROTOCOLS}"
            ))
        }
    }
    let port = address
        .rsplit_once(':')
        .filter(|(host, _)| !host.is_empty() && !host.ends_with(':'))
        .map(|(_, port)| port);
    match port.map(str::parse::<u16>) {
        Some(Ok(0)) if !listen => Err("has port 0, which only a listener may use".into()),
        Some(Ok(_)) => Ok(Address::Tcp(address)),
        Some(Err(_)) | None => Err(format!(
            "has no valid port (1 to 65535); write e.g. {protocol}/{}:7447",
            host_of(address)
        )),
    }
}

/// The host of a TCP address whose port is missing or wrong, as a hint writes it: an IPv6
/// address in brackets (`[::1]`), else what comes before the last `:`.
fn host_of(address: &str) -> String {
    if address.starts_with('[') {
        return address
            .find(']')
            .map_or_else(|| format!("{address}]"), |end| address[..=end].to_owned());
    }
    match address.rsplit_once(':') {
        // Two colons or more: an IPv6 address without its brackets.
        Some((host, _)) if host.contains(':') => format!("[{address}]"),
        Some((host, _)) => host.to_owned(),
        None => address.to_owned(),
    }
}

enum Answer {
    Unresolved(String),
    Refused(String),
    Answers,
}

/// What a connection to `address` says now (TCP: at most 1 s).
fn why_no_answer(address: Address<'_>) -> Answer {
    let address = match address {
        Address::Unix(path) => {
            return match std::os::unix::net::UnixStream::connect(path) {
                Ok(_) => Answer::Answers,
                Err(e) => Answer::Refused(e.to_string()),
            }
        }
        Address::Tcp(address) => address,
    };
    let addrs = match address.to_socket_addrs() {
        Ok(a) => a.collect::<Vec<_>>(),
        Err(e) => return Answer::Unresolved(e.to_string()),
    };
    let mut last = String::from("no address");
    for a in addrs {
        match TcpStream::connect_timeout(&a, Duration::from_secs(1)) {
            Ok(_) => return Answer::Answers,
            Err(e) => last = e.to_string(),
        }
    }
    Answer::Refused(last)
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
        // zenoh's defaults (AimRT's native config sets no endpoints) pass the check.
        let defaults = Connect::of(&zenoh::Config::default());
        assert_eq!(defaults.mode, "peer");
        assert_eq!(defaults.check(), Ok(()));
    }

    #[test]
    fn endpoints_no_wait_can_mend_are_refused_before_opening() {
        let check = |json: &str| connect(json).check();
        assert_eq!(
            check(
                r#"{"mode": "peer", "listen": {"endpoints": ["tcp/127.0.0.1:0", "tcp/[::1]:7447#iface=lo", "unixsock-stream//tmp/robot.sock"]}, "connect": {"endpoints": ["tcp/robot.local:7447?prio=1", "unixsock-stream//tmp/other.sock"]}}"#
            ),
            Ok(())
        );
        for (json, says) in [
            (
                r#"{"mode": "client", "connect": {"endpoints": ["tcp/127.0.0.1"]}}"#,
                "connect endpoint 'tcp/127.0.0.1' has no valid port (1 to 65535); write e.g. tcp/127.0.0.1:7447",
            ),
            (
                r#"{"mode": "client", "connect": {"endpoints": ["tcp/127.0.0.1:99999"]}}"#,
                "connect endpoint 'tcp/127.0.0.1:99999' has no valid port (1 to 65535); write e.g. tcp/127.0.0.1:7447",
            ),
            (
                r#"{"mode": "client", "connect": {"endpoints": ["tcp/[::1]"]}}"#,
                "connect endpoint 'tcp/[::1]' has no valid port (1 to 65535); write e.g. tcp/[::1]:7447",
            ),
            (
                r#"{"mode": "client", "connect": {"endpoints": ["tcp/[fe80::1]:x?iface=eth0"]}}"#,
                "connect endpoint 'tcp/[fe80::1]:x?iface=eth0' has no valid port (1 to 65535); write e.g. tcp/[fe80::1]:7447",
            ),
            (
                r#"{"mode": "client", "connect": {"endpoints": ["tcp/fe80::1"]}}"#,
                "connect endpoint 'tcp/fe80::1' has no valid port (1 to 65535); write e.g. tcp/[fe80::1]:7447",
            ),
            (
                r#"{"mode": "client", "connect": {"endpoints": ["tcp/robot"]}}"#,
                "connect endpoint 'tcp/robot' has no valid port (1 to 65535); write e.g. tcp/robot:7447",
            ),
            (
                r#"{"mode": "client", "connect": {"endpoints": ["tcp/127.0.0.1:0"]}}"#,
                "connect endpoint 'tcp/127.0.0.1:0' has port 0, which only a listener may use",
            ),
            (
                r#"{"mode": "peer", "listen": {"endpoints": ["udp/127.0.0.1:7447"]}}"#,
                "listen endpoint 'udp/127.0.0.1:7447' uses protocol 'udp': this build has zenoh's TCP and unix-socket transports alone; write tcp/<host>:<port> or unixsock-stream/<socket file>",
            ),
        ] {
            assert_eq!(check(json), Err(says.to_owned()), "{json}");
        }
    }

    #[test]
    fn nothing_answering_reads_as_why_each_endpoint_did_not_and_what_to_do() {
        // A port nothing listens on: bound, then closed.
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .unwrap()
            .port();
        // What a client of `endpoint` says when zenoh could not connect to it.
        let said_of = |endpoint: &str| {
            connect(&format!(
                r#"{{"mode": "client", "connect": {{"endpoints": ["{endpoint}"]}}}}"#
            ))
            .unreachable(&format!(
                "Unable to connect to any of [Single({endpoint})]!"
            ))
            .unwrap()
        };
        let said = said_of(&format!("tcp/127.0.0.1:{port}"));
        assert!(
            said.starts_with(&format!("cannot connect: tcp/127.0.0.1:{port}: Connection refused (os error 111). Start the process that listens there first")),
            "{said}"
        );
        let c = connect(
            r#"{"mode": "client", "connect": {"endpoints": ["tcp/no-such-host.invalid:7447"]}}"#,
        );
        let said = c
            .unreachable(
                "Unable to connect to any of [Single(tcp/no-such-host.invalid:7447)]. Timeout!",
            )
            .unwrap();
        assert!(
            said.starts_with("cannot connect within connect.timeout_ms: tcp/no-such-host.invalid:7447: the name does not resolve (")
                && said.ends_with("). Check the host names in the native config's connect.endpoints"),
            "{said}"
        );
        assert_eq!(c.unreachable("Address already in use"), None);
        // A socket file nobody listens on: why, as for TCP.
        let said = said_of("unixsock-stream//nonexistent/robot.sock");
        assert!(
            said.starts_with("cannot connect: unixsock-stream//nonexistent/robot.sock: No such file or directory (os error 2). Start the process that listens there first"),
            "{said}"
        );
        // Something listens there but is not zenoh: no advice to start it.
        let listening = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let port = listening.local_addr().unwrap().port();
        assert_eq!(
            said_of(&format!("tcp/127.0.0.1:{port}")),
            format!("cannot connect: tcp/127.0.0.1:{port}: it takes a connection now, but did not answer as zenoh")
        );
        // A tls/ endpoint is refused before the session opens, saying why.
        let tls = connect(r#"{"mode": "peer", "listen": {"endpoints": ["tls/0.0.0.0:7447"]}}"#);
        let said = tls.check().unwrap_err();
        assert!(
            said.starts_with("listen endpoint 'tls/0.0.0.0:7447' uses protocol 'tls', which this build leaves out: zenoh 1.10.2's TLS link")
                && said.contains("zenoh issue #2557")
                && said.ends_with("write tcp/<host>:<port> or unixsock-stream/<socket file>, and encrypt below zenoh (a VPN such as WireGuard; docs/zenoh.md#tls)"),
            "{said}"
        );
        // Endpoints found by scouting, none configured: zenoh's own words.
        let scouted = connect(r#"{"mode": "client"}"#);
        assert_eq!(
            scouted.unreachable("Unable to connect to any of [Single(tcp/10.0.0.9:7447)]!"),
            None
        );
    }

    /// The example pair's unix-socket configs load, pass the check and listen where the
    /// other connects.
    #[test]
    fn the_example_unix_socket_configs_pass_the_check() {
        let of = |side: &str| {
            let path = format!(
                "{}/../../config/zenoh_native_unix_{side}.json5",
                env!("CARGO_MANIFEST_DIR")
            );
            let config = zenoh::Config::from_file(&path).unwrap();
            let c = Connect::of(&config);
            assert_eq!(c.check(), Ok(()), "{path}");
            c
        };
        let (a, b) = (of("a"), of("b"));
        assert!(a.listen[0].starts_with("unixsock-stream//"), "{a:?}");
        assert_eq!((&a.listen, &b.listen), (&b.endpoints, &a.endpoints));
    }

    /// Every zenoh config docs/zenoh.md shows (a fragment inside `{ }`) is one zenoh 1.10
    /// loads, with endpoints that pass the check: a user copies them as they are.
    #[test]
    fn the_native_configs_zenoh_md_shows_load_and_pass_the_check() {
        let page = concat!(env!("CARGO_MANIFEST_DIR"), "/../../docs/zenoh.md");
        let page = std::fs::read_to_string(page).expect("docs/zenoh.md");
        let mut shown = 0;
        let mut block: Option<String> = None;
        for line in page.lines() {
            let fence = line.trim_start().strip_prefix("```");
            match (&mut block, fence) {
                (None, Some("json5")) => block = Some(String::new()),
                (Some(text), Some(_)) => {
                    let text = text.trim().trim_end_matches(',');
                    let text = if text.starts_with('{') || text.starts_with("//") {
                        text.to_owned()
                    } else {
                        format!("{{ {text} }}")
                    };
                    let config = zenoh::Config::from_json5(&text).unwrap_or_else(|e| {
                        panic!("zenoh.md shows a config zenoh rejects: {e}\n{text}")
                    });
                    assert_eq!(Connect::of(&config).check(), Ok(()), "{text}");
                    shown += 1;
                    block = None;
                }
                (Some(text), None) => {
                    text.push_str(line);
                    text.push('\n');
                }
                _ => {}
            }
        }
        assert!(shown >= 5, "only {shown} configs found in zenoh.md");
    }
}
