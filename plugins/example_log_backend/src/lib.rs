//! An example plugin with a log backend type (ABI 1.11; AimRT's
//! `RegisterLoggerBackendGenFunc`), exported from `libexample_log_backend_plugin.so`:
//! `udp_lines` sends each line an `aimrt.log.backends` entry admits as one UDP datagram
//! to `address` (a log collector, `nc -ul 9999`): with `format: line` (the default) the
//! line formatted with the entry's `pattern`, with `format: json` one JSON object of the
//! line's parts (`time_ns`, `level`, `module`, `thread_id`, `file`, `line`, `function`,
//! `message`). A line that cannot be sent (no route, the network is down; UDP does not
//! tell whether anybody listens) is counted as lost by the runtime, which reports the
//! losses when sending works again (`config/log_backend_plugin.yaml`, docs/logging.md).
//!
//! ```yaml
//! aimrt:
//!   plugin:
//!     plugins:
//!       - name: example_log_backend
//!         path: ./target/debug/libexample_log_backend_plugin.so
//!   log:
//!     backends:
//!       - type: udp_lines
//!         options:
//!           address: 127.0.0.1:9999
//!           format: json            # or line (the default)
//!           module_filter: "(.*)"   # read by the runtime, as for console
//! ```
#![deny(unsafe_code)]

use std::net::{SocketAddr, UdpSocket};

use aimrt_plugin_api::{
    BackendOptions, Error, LogBackend, LogEntry, Plugin, PluginOptions, Registrar,
};
use serde::{Deserialize, Serialize};

/// The largest line sent whole; a longer one is cut to it (a UDP datagram holds 65 507
/// bytes).
const MAX_DATAGRAM: usize = 65_507;

#[derive(Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
struct UdpLinesOptions {
    /// Where the datagrams go, `ip:port`.
    address: String,
    /// What a datagram holds.
    #[serde(default)]
    format: Format,
}

/// What a datagram holds.
#[derive(Debug, Default, Clone, Copy, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
enum Format {
    /// The line formatted with the entry's `pattern`.
    #[default]
    Line,
    /// The line's parts as one JSON object.
    Json,
}

/// One `udp_lines` backend: a socket bound to an ephemeral port, sending to `to`.
struct UdpLines {
    socket: UdpSocket,
    to: SocketAddr,
    format: Format,
}

impl UdpLines {
    fn open(options: &BackendOptions) -> Result<UdpLines, Error> {
        // Read and reported: `--dump_cfg_file` shows them with `format` filled in.
        let o: UdpLinesOptions = options.read()?;
        let to: SocketAddr = o.address.parse().map_err(|e| {
            options.invalid(format!(
                "address '{}' is not ip:port ({e}); write e.g. 127.0.0.1:9999",
                o.address
            ))
        })?;
        let any: SocketAddr = if to.is_ipv4() {
            ([0, 0, 0, 0], 0).into()
        } else {
            (std::net::Ipv6Addr::UNSPECIFIED, 0).into()
        };
        let socket = UdpSocket::bind(any)
            .map_err(|e| options.invalid(format!("cannot open a UDP socket: {e}")))?;
        Ok(UdpLines {
            socket,
            to,
            format: o.format,
        })
    }
}

/// `entry`'s parts as one JSON object.
fn json_of(entry: &LogEntry<'_>) -> String {
    let time_ns = entry
        .time
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX));
    serde_json::json!({
        "time_ns": time_ns,
        "level": entry.level.name(),
        "module": entry.module,
        "thread_id": entry.thread_id,
        "file": entry.file,
        "line": entry.source_line,
        "function": entry.function,
        "message": entry.message,
    })
    .to_string()
}

impl LogBackend for UdpLines {
    fn write(&mut self, entry: &LogEntry<'_>) -> Result<(), String> {
        let json;
        let line = match self.format {
            Format::Line => entry.formatted,
            Format::Json => {
                json = json_of(entry);
                &json
            }
        };
        // A JSON object cut short is no longer JSON: too long a one is refused (counted
        // as lost); a plain line is cut.
        if line.len() > MAX_DATAGRAM && matches!(self.format, Format::Json) {
            return Err(format!(
                "udp_lines: a {}-byte JSON entry does not fit one datagram ({MAX_DATAGRAM} bytes)",
                line.len()
            ));
        }
        let bytes = &line.as_bytes()[..line.len().min(MAX_DATAGRAM)];
        self.socket
            .send_to(bytes, self.to)
            .map(drop)
            .map_err(|e| format!("udp_lines cannot send to {}: {e}", self.to))
    }
}

struct ExampleLogBackend;

impl Plugin for ExampleLogBackend {
    fn name(&self) -> &str {
        "example_log_backend"
    }

    fn initialize(
        &mut self,
        registrar: &mut Registrar<'_>,
        _: &PluginOptions,
    ) -> Result<(), Error> {
        registrar.register_log_backend_type("udp_lines", UdpLines::open)
    }
}

fn plugin() -> Box<dyn Plugin> {
    Box::new(ExampleLogBackend)
}

aimrt_plugin_api::export_plugin!(plugin);
