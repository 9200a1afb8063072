//! Server filters around a plugin's own service (bytes in, bytes out), for a call a
//! backend received: as in AimRT, whose plugins register their services like modules, a
//! `servers_options` rule's `enable_filters` covers them too. The filters see the request
//! and the response as messages of type [`BYTES`], which encode only in the call's
//! serialization type (`json` shows as JSON in `debug_log`).

use std::sync::Arc;

use aimrt_plugin_api::channel::{Message, MessageError};
use aimrt_plugin_api::ffi::{MetaPair, RawMessage, RawRpcReply, RawService, ReplyParts};
use aimrt_plugin_api::rpc::{BackendAnswer, BackendReply, CallFilterSide, CallView};
use aimrt_plugin_api::{Responder, RpcStatus};

use super::calls::{nanos, server_meta, RpcRegistry};
use super::filter::{RpcChain, Subject};

/// The type name filters see for a plugin service's request and response.
pub(crate) const BYTES: &str = "bytes";

/// A plugin service's request or response: its bytes in the call's serialization type.
struct ServiceBytes {
    format: String,
    bytes: Vec<u8>,
}

impl Message for ServiceBytes {
    fn type_name() -> &'static str {
        BYTES
    }
    fn formats() -> &'static [&'static str] {
        &["json", "pb"]
    }
    fn encode(&self, format: &str) -> Result<Vec<u8>, MessageError> {
        if format == self.format {
            return Ok(self.bytes.clone());
        }
        Err(MessageError::UnsupportedFormat {
            type_name: BYTES.to_owned(),
            format: format.to_owned(),
            supported: self.format.clone(),
        })
    }
    fn decode(format: &str, bytes: &[u8]) -> Result<Self, MessageError> {
        Ok(ServiceBytes {
            format: format.to_owned(),
            bytes: bytes.to_vec(),
        })
    }
}

fn message(format: &str, bytes: Vec<u8>) -> RawMessage {
    RawMessage::new(Arc::new(ServiceBytes {
        format: format.to_owned(),
        bytes,
    }))
}

/// The service's response bytes back out of the message that carried them through the
/// filters (without a copy when no filter kept a reference to it).
fn body_of(rsp: RawMessage, format: &str) -> Result<Vec<u8>, String> {
    match rsp.downcast::<ServiceBytes>() {
        Ok(bytes) => match Arc::try_unwrap(bytes) {
            Ok(owned) => Ok(owned.bytes),
            Err(shared) => Ok(shared.bytes.clone()),
        },
        Err(other) => other.encode(format),
    }
}

/// A plugin's service as a backend reaches it.
pub(crate) struct PluginServer<'a> {
    pub(crate) func: &'a str,
    /// The plugin that registered it.
    pub(crate) owner: &'a str,
    pub(crate) service: &'a RawService,
    /// Its server filters (not empty).
    pub(crate) filters: &'a RpcChain,
}

impl RpcRegistry {
    /// Serves `call`, which `backend` received for `server`, with its filters around it.
    /// A call a filter stops is answered with the filter's status and logged (rate-limited).
    pub(crate) fn serve_plugin(
        &self,
        backend: &str,
        server: &PluginServer<'_>,
        call: CallView<'_>,
        reply: BackendReply,
    ) {
        let format = call
            .serialization_type()
            .filter(|f| !f.is_empty())
            .unwrap_or("json")
            .to_owned();
        let meta: Vec<MetaPair<'_>> = server_meta(call.pairs(), &format, server.func, backend);
        let req = message(&format, call.body.to_vec());
        let encode_in = format.clone();
        // The answer, as it comes out of the outermost filter.
        let answered = RawRpcReply::new(move |parts: ReplyParts| {
            reply.send(match (parts.status.is_ok(), parts.rsp) {
                (true, Some(rsp)) => match body_of(rsp, &encode_in) {
                    Ok(body) => BackendAnswer::ok(body),
                    Err(e) => BackendAnswer::fail(RpcStatus::SVR_SERIALIZATION_FAILED, e),
                },
                (true, None) => BackendAnswer::ok(Vec::new()),
                (false, _) => BackendAnswer::fail(parts.status, parts.detail),
            })
        });
        let func = server.func;
        let subject = Subject {
            side: CallFilterSide::Server,
            func,
            module: server.owner,
            // The caller's deadline where the wire carries it, else none (AimRT's 0).
            timeout_ns: call.timeout.map_or(0, nanos),
            req: &req,
            refuse: &|reply: RawRpcReply, status, detail: String| {
                self.log_failure(
                    status,
                    &format!("call of '{func}' failed on the server: {detail}"),
                );
                reply.complete(status, None, &[], &detail)
            },
        };
        server
            .filters
            .run(&subject, &meta, answered, &mut |_, reply: RawRpcReply| {
                let answer_in = format.clone();
                let responder = Responder::from_fn(move |r| match r {
                    Ok(bytes) => {
                        reply.complete(RpcStatus::OK, Some(message(&answer_in, bytes)), &[], "")
                    }
                    Err(e) => reply.complete(e.rpc_status(), None, &[], e.message()),
                });
                server.service.call(&format, call.body, responder);
            });
    }
}
