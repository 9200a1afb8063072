//! `net_plugin`: the `http` RPC backend and the `http`, `tcp` and `udp` channel backends,
//! configured like AimRT's net_plugin, in AimRT's wire formats, on hyper and tokio. This
//! crate is the plugin as an rlib; `plugins/net/so` exports it from
//! `libaimrt_net_plugin.so`.
//!
//! ```yaml
//! aimrt:
//!   plugin:
//!     plugins:
//!       - name: net_plugin
//!         path: ./target/debug/libaimrt_net_plugin.so
//!         options:
//!           thread_num: 4            # HTTP server threads (default 2)
//!           http_options:
//!             listen_ip: 127.0.0.1   # default 127.0.0.1 (loopback)
//!             listen_port: 50080     # required; 0 picks a free port (logged)
//!   rpc:
//!     backends:
//!       - type: http
//!     servers_options:
//!       - func_name: "(pb:/aimrt.protocols.time_manipulator_plugin.*)"
//!         enable_backends: [http]
//! ```
//!
//! `POST /rpc/<Service>/<Method>` with a JSON body calls the service function
//! `pb:/<Service>/<Method>`; the answer is the service's JSON with status 200. Errors are
//! JSON `{"error": "…"}` with 400 (malformed request), 404 (no such function, or not
//! enabled for `http`), 405 (not POST), 413 (body over 16 MiB), 415 (not
//! `application/json`) or 500 (the service failed). `OPTIONS` answers CORS preflight.
#![deny(unsafe_code)]

mod channel;
pub mod close;
pub mod header;
mod http;
mod http_channel;
mod http_client;
pub mod receiving;
mod tcp;
mod udp;
pub mod wire;

use aimrt_plugin_api::{Error, Plugin, PluginOptions, Registrar};
use serde::{Deserialize, Serialize};

use crate::http::{HttpBackend, HttpOptions, HttpShared};

#[derive(Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
struct NetOptions {
    #[serde(default = "default_thread_num")]
    thread_num: u32,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    http_options: Option<HttpOptions>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    tcp_options: Option<tcp::TcpOptions>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    udp_options: Option<udp::UdpOptions>,
}

fn default_thread_num() -> u32 {
    2
}

struct NetPlugin;

impl Plugin for NetPlugin {
    fn name(&self) -> &str {
        "net_plugin"
    }

    fn initialize(
        &mut self,
        registrar: &mut Registrar<'_>,
        options: &PluginOptions,
    ) -> Result<(), Error> {
        let o: NetOptions = options.get()?;
        if o.thread_num == 0 || o.thread_num > aimrt_plugin_api::MAX_THREAD_NUM {
            return Err(options.invalid(format!(
                "thread_num must be in 1 ..= {}, got {}",
                aimrt_plugin_api::MAX_THREAD_NUM,
                o.thread_num
            )));
        }
        registrar.update_options(&o)?;
        registrar.register_channel_backend(tcp::TcpChannel::new(
            o.tcp_options,
            options.location().to_owned(),
        ))?;
        registrar.register_channel_backend(udp::UdpChannel::new(
            o.udp_options,
            options.location().to_owned(),
        ))?;
        let shared = HttpShared::new(
            o.thread_num as usize,
            o.http_options,
            options.location().to_owned(),
        );
        registrar.register_channel_backend(http_channel::HttpChannel::new(shared.clone()))?;
        registrar.register_rpc_backend(HttpBackend::new(shared))
    }
}

/// How many connections may wait to be accepted on a listening socket (the kernel caps it
/// at `net.core.somaxconn`): asio's default, which AimRT's servers listen with. std's 128
/// was too few for a burst of new connections (a publisher opens one per request in
/// flight): the kernel dropped the rest's SYN, and each waited a second for it to be sent
/// again.
const LISTEN_BACKLOG: i32 = 4096;

/// A multi-threaded tokio runtime of `threads` workers named `name`, for the `what`
/// (`HTTP`, `TCP`) threads; an error when the system refuses a thread (out of threads or
/// memory).
///
/// tokio panics when it cannot spawn a worker, and when that is not the first, it then
/// waits forever for the workers it did start (tokio 1.54's `build`). The runtime is
/// therefore built on a helper thread, and an error is returned when it is not built
/// within 5 s; the helper is left behind, and start-up stops.
pub fn start_runtime(
    threads: usize,
    name: &str,
    what: &str,
) -> Result<tokio::runtime::Runtime, Error> {
    let thread_name = name.to_owned();
    let built = aimrt_plugin_api::__private::contain_on_helper(
        &format!("{name}_start"),
        RUNTIME_START_LIMIT,
        move || {
            tokio::runtime::Builder::new_multi_thread()
                .worker_threads(threads)
                .thread_name(thread_name)
                .enable_io()
                .enable_time()
                .build()
        },
    );
    let why = match built {
        Ok(Ok(runtime)) => return Ok(runtime),
        Ok(Err(e)) => e.to_string(),
        Err(e) => e.to_string(),
    };
    Err(Error::msg(format!(
        "cannot start the {what} threads ({threads} workers): {why}; the process may start no more threads (`ulimit -u`), or is out of memory"
    )))
}

/// How long [`start_runtime`] waits for tokio to start a runtime's workers (it takes
/// well under a millisecond when the system grants the threads).
const RUNTIME_START_LIMIT: std::time::Duration = std::time::Duration::from_secs(5);

/// Why `<what>_options` (`http`, `tcp`, `udp`) cannot listen on `addr`, with what would
/// be right for the kind of error, for the plugin's options at `location`.
pub(crate) fn cannot_listen(
    what: &str,
    addr: &dyn std::fmt::Display,
    e: &std::io::Error,
    location: &str,
) -> Error {
    let fix = match e.kind() {
        std::io::ErrorKind::AddrInUse => format!(
            "another socket has the port; choose another {what}_options.listen_port (0 picks a free one)"
        ),
        std::io::ErrorKind::AddrNotAvailable => format!(
            "{what}_options.listen_ip is not an address of this machine; use 127.0.0.1 (loopback), 0.0.0.0 (every interface) or one of this machine's addresses"
        ),
        std::io::ErrorKind::PermissionDenied => format!(
            "ports below 1024 need privileges; choose a {what}_options.listen_port of 1024 or more"
        ),
        _ => format!("check {what}_options.listen_ip and listen_port"),
    };
    Error::msg(format!(
        "cannot listen for {} on {addr}: {e}; {fix}, in the options of net_plugin at {location}",
        what.to_ascii_uppercase()
    ))
}

/// A non-blocking TCP listener on the first address of `addr` that takes one, with
/// `SO_REUSEADDR` (as std sets it on Unix, so a restarted server binds at once) and a
/// backlog of 4096 (asio's default, capped by `net.core.somaxconn`).
pub fn listen_tcp(addr: impl std::net::ToSocketAddrs) -> std::io::Result<std::net::TcpListener> {
    let listen = |sa: std::net::SocketAddr| -> std::io::Result<std::net::TcpListener> {
        let socket = socket2::Socket::new(
            socket2::Domain::for_address(sa),
            socket2::Type::STREAM,
            Some(socket2::Protocol::TCP),
        )?;
        socket.set_reuse_address(true)?;
        socket.bind(&sa.into())?;
        socket.listen(LISTEN_BACKLOG)?;
        socket.set_nonblocking(true)?;
        Ok(socket.into())
    };
    let mut last = None;
    for sa in addr.to_socket_addrs()? {
        match listen(sa) {
            Ok(l) => return Ok(l),
            Err(e) => last = Some(e),
        }
    }
    Err(last.unwrap_or_else(|| {
        std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            "the address resolves to no address",
        )
    }))
}

/// The plugin, as `libaimrt_net_plugin.so` exports it (`plugins/net/so`).
pub fn plugin() -> Box<dyn Plugin> {
    Box::new(NetPlugin)
}

#[cfg(test)]
mod tests {
    use std::net::TcpStream;
    use std::time::Duration;

    /// More connections than std's backlog of 128 wait to be accepted, none refused or
    /// left waiting for its SYN to be sent again.
    #[test]
    fn a_listener_holds_a_burst_of_connections_it_has_not_accepted_yet() {
        let listener = super::listen_tcp("127.0.0.1:0").unwrap();
        let addr = listener.local_addr().unwrap();
        let somaxconn: usize = std::fs::read_to_string("/proc/sys/net/core/somaxconn")
            .ok()
            .and_then(|s| s.trim().parse().ok())
            .unwrap_or(4096);
        let n = somaxconn.min(300);
        assert!(
            n > 129,
            "net.core.somaxconn is {somaxconn}: this test needs more than 129"
        );
        let open: Vec<TcpStream> = (0..n)
            .map(|i| {
                TcpStream::connect_timeout(&addr, Duration::from_millis(500))
                    .unwrap_or_else(|e| panic!("connection {i} of {n} not taken: {e}"))
            })
            .collect();
        assert_eq!(open.len(), n);
    }

    #[test]
    fn a_listener_on_a_busy_port_says_so() {
        let first = super::listen_tcp("127.0.0.1:0").unwrap();
        let err = super::listen_tcp(first.local_addr().unwrap()).unwrap_err();
        assert_eq!(err.kind(), std::io::ErrorKind::AddrInUse, "{err}");
    }
}

/// For the fuzz targets in `fuzz/`; not a stable API.
#[doc(hidden)]
pub mod __fuzz {
    pub use crate::http::{echo_host, serve_bytes};
}
