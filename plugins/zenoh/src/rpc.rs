//! The `zenoh` RPC backend, AimRT's request/response over two pub/sub keys per function:
//! a client puts requests on `req/P` and hears answers on `rsp/P`; a server hears `req/P`
//! and answers on `rsp/<the pattern in the request>` ([`crate::wire::rpc_pattern`]).
//!
//! Where this differs from AimRT:
//! - request ids start at a random value per process, so clients of the same function in
//!   several processes (which all hear the same `rsp/P`) do not take each other's answers;
//!   an answer for an id no call here waits for is counted and dropped;
//! - a call whose `req/P` has no subscriber (no server) is answered at once with 2010, and
//!   calls in flight when the last server of their function goes away are answered 2010
//!   too; the runtime answers 2 at the caller's deadline in every other case;
//! - a request that cannot be handled is answered with its status (AimRT sends none), and
//!   every answer carries the length prefix (AimRT's error answers have none).

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, OnceLock, RwLock};

use aimrt_plugin_api::rpc::{BackendAnswer, BackendCall, BackendReply, RpcBackend};
use aimrt_plugin_api::{BackendOptions, Error, RpcStatus, ServiceHost};
use aimrt_wire::pending::PendingCalls;
use serde::Deserialize;
use zenoh::pubsub::{Publisher, Subscriber};
use zenoh::Wait;

use crate::session::{follow_matching, lock, read, said, write, Zenoh};
use crate::wire::{
    decode_request, decode_response, encode_request, encode_response, rpc_pattern, Request,
    Response,
};
use crate::{Release, ShmRule, ShmRules};

#[derive(Debug, Default, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct Options {
    #[serde(default)]
    timeout_executor: String,
    #[serde(default)]
    clients_options: Vec<ShmRule>,
    #[serde(default)]
    servers_options: Vec<ShmRule>,
}

/// A function this process calls.
struct ClientFunc {
    pattern: Arc<str>,
    publisher: Publisher<'static>,
    shm: bool,
    /// Whether some server's subscriber matches `req/P`.
    matching: Arc<AtomicBool>,
}

/// State shared with the zenoh callbacks.
pub(crate) struct Shared {
    zenoh: Arc<Zenoh>,
    host: OnceLock<ServiceHost>,
    /// Each call with its function's pattern.
    pending: PendingCalls<Arc<str>>,
    /// Answer publishers by pattern (a server's `rsp/P`).
    /// Taken out (the `Arc` cloned) for a put: no lock is held while zenoh calls a client
    /// of this process inside it.
    answers: RwLock<HashMap<String, Arc<(Publisher<'static>, bool)>>>,
    /// The functions served, by pattern.
    served: RwLock<HashMap<String, String>>,
    running: AtomicBool,
    /// The functions called, by name.
    clients: RwLock<HashMap<String, Arc<ClientFunc>>>,
    subscribers: Mutex<Vec<Subscriber<()>>>,
}

impl Release for Shared {
    /// Undeclares the subscribers and drops the publishers (a call on its way finishes
    /// its put first).
    fn release(&self) {
        crate::session::undeclare_all(&self.subscribers);
        write(&self.clients).clear();
        write(&self.answers).clear();
    }
}

/// The backend.
pub(crate) struct ZenohRpc {
    shared: Arc<Shared>,
    client_rules: OnceLock<ShmRules>,
    server_rules: OnceLock<ShmRules>,
}

impl ZenohRpc {
    pub(crate) fn new(zenoh: Arc<Zenoh>) -> ZenohRpc {
        ZenohRpc {
            shared: Arc::new(Shared {
                zenoh,
                host: OnceLock::new(),
                pending: PendingCalls::new("zenoh"),
                answers: RwLock::default(),
                served: RwLock::default(),
                running: AtomicBool::new(false),
                clients: RwLock::default(),
                subscribers: Mutex::default(),
            }),
            client_rules: OnceLock::new(),
            server_rules: OnceLock::new(),
        }
    }

    fn keep(&self, s: Subscriber<()>) {
        lock(&self.shared.subscribers).push(s);
    }

    /// What [`Release`] drops: for the plugin, whose shutdown comes also where the
    /// backend's does not (a start-up that failed before RPC started).
    pub(crate) fn declared(&self) -> Arc<Shared> {
        self.shared.clone()
    }
}

impl RpcBackend for ZenohRpc {
    fn type_name(&self) -> &str {
        "zenoh"
    }

    fn init(&self, options: &BackendOptions, host: ServiceHost) -> Result<(), Error> {
        let o: Options = options.read()?;
        if !o.timeout_executor.is_empty() && host.executor(&o.timeout_executor).is_none() {
            return Err(Error::Options {
                what: format!("zenoh backend options at {}", options.location()),
                message: format!(
                    "timeout_executor '{}' is not an executor of aimrt.executor.executors",
                    o.timeout_executor
                ),
            });
        }
        let where_ = options.location();
        let _ = self.client_rules.set(ShmRules::compile(
            o.clients_options,
            where_,
            "clients_options",
            "func_name",
        )?);
        let _ = self.server_rules.set(ShmRules::compile(
            o.servers_options,
            where_,
            "servers_options",
            "func_name",
        )?);
        let _ = self.shared.host.set(host);
        Ok(())
    }

    fn start(&self) -> Result<(), Error> {
        self.shared.running.store(true, Ordering::SeqCst);
        Ok(())
    }

    fn shutdown(&self) {
        self.shared.running.store(false, Ordering::SeqCst);
        self.shared.release();
        self.shared.pending.fail_where(
            |_| true,
            RpcStatus::CLI_NOT_READY,
            "the zenoh backend shut down before the answer arrived",
        );
    }

    fn register_service_func(&self, func: &str) -> Result<(), Error> {
        let z = &self.shared.zenoh;
        let pattern = rpc_pattern(func, &z.limit_domain);
        // Several modules of this process may serve one function: the runtime hands each
        // request to one of them, so one subscriber of `req/P` serves them all (one per
        // module ran each request once per module and sent as many answers).
        if read(&self.shared.served).contains_key(&pattern) {
            return Ok(());
        }
        let short = aimrt_wire::name_without_prefix(func);
        let shm = self
            .server_rules
            .get()
            .is_some_and(|r| r.shm(&[func, short]));
        if shm {
            z.ensure_shm()?;
        }
        let rsp = format!("rsp/{pattern}");
        let publisher = z
            .session()?
            .declare_publisher(rsp.clone())
            .wait()
            .map_err(|e| {
                Error::msg(format!(
                    "cannot declare a zenoh publisher on '{rsp}': {}",
                    said(&e)
                ))
            })?;
        write(&self.shared.answers).insert(pattern.clone(), Arc::new((publisher, shm)));
        write(&self.shared.served).insert(pattern.clone(), func.to_owned());
        let req = format!("req/{pattern}");
        let shared = self.shared.clone();
        let func_owned = func.to_owned();
        let subscriber = z
            .session()?
            .declare_subscriber(req.clone())
            .callback(move |sample| {
                let bytes = sample.payload().to_bytes();
                serve(&shared, &func_owned, &bytes);
            })
            .wait()
            .map_err(|e| {
                Error::msg(format!(
                    "cannot declare a zenoh subscriber on '{req}': {}",
                    said(&e)
                ))
            })?;
        self.keep(subscriber);
        tracing::info!(target: "aimrt", "Service with keyexpr: {pattern} ,role: server , shm_enabled: {shm}  is registered successfully.");
        // Clients of this process registered before: a server is here now.
        for c in read(&self.shared.clients).values() {
            if *c.pattern == *pattern {
                c.matching.store(true, Ordering::SeqCst);
            }
        }
        Ok(())
    }

    fn register_client_func(&self, func: &str) -> Result<(), Error> {
        let z = &self.shared.zenoh;
        let pattern = rpc_pattern(func, &z.limit_domain);
        if read(&self.shared.clients).contains_key(func) {
            return Ok(());
        }
        let short = aimrt_wire::name_without_prefix(func);
        let shm = self
            .client_rules
            .get()
            .is_some_and(|r| r.shm(&[func, short]));
        if shm {
            z.ensure_shm()?;
        }
        let req = format!("req/{pattern}");
        let publisher = z
            .session()?
            .declare_publisher(req.clone())
            .wait()
            .map_err(|e| {
                Error::msg(format!(
                    "cannot declare a zenoh publisher on '{req}': {}",
                    said(&e)
                ))
            })?;
        // A server of this process counts from its registration on (zenoh's listener says
        // so only a moment later, on another thread: a call at start would find none).
        let served_here = read(&self.shared.served).contains_key(&pattern);
        let pattern: Arc<str> = pattern.into();
        let matching = Arc::new(AtomicBool::new(served_here));
        {
            let flag = matching.clone();
            let shared = self.shared.clone();
            let pattern = pattern.clone();
            // Told the servers already known before it returns, so a call made right after
            // start is not answered "no server" while the news is on its way.
            follow_matching(&publisher, "servers", move |now| {
                flag.store(now, Ordering::SeqCst);
                if !now {
                    fail_pending(&shared, &pattern);
                }
            })?;
        }
        // Answers for every client of this pattern here: one subscriber per pattern.
        let rsp = format!("rsp/{pattern}");
        let shared = self.shared.clone();
        let subscriber = z
            .session()?
            .declare_subscriber(rsp.clone())
            .callback(move |sample| {
                let bytes = sample.payload().to_bytes();
                answer(&shared, &bytes);
            })
            .wait()
            .map_err(|e| {
                Error::msg(format!(
                    "cannot declare a zenoh subscriber on '{rsp}': {}",
                    said(&e)
                ))
            })?;
        self.keep(subscriber);
        tracing::info!(target: "aimrt", "Client with keyexpr: {pattern} ,role: client , shm_enabled: {shm}  is registered successfully.");
        write(&self.shared.clients).insert(
            func.to_owned(),
            Arc::new(ClientFunc {
                pattern,
                publisher,
                shm,
                matching,
            }),
        );
        Ok(())
    }

    fn invoke(&self, call: BackendCall, reply: BackendReply) {
        let z = &self.shared.zenoh;
        if !self.shared.running.load(Ordering::SeqCst) {
            return reply.send(BackendAnswer::fail(
                RpcStatus::CLI_NOT_READY,
                "the zenoh backend is not running",
            ));
        }
        let client = read(&self.shared.clients).get(&call.func).cloned();
        let Some(client) = client else {
            return reply.send(BackendAnswer::fail(
                RpcStatus::CLI_FUNC_NOT_REGISTERED,
                format!(
                    "'{}' was not registered as a zenoh client function",
                    call.func
                ),
            ));
        };
        if !client.matching.load(Ordering::SeqCst) {
            return reply.send(BackendAnswer::fail(
                RpcStatus::CLI_SEND_REQ_FAILED,
                format!(
                    "no zenoh server of '{}' is reachable (nobody subscribes to 'req/{}')",
                    call.func, client.pattern
                ),
            ));
        }
        let pending = &self.shared.pending;
        let id = pending.insert(reply, call.timeout, client.pattern.clone());
        let serialization_type = call.serialization_type().unwrap_or("pb").to_owned();
        let request = Request {
            serialization_type,
            reply_to: client.pattern.to_string(),
            req_id: id.to_le_bytes(),
            meta: call
                .meta_pairs()
                .map(|(k, v)| (k.to_owned(), v.to_owned()))
                .collect(),
            body: call.body,
        };
        let bytes = match encode_request(&request) {
            Ok(b) => b,
            Err(e) => {
                z.stats.refused.fetch_add(1, Ordering::Relaxed);
                return pending.fail(
                    id,
                    RpcStatus::CLI_INVALID_CONTEXT,
                    format!("the request cannot be laid out: {e}"),
                );
            }
        };
        if let Err(why) = z.put(&client.publisher, bytes, client.shm) {
            pending.fail(id, RpcStatus::CLI_SEND_REQ_FAILED, why);
        }
    }
}

/// The last server of `pattern` went away: its calls in flight get 2010.
fn fail_pending(shared: &Shared, pattern: &str) {
    shared.pending.fail_where(
        |p| **p == *pattern,
        RpcStatus::CLI_SEND_REQ_FAILED,
        &format!("the zenoh server of 'req/{pattern}' went away before it answered"),
    );
}

/// One answer heard on `rsp/P`.
fn answer(shared: &Shared, bytes: &[u8]) {
    let z = &shared.zenoh;
    let rsp = match decode_response(bytes) {
        Ok(r) => r,
        Err(e) => {
            z.stats.malformed.fetch_add(1, Ordering::Relaxed);
            z.warn(format_args!(
                "Handle zenoh rpc msg failed: a {}-byte answer is malformed: {e}",
                bytes.len()
            ));
            return;
        }
    };
    let id = u32::from_le_bytes(rsp.req_id);
    if !shared.pending.answer(rsp) {
        // Another process's call, or one this process gave up on.
        z.stats.unknown_ids.fetch_add(1, Ordering::Relaxed);
        tracing::trace!(target: "aimrt", "Can not get req id {id} from recorder.");
    }
}

/// One request heard on `req/P` for `func`: handed to the runtime, answered on
/// `rsp/<its pattern>`.
fn serve(shared: &Arc<Shared>, func: &str, bytes: &[u8]) {
    let z = &shared.zenoh;
    let req = match decode_request(bytes) {
        Ok(r) => r,
        Err(e) => {
            z.stats.malformed.fetch_add(1, Ordering::Relaxed);
            z.warn(format_args!(
                "Handle zenoh rpc msg failed: a {}-byte request for '{func}' is malformed: {e}",
                bytes.len()
            ));
            return;
        }
    };
    let Some(host) = shared.host.get().copied() else {
        return;
    };
    let (call, answering) = req.into_call(func);
    let shared = shared.clone();
    host.call(&call, move |a| {
        send_answer(&shared, &answering.reply_to, answering.response(a));
    });
}

/// Puts an answer on `rsp/<pattern>`: through the declared publisher of a pattern served
/// here, else (a client that wrote another pattern) with a one-off put.
fn send_answer(shared: &Shared, pattern: &str, rsp: Response) {
    let z = &shared.zenoh;
    let bytes = match encode_response(&rsp) {
        Ok(b) => b,
        Err(e) => {
            z.stats.refused.fetch_add(1, Ordering::Relaxed);
            z.warn(format_args!("an answer cannot be laid out: {e}"));
            return;
        }
    };
    let answerer = read(&shared.answers).get(pattern).cloned();
    let result = match answerer.as_deref() {
        Some((publisher, shm)) => z.put(publisher, bytes, *shm),
        None => z.session().map_err(|e| e.to_string()).and_then(|session| {
            session
                .put(format!("rsp/{pattern}"), bytes)
                .wait()
                .map(|()| {
                    z.stats.sent.fetch_add(1, Ordering::Relaxed);
                })
                .map_err(|e| {
                    z.stats.put_failed.fetch_add(1, Ordering::Relaxed);
                    format!("zenoh refused the answer on 'rsp/{pattern}': {}", said(&e))
                })
        }),
    };
    if let Err(why) = result {
        z.warn(format_args!("{why}"));
    }
}
