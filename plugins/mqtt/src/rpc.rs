//! The `mqtt` RPC backend, AimRT's request/response over MQTT topics
//! ([`crate::wire`]): a client publishes a request naming its answer topic
//! (`aimrt_rpc_rsp/<client_id>/<func>`), on `aimrt_rpc_req/<func>` (any server: the servers
//! share that subscription and take turns) or `aimrt_rpc_req/<server_mqtt_id>/<func>` (one
//! server); the server answers on the topic the request names.
//!
//! Where this differs from AimRT:
//! - a request that cannot be handled is answered with its status, as AimRT; one whose
//!   bytes cannot be read is counted and logged (AimRT logs it);
//! - services run on `callback_executor_name`, else on a thread of the plugin's own,
//!   never on the connection's thread (a slow service does not hold up the connection);
//! - request ids start at a random value per process, and answers for an id no call here
//!   waits for are counted;
//! - `aimrt-to_addr` other than `mqtt://<server client_id>` is answered 2004
//!   (`CLI_INVALID_ADDR`; AimRT 2002);
//! - a call is answered `CLI_NOT_READY` when the backend has shut down before its answer
//!   came, and `TIMEOUT` at its deadline in every other case without an answer (MQTT tells
//!   no one whether a server listens).

use std::collections::{HashMap, HashSet};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, OnceLock, RwLock};

use aimrt_plugin_api::rpc::{BackendAnswer, BackendCall, BackendReply, RpcBackend};
use aimrt_plugin_api::{meta_keys, BackendOptions, Error, ExecutorRef, RpcStatus, ServiceHost};
use aimrt_wire::payload::{Request, Response};
use aimrt_wire::pending::PendingCalls;
use rumqttc::QoS;
use serde::Deserialize;

use crate::connection::{lock, qos_of, read, write, Mqtt};
use crate::wire::{request_topic, response_topic, shared_request_filter};
use crate::{check_qos, Rules};

/// The meta key naming the calling process's client id (AimRT's).
pub(crate) const KEY_FROM_CLIENT: &str = "aimrt-from_mqtt_client";

#[derive(Debug, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct ClientRule {
    func_name: String,
    #[serde(default)]
    server_mqtt_id: String,
    #[serde(default)]
    qos: Option<i64>,
}

#[derive(Debug, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct ServerRule {
    func_name: String,
    #[serde(default = "yes")]
    allow_share: bool,
    #[serde(default)]
    qos: Option<i64>,
}

fn yes() -> bool {
    true
}

#[derive(Debug, Default, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct Options {
    #[serde(default)]
    timeout_executor: String,
    #[serde(default)]
    clients_options: Vec<ClientRule>,
    #[serde(default)]
    servers_options: Vec<ServerRule>,
}

/// A function this process calls.
struct ClientFunc {
    server: String,
    qos: QoS,
    /// Where its answers come (`aimrt_rpc_rsp/<client_id>/<func>`).
    reply_to: String,
}

/// State shared with the connection's handlers.
pub(crate) struct Shared {
    mqtt: Arc<Mqtt>,
    host: OnceLock<ServiceHost>,
    /// `callback_executor_name`'s executor, when named.
    executor: OnceLock<ExecutorRef>,
    pending: PendingCalls<()>,
    /// Calls are carried (from start until shutdown).
    running: AtomicBool,
    /// The backend has shut down: requests from other processes are answered
    /// `SVR_NOT_READY` without reaching the runtime.
    stopped: AtomicBool,
    clients: RwLock<HashMap<String, Arc<ClientFunc>>>,
    /// The functions served (names without prefix).
    served: Mutex<HashSet<String>>,
}

impl Shared {
    /// Refuses calls from now on and answers those in flight `CLI_NOT_READY`.
    pub(crate) fn stop(&self) {
        self.running.store(false, Ordering::SeqCst);
        self.stopped.store(true, Ordering::SeqCst);
        self.pending.fail_where(
            |_| true,
            RpcStatus::CLI_NOT_READY,
            "the mqtt backend shut down before the answer arrived",
        );
    }
}

/// The backend.
pub(crate) struct MqttRpc {
    shared: Arc<Shared>,
    client_rules: OnceLock<Rules<(String, u8)>>,
    server_rules: OnceLock<Rules<(bool, u8)>>,
}

impl MqttRpc {
    pub(crate) fn new(mqtt: Arc<Mqtt>) -> MqttRpc {
        MqttRpc {
            shared: Arc::new(Shared {
                mqtt,
                host: OnceLock::new(),
                executor: OnceLock::new(),
                pending: PendingCalls::new("mqtt"),
                running: AtomicBool::new(false),
                stopped: AtomicBool::new(false),
                clients: RwLock::default(),
                served: Mutex::default(),
            }),
            client_rules: OnceLock::new(),
            server_rules: OnceLock::new(),
        }
    }

    /// What the plugin stops at its shutdown (also where the backend's does not come).
    pub(crate) fn shared(&self) -> Arc<Shared> {
        self.shared.clone()
    }
}

impl RpcBackend for MqttRpc {
    fn type_name(&self) -> &str {
        "mqtt"
    }

    fn init(&self, options: &BackendOptions, host: ServiceHost) -> Result<(), Error> {
        let o: Options = options.read()?;
        let where_ = options.location();
        let bad = |message: String| Error::Options {
            what: format!("mqtt backend options at {where_}"),
            message,
        };
        if !o.timeout_executor.is_empty() && host.executor(&o.timeout_executor).is_none() {
            return Err(bad(format!(
                "timeout_executor '{}' is not an executor of aimrt.executor.executors",
                o.timeout_executor
            )));
        }
        let callback = &self.shared.mqtt.callback_executor_name;
        if !callback.is_empty() {
            let Some(executor) = host.executor(callback) else {
                return Err(bad(format!(
                    "the mqtt_plugin's callback_executor_name '{callback}' is not an executor of aimrt.executor.executors"
                )));
            };
            let _ = self.shared.executor.set(executor);
        }
        let mut clients = Vec::new();
        for (i, r) in o.clients_options.into_iter().enumerate() {
            let qos = check_qos(r.qos, where_, "clients_options", i)?;
            clients.push((r.func_name, (r.server_mqtt_id, qos)));
        }
        let mut servers = Vec::new();
        for (i, r) in o.servers_options.into_iter().enumerate() {
            let qos = check_qos(r.qos, where_, "servers_options", i)?;
            servers.push((r.func_name, (r.allow_share, qos)));
        }
        let _ = self.client_rules.set(Rules::compile(
            clients,
            where_,
            "clients_options",
            "func_name",
        )?);
        let _ = self.server_rules.set(Rules::compile(
            servers,
            where_,
            "servers_options",
            "func_name",
        )?);
        let _ = self.shared.host.set(host);
        Ok(())
    }

    fn start(&self) -> Result<(), Error> {
        self.shared.mqtt.wait_subscribed();
        self.shared.running.store(true, Ordering::SeqCst);
        Ok(())
    }

    fn shutdown(&self) {
        self.shared.stop();
    }

    fn register_service_func(&self, func: &str) -> Result<(), Error> {
        let short = aimrt_wire::name_without_prefix(func);
        // Several modules of this process may serve one function: the runtime hands each
        // request to one of them, so one subscription serves them all.
        if !lock(&self.shared.served).insert(short.to_owned()) {
            return Ok(());
        }
        let (allow_share, qos) = self
            .server_rules
            .get()
            .and_then(|r| r.first(&[func, short]).copied())
            .unwrap_or((true, 2));
        let qos = qos_of(qos);
        let mqtt = &self.shared.mqtt;
        let handler = {
            let shared = self.shared.clone();
            let func = func.to_owned();
            Arc::new(move |bytes: &bytes::Bytes| serve(&shared, &func, qos, bytes))
        };
        if allow_share {
            mqtt.listen(
                shared_request_filter(func),
                request_topic(func, ""),
                qos,
                handler.clone(),
            );
        }
        let own = request_topic(func, &mqtt.client_id);
        mqtt.listen(own.clone(), own, qos, handler);
        tracing::info!(target: "aimrt", "Register mqtt handle for rpc server, func '{func}', allow_share: {allow_share}");
        Ok(())
    }

    fn register_client_func(&self, func: &str) -> Result<(), Error> {
        if read(&self.shared.clients).contains_key(func) {
            return Ok(());
        }
        let short = aimrt_wire::name_without_prefix(func);
        let (server, qos) = self
            .client_rules
            .get()
            .and_then(|r| r.first(&[func, short]).cloned())
            .unwrap_or((String::new(), 2));
        let mqtt = &self.shared.mqtt;
        let reply_to = response_topic(&mqtt.client_id, func);
        if reply_to.len() > 255 {
            return Err(Error::msg(format!(
                "Too long mqtt topic name: {reply_to} ({} bytes; a request names it in at most 255)",
                reply_to.len()
            )));
        }
        let qos = qos_of(qos);
        let shared = self.shared.clone();
        mqtt.listen(
            reply_to.clone(),
            reply_to.clone(),
            qos,
            Arc::new(move |bytes: &bytes::Bytes| answer(&shared, bytes)),
        );
        write(&self.shared.clients).insert(
            func.to_owned(),
            Arc::new(ClientFunc {
                server,
                qos,
                reply_to,
            }),
        );
        Ok(())
    }

    fn invoke(&self, call: BackendCall, reply: BackendReply) {
        let mqtt = &self.shared.mqtt;
        if !self.shared.running.load(Ordering::SeqCst) {
            return reply.send(BackendAnswer::fail(
                RpcStatus::CLI_NOT_READY,
                "the mqtt backend is not running",
            ));
        }
        let client = read(&self.shared.clients).get(&call.func).cloned();
        let Some(client) = client else {
            return reply.send(BackendAnswer::fail(
                RpcStatus::CLI_FUNC_NOT_REGISTERED,
                format!(
                    "'{}' was not registered as a mqtt client function",
                    call.func
                ),
            ));
        };
        let server = match call.meta(meta_keys::TO_ADDR).filter(|a| !a.is_empty()) {
            None => client.server.as_str(),
            Some(addr) => match addr.strip_prefix("mqtt://").filter(|s| !s.is_empty()) {
                Some(id) => id.trim_end_matches('/'),
                None => {
                    return reply.send(BackendAnswer::fail(
                        RpcStatus::CLI_INVALID_ADDR,
                        format!("aimrt-to_addr '{addr}' is not mqtt://<server client_id>"),
                    ))
                }
            },
        };
        let topic = request_topic(&call.func, server);
        let mut meta: Vec<(String, String)> = call
            .meta_pairs()
            .filter(|(k, _)| *k != KEY_FROM_CLIENT)
            .map(|(k, v)| (k.to_owned(), v.to_owned()))
            .collect();
        meta.push((KEY_FROM_CLIENT.to_owned(), mqtt.client_id.clone()));
        let pending = &self.shared.pending;
        let id = pending.insert(reply, call.timeout, ());
        let request = Request {
            serialization_type: call.serialization_type().unwrap_or("pb").to_owned(),
            reply_to: client.reply_to.clone(),
            req_id: id.to_le_bytes(),
            meta,
            body: call.body,
        };
        let mut bytes = Vec::new();
        if let Err(e) = request.write_to(&mut bytes) {
            mqtt.stats.refused.fetch_add(1, Ordering::Relaxed);
            return pending.fail(
                id,
                RpcStatus::CLI_INVALID_CONTEXT,
                format!("the request cannot be laid out: {e}"),
            );
        }
        if let Err(why) = mqtt.publish(&topic, client.qos, bytes) {
            pending.fail(id, RpcStatus::CLI_SEND_REQ_FAILED, why);
        }
    }
}

/// One answer heard on this process's answer topic.
fn answer(shared: &Shared, bytes: &[u8]) {
    let mqtt = &shared.mqtt;
    let rsp = match Response::read(bytes) {
        Ok(r) => r,
        Err(e) => {
            mqtt.stats.malformed.fetch_add(1, Ordering::Relaxed);
            mqtt.warn(format_args!(
                "Handle mqtt rpc msg failed: a {}-byte answer is malformed: {e}",
                bytes.len()
            ));
            return;
        }
    };
    let id = u32::from_le_bytes(rsp.req_id);
    if !shared.pending.answer(rsp) {
        // A call this process gave up on, or a forged answer.
        mqtt.stats.unknown_ids.fetch_add(1, Ordering::Relaxed);
        tracing::trace!(target: "aimrt", "Can not get req id {id} from recorder.");
    }
}

/// One request heard for `func`: handed to the runtime on the callback executor (or a
/// thread of the plugin's), answered on the topic it names.
fn serve(shared: &Arc<Shared>, func: &str, qos: QoS, bytes: &[u8]) {
    let mqtt = &shared.mqtt;
    let req = match Request::read(bytes) {
        Ok(r) => r,
        Err(e) => {
            mqtt.stats.malformed.fetch_add(1, Ordering::Relaxed);
            mqtt.warn(format_args!(
                "Handle mqtt rpc msg failed: a {}-byte request for '{func}' is malformed: {e}",
                bytes.len()
            ));
            return;
        }
    };
    let (call, answering) = req.into_call(func);
    let answering = Arc::new(answering);
    let refuse = |status: RpcStatus| {
        let rsp = answering.status(status, Vec::new());
        send_answer(mqtt, &answering.reply_to, qos, &rsp);
    };
    let host = match shared.host.get() {
        Some(host) if !shared.stopped.load(Ordering::SeqCst) => *host,
        _ => return refuse(RpcStatus::SVR_NOT_READY),
    };
    let work = {
        let shared = shared.clone();
        let answering = answering.clone();
        move || {
            host.call(&call, move |a| {
                let rsp = answering.response(a);
                send_answer(&shared.mqtt, &answering.reply_to, qos, &rsp);
            });
        }
    };
    let refused = match shared.executor.get() {
        Some(executor) => executor.execute(work).err().map(|e| e.to_string()),
        None => {
            drop(mqtt.serve.spawn_blocking(work));
            None
        }
    };
    if let Some(why) = refused {
        mqtt.warn(format_args!(
            "the callback executor refused a request for '{func}': {why}"
        ));
        refuse(RpcStatus::SVR_BACKEND_INTERNAL_ERROR);
    }
}

/// Sends `rsp` to `topic`. An answer over `max_pkg_size_k` goes as `SVR_UNKNOWN` (AimRT's
/// code for it) without its body, so the caller learns of it before its deadline.
fn send_answer(mqtt: &Mqtt, topic: &str, qos: QoS, rsp: &Response) {
    if rsp.encoded_len() > mqtt.max_payload {
        mqtt.stats.refused.fetch_add(1, Ordering::Relaxed);
        mqtt.warn(format_args!(
            "Mqtt publish failed, pkg is too large, limit {} bytes, actual {} bytes: the answer to '{topic}' goes as SVR_UNKNOWN",
            mqtt.max_payload,
            rsp.encoded_len()
        ));
        let status_only = Response {
            serialization_type: rsp.serialization_type.clone(),
            req_id: rsp.req_id,
            status: RpcStatus::SVR_UNKNOWN.code(),
            body: Vec::new(),
        };
        return send_answer(mqtt, topic, qos, &status_only);
    }
    let mut bytes = Vec::new();
    let sent = rsp
        .write_to(&mut bytes)
        .map_err(|e| {
            mqtt.stats.refused.fetch_add(1, Ordering::Relaxed);
            format!("an answer cannot be laid out: {e}")
        })
        .and_then(|()| mqtt.publish(topic, qos, bytes));
    if let Err(why) = sent {
        mqtt.warn(format_args!("the answer to '{topic}' is not sent: {why}"));
    }
}

#[cfg(test)]
mod tests {
    use std::sync::mpsc;
    use std::time::Duration;

    use super::*;
    use crate::connection::tests::open;
    use crate::test_broker::Broker;

    #[test]
    fn an_answer_over_max_pkg_size_k_goes_as_svr_unknown_and_one_that_fits_goes_whole() {
        let broker = Broker::start("127.0.0.1:0").unwrap();
        let server = open(&broker, "server", 1);
        let client = open(&broker, "client", 1024);
        let (tx, rx) = mpsc::channel();
        client.listen(
            "answers".into(),
            "answers".into(),
            QoS::AtMostOnce,
            Arc::new(move |b: &bytes::Bytes| {
                let _ = tx.send(b.to_vec());
            }),
        );
        client.wait_subscribed();
        server.wait_subscribed();
        let answer = |body: Vec<u8>| Response {
            serialization_type: "pb".into(),
            req_id: 7u32.to_le_bytes(),
            status: 0,
            body,
        };
        let heard = || {
            let bytes = rx.recv_timeout(Duration::from_secs(10)).expect("an answer");
            Response::read(&bytes).unwrap()
        };
        send_answer(&server, "answers", QoS::AtMostOnce, &answer(vec![0; 2048]));
        let got = heard();
        assert_eq!(got.status, RpcStatus::SVR_UNKNOWN.code());
        assert!(got.body.is_empty());
        assert_eq!(got.req_id, 7u32.to_le_bytes());
        let fits = answer(vec![1; 1000]);
        send_answer(&server, "answers", QoS::AtMostOnce, &fits);
        assert_eq!(heard(), fits);
        assert_eq!(server.stats.refused.load(Ordering::Relaxed), 1);
        server.close();
        client.close();
    }
}
