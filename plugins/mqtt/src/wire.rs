//! AimRT mqtt_plugin's topics; its payloads are [`aimrt_wire::payload`]'s, with no length
//! prefix (the MQTT packet says the length).
//!
//! | what | topic |
//! |------|-------|
//! | a channel's messages | `/channel/<UrlEncode(topic)>/<UrlEncode(type)>` |
//! | requests to any server of a function | `aimrt_rpc_req/<UrlEncode(name without prefix)>`, heard as `$share/aimrt/aimrt_rpc_req/…` |
//! | requests to one server | `aimrt_rpc_req/<UrlEncode(server client_id)>/<UrlEncode(name)>` |
//! | answers to one client | `aimrt_rpc_rsp/<UrlEncode(client client_id)>/<UrlEncode(name)>` |

use aimrt_wire::{name_without_prefix, url_encode};

/// The topic of a channel topic and message type.
///
/// ```
/// assert_eq!(
///     aimrt_mqtt::wire::channel_topic("test_topic", "pb:aimrt.protocols.example.ExampleEventMsg"),
///     "/channel/test_topic/pb%3Aaimrt.protocols.example.ExampleEventMsg"
/// );
/// ```
pub fn channel_topic(topic: &str, msg_type: &str) -> String {
    format!("/channel/{}/{}", url_encode(topic), url_encode(msg_type))
}

/// The topic requests of `func` go to: to any server (`server` empty; each request goes
/// to one of them), or to the server whose client_id is `server`.
///
/// ```
/// const F: &str = "pb:/aimrt.protocols.example.ExampleService/GetFooData";
/// assert_eq!(
///     aimrt_mqtt::wire::request_topic(F, ""),
///     "aimrt_rpc_req/%2Faimrt.protocols.example.ExampleService%2FGetFooData"
/// );
/// assert_eq!(
///     aimrt_mqtt::wire::request_topic(F, "server_a"),
///     "aimrt_rpc_req/server_a/%2Faimrt.protocols.example.ExampleService%2FGetFooData"
/// );
/// ```
pub fn request_topic(func: &str, server: &str) -> String {
    let name = url_encode(name_without_prefix(func));
    if server.is_empty() {
        format!("aimrt_rpc_req/{name}")
    } else {
        format!("aimrt_rpc_req/{}/{name}", url_encode(server))
    }
}

/// The shared subscription through which the servers of `func` take turns with the
/// requests sent to any of them (`allow_share`).
pub fn shared_request_filter(func: &str) -> String {
    format!("$share/aimrt/{}", request_topic(func, ""))
}

/// The topic a client hears its answers of `func` on.
///
/// ```
/// assert_eq!(
///     aimrt_mqtt::wire::response_topic("cli", "pb:/a.S/M"),
///     "aimrt_rpc_rsp/cli/%2Fa.S%2FM"
/// );
/// ```
pub fn response_topic(client_id: &str, func: &str) -> String {
    format!(
        "aimrt_rpc_rsp/{}/{}",
        url_encode(client_id),
        url_encode(name_without_prefix(func))
    )
}

/// Reads `data` every way a payload from the broker is read: as a channel message, an
/// RPC request and an RPC answer. What reads must write back to exactly `data`, else this
/// panics. For the fuzz target `mqtt_wire` and the tests, which hold every input to it.
#[doc(hidden)]
pub fn read_any(data: &[u8]) {
    use aimrt_wire::payload::{put_channel_header, ChannelView, Request, Response};
    if let Ok(v) = ChannelView::read(data) {
        let mut again = Vec::new();
        put_channel_header(&mut again, v.serialization_type, v.meta.iter())
            .expect("what was read fits the layout");
        again.extend_from_slice(v.message);
        assert_eq!(again, data);
    }
    if let Ok(r) = Request::read(data) {
        let mut again = Vec::new();
        r.write_to(&mut again)
            .expect("what was read fits the layout");
        assert_eq!(again, data);
    }
    if let Ok(r) = Response::read(data) {
        let mut again = Vec::new();
        r.write_to(&mut again)
            .expect("what was read fits the layout");
        assert_eq!(again, data);
    }
}
