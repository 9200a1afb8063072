//! The calls an RPC backend over publish/subscribe (zenoh_plugin, mqtt_plugin) has sent and
//! waits to hear answered, by request id ([`crate::payload::Request::req_id`]).
//!
//! Ids start at a random value in each process, so clients of one function in several
//! processes that hear the same answers do not take each other's. A call is forgotten a
//! second after its deadline (the runtime has answered it `TIMEOUT` by then), when a later
//! call comes; the backend answers what is left at its shutdown. A call whose deadline has
//! passed is given up with `TIMEOUT` whatever the reason (forgotten, its server gone, the
//! backend shut down): the runtime takes that for the timeout it has answered already,
//! not for a late answer.
//!
//! ```
//! use aimrt_plugin_api::rpc::{BackendAnswer, BackendReply};
//! use aimrt_plugin_api::RpcStatus;
//! use aimrt_wire::payload::Response;
//! use aimrt_wire::pending::PendingCalls;
//! use std::sync::mpsc;
//!
//! let calls: PendingCalls<()> = PendingCalls::new("mqtt");
//! let (tx, rx) = mpsc::channel();
//! let id = calls.insert(BackendReply::from_fn(move |a| tx.send(a).unwrap()), None, ());
//! let answer = Response { serialization_type: "pb".into(), req_id: id.to_le_bytes(), status: 0, body: b"ok".to_vec() };
//! assert!(calls.answer(answer.clone()));
//! assert_eq!(rx.recv().unwrap().body, b"ok");
//! // The same id again: no call waits for it.
//! assert!(!calls.answer(answer));
//! ```

use std::collections::HashMap;
use std::hash::{BuildHasher, Hasher};
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use aimrt_plugin_api::rpc::{BackendAnswer, BackendReply};
use aimrt_plugin_api::RpcStatus;

use crate::payload::Response;

/// How long after a call's deadline its record is dropped.
const GRACE: Duration = Duration::from_secs(1);

/// The deadline of a call without a timeout (the runtime's default).
const DEFAULT_TIMEOUT: Duration = Duration::from_secs(5);

struct Pending<T> {
    reply: BackendReply,
    tag: T,
    deadline: Instant,
}

/// The calls waiting for their answers; `T` is what the backend keeps with each (zenoh:
/// the function's pattern, to fail its calls when its last server goes away).
pub struct PendingCalls<T> {
    backend: &'static str,
    calls: Mutex<HashMap<u32, Pending<T>>>,
    next_id: AtomicU32,
    next_sweep: Mutex<Instant>,
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// A random request id to start from.
fn random_start() -> u32 {
    let mut h = std::collections::hash_map::RandomState::new().build_hasher();
    h.write_u32(std::process::id());
    h.write_u128(
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos()),
    );
    h.finish() as u32
}

impl<T> PendingCalls<T> {
    /// No call yet; `backend` names the backend in the answers' details.
    pub fn new(backend: &'static str) -> PendingCalls<T> {
        PendingCalls {
            backend,
            calls: Mutex::default(),
            next_id: AtomicU32::new(random_start()),
            next_sweep: Mutex::new(Instant::now()),
        }
    }

    /// Records a call with its deadline (`None`: 5 s) and returns its request id. First
    /// forgets, at most once a second, the calls a second past their deadline.
    pub fn insert(&self, reply: BackendReply, timeout: Option<Duration>, tag: T) -> u32 {
        let now = Instant::now();
        self.sweep(now);
        let id = self.next_id.fetch_add(1, Ordering::Relaxed);
        let deadline = now + timeout.unwrap_or(DEFAULT_TIMEOUT);
        lock(&self.calls).insert(
            id,
            Pending {
                reply,
                tag,
                deadline,
            },
        );
        id
    }

    /// Takes call `id` out and answers it with `status` (a send that failed).
    pub fn fail(&self, id: u32, status: RpcStatus, why: String) {
        let taken = lock(&self.calls).remove(&id);
        if let Some(p) = taken {
            self.give_up(p, status, &why, Instant::now());
        }
    }

    /// Answers `p` with `status`, or with `TIMEOUT` once its deadline has passed.
    fn give_up(&self, p: Pending<T>, status: RpcStatus, why: &str, now: Instant) {
        let answer = if p.deadline < now {
            BackendAnswer::fail(
                RpcStatus::TIMEOUT,
                format!("no {} answer arrived before the deadline", self.backend),
            )
        } else {
            BackendAnswer::fail(status, why)
        };
        p.reply.send(answer);
    }

    /// Answers the call `rsp` is for; `false` when no call here waits for its id (a call
    /// that has timed out, another process's, or a forged answer).
    pub fn answer(&self, rsp: Response) -> bool {
        let id = u32::from_le_bytes(rsp.req_id);
        let taken = lock(&self.calls).remove(&id);
        let Some(p) = taken else {
            return false;
        };
        p.reply.send(if rsp.status == 0 {
            BackendAnswer::ok(rsp.body)
        } else {
            let status = RpcStatus::from_code(rsp.status);
            BackendAnswer::fail(
                status,
                format!("the {} server answered {status}", self.backend),
            )
        });
        true
    }

    /// Answers every call whose tag `which` picks with `status` (`TIMEOUT` where its
    /// deadline has passed).
    pub fn fail_where(&self, which: impl Fn(&T) -> bool, status: RpcStatus, why: &str) {
        let now = Instant::now();
        for p in self.take_where(|p| which(&p.tag)) {
            self.give_up(p, status, why, now);
        }
    }

    /// Answers `TIMEOUT` to the calls a second past their deadline (at most once a second).
    fn sweep(&self, now: Instant) {
        {
            let mut next = lock(&self.next_sweep);
            if now < *next {
                return;
            }
            *next = now + Duration::from_secs(1);
        }
        for p in self.take_where(|p| p.deadline + GRACE <= now) {
            self.give_up(p, RpcStatus::TIMEOUT, "", now);
        }
    }

    /// Takes out the calls `which` picks (answered after the lock is let go).
    fn take_where(&self, which: impl Fn(&Pending<T>) -> bool) -> Vec<Pending<T>> {
        let mut calls = lock(&self.calls);
        let ids: Vec<u32> = calls
            .iter()
            .filter(|(_, p)| which(p))
            .map(|(id, _)| *id)
            .collect();
        ids.iter().filter_map(|id| calls.remove(id)).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::mpsc;

    fn call(calls: &PendingCalls<u8>, timeout: Duration, tag: u8) -> mpsc::Receiver<RpcStatus> {
        let (tx, rx) = mpsc::channel();
        let reply = BackendReply::from_fn(move |a| tx.send(a.status).unwrap());
        calls.insert(reply, Some(timeout), tag);
        rx
    }

    #[test]
    fn a_call_given_up_after_its_deadline_is_answered_timeout_whatever_the_reason() {
        let calls = PendingCalls::new("zenoh");
        let expired = call(&calls, Duration::ZERO, 1);
        let waiting = call(&calls, Duration::from_secs(60), 1);
        let other = call(&calls, Duration::ZERO, 2);
        std::thread::sleep(Duration::from_millis(5));
        calls.fail_where(
            |t| *t == 1,
            RpcStatus::CLI_SEND_REQ_FAILED,
            "its server went away",
        );
        assert_eq!(expired.try_recv(), Ok(RpcStatus::TIMEOUT));
        assert_eq!(waiting.try_recv(), Ok(RpcStatus::CLI_SEND_REQ_FAILED));
        assert!(other.try_recv().is_err(), "not picked");
    }

    #[test]
    fn a_call_a_second_past_its_deadline_is_forgotten_when_a_later_call_comes() {
        let calls = PendingCalls::new("mqtt");
        let expired = call(&calls, Duration::ZERO, 0);
        let within = call(&calls, Duration::from_millis(500), 0);
        std::thread::sleep(GRACE + Duration::from_millis(100));
        let _later = call(&calls, Duration::from_secs(60), 0);
        assert_eq!(expired.try_recv(), Ok(RpcStatus::TIMEOUT));
        assert!(
            within.try_recv().is_err(),
            "kept: within a second of its deadline"
        );
    }
}
