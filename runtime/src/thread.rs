//! The runtime's thread factory: every executor thread is configured through it (seed 002's
//! thread-manager idea, AimRT's `thread_sched_policy` / `thread_bind_cpu`).
//!
//! The name is set by the spawning side ([`aimrt_plugin_api::ThreadFactory::spawn`]); here
//! the calling thread gets its CPU binding and then its scheduling policy. Unlike AimRT, a
//! refused binding does not skip the policy: each setting is tried, and every refusal is
//! reported in one message with the OS's reason.

use aimrt_plugin_api::{ThreadConfigurator, ThreadSettingsRef};
use nix::sched::{sched_getaffinity, sched_setaffinity, CpuSet};
use nix::unistd::Pid;
use thread_priority::unix::{
    set_thread_priority_and_policy, thread_native_id, thread_schedule_policy_param,
    NormalThreadSchedulePolicy, RealtimeThreadSchedulePolicy, ThreadSchedulePolicy,
};
use thread_priority::{ThreadPriority, ThreadPriorityValue};

/// A scheduling policy as AimRT spells it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum SchedPolicy {
    /// `SCHED_OTHER`: the default time-sharing policy.
    Other,
    /// `SCHED_FIFO:<prio>`.
    Fifo(u8),
    /// `SCHED_RR:<prio>`.
    RoundRobin(u8),
}

impl SchedPolicy {
    /// Parses `""` (no change), `SCHED_OTHER`, `SCHED_FIFO:<1-99>` or `SCHED_RR:<1-99>`.
    pub(crate) fn parse(text: &str) -> Result<Option<SchedPolicy>, String> {
        let text = text.trim();
        if text.is_empty() {
            return Ok(None);
        }
        if text == "SCHED_OTHER" {
            return Ok(Some(SchedPolicy::Other));
        }
        let expected = "expected SCHED_OTHER, SCHED_FIFO:<1-99> or SCHED_RR:<1-99>";
        let Some((policy, prio)) = text.split_once(':') else {
            return Err(format!(
                "thread_sched_policy '{text}' is invalid: {expected}"
            ));
        };
        let prio: u8 = match prio.trim().parse() {
            Ok(p @ 1..=99) => p,
            _ => {
                return Err(format!(
                    "thread_sched_policy '{text}': priority '{prio}' is not in 1..=99"
                ))
            }
        };
        match policy {
            "SCHED_FIFO" => Ok(Some(SchedPolicy::Fifo(prio))),
            "SCHED_RR" => Ok(Some(SchedPolicy::RoundRobin(prio))),
            _ => Err(format!(
                "thread_sched_policy '{text}': unknown policy '{policy}'; {expected}"
            )),
        }
    }

    fn apply_to_current(self) -> Result<(), String> {
        let native = thread_native_id();
        let (policy, prio) = match self {
            SchedPolicy::Fifo(p) => (
                ThreadSchedulePolicy::Realtime(RealtimeThreadSchedulePolicy::Fifo),
                p,
            ),
            SchedPolicy::RoundRobin(p) => (
                ThreadSchedulePolicy::Realtime(RealtimeThreadSchedulePolicy::RoundRobin),
                p,
            ),
            SchedPolicy::Other => {
                let other = ThreadSchedulePolicy::Normal(NormalThreadSchedulePolicy::Other);
                if thread_schedule_policy_param(native).is_ok_and(|(p, _)| p == other) {
                    return Ok(());
                }
                // The crate maps 0..=99 onto niceness; 47 is nice 0, the default.
                (other, 47)
            }
        };
        let value = ThreadPriorityValue::try_from(prio).map_err(|e| e.to_owned())?;
        set_thread_priority_and_policy(native, ThreadPriority::Crossplatform(value), policy)
            .map_err(|e| {
                format!(
                    "the OS refused thread_sched_policy {self}: {}",
                    os_reason(&e)
                )
            })?;
        match thread_schedule_policy_param(native) {
            Ok((actual, params))
                if actual == policy
                    && (self == SchedPolicy::Other || params.sched_priority == i32::from(prio)) =>
            {
                Ok(())
            }
            Ok((actual, params)) => Err(format!(
                "thread_sched_policy {self} did not hold: the thread runs with {actual:?} priority {}",
                params.sched_priority
            )),
            Err(e) => Err(format!(
                "cannot read back the scheduling policy: {}",
                os_reason(&e)
            )),
        }
    }
}

impl std::fmt::Display for SchedPolicy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SchedPolicy::Other => f.write_str("SCHED_OTHER"),
            SchedPolicy::Fifo(p) => write!(f, "SCHED_FIFO:{p}"),
            SchedPolicy::RoundRobin(p) => write!(f, "SCHED_RR:{p}"),
        }
    }
}

fn os_reason(e: &thread_priority::Error) -> String {
    match e {
        thread_priority::Error::OS(code) => std::io::Error::from_raw_os_error(*code).to_string(),
        other => other.to_string(),
    }
}

/// The CPUs this process may run on, from `sched_getaffinity`.
pub(crate) fn allowed_cpus() -> Vec<u32> {
    let Ok(set) = sched_getaffinity(Pid::from_raw(0)) else {
        return Vec::new();
    };
    (0..CpuSet::count())
        .filter(|&i| set.is_set(i).unwrap_or(false))
        .filter_map(|i| u32::try_from(i).ok())
        .collect()
}

/// Binds the calling thread to the requested CPUs that this process may use. Requested CPUs
/// outside the allowed set are refused (and reported); if none is left, nothing is bound.
fn bind_current(requested: &[u32], allowed: &[u32]) -> Result<(), String> {
    if requested.is_empty() {
        return Ok(());
    }
    let (usable, refused): (Vec<u32>, Vec<u32>) =
        requested.iter().partition(|c| allowed.contains(c));
    let mut problems = Vec::new();
    if !refused.is_empty() {
        problems.push(format!(
            "thread_bind_cpu {refused:?} not available (this process may use CPUs {allowed:?})"
        ));
    }
    if usable.is_empty() {
        problems.push("the thread is not bound to any CPU".to_owned());
    } else {
        let mut set = CpuSet::new();
        for &cpu in &usable {
            set.set(cpu as usize)
                .map_err(|e| format!("CPU {cpu}: {e}"))?;
        }
        if let Err(e) = sched_setaffinity(Pid::from_raw(0), &set) {
            problems.push(format!("the OS refused binding to CPUs {usable:?}: {e}"));
        } else if !refused.is_empty() {
            problems.push(format!("bound to CPUs {usable:?} only"));
        }
    }
    if problems.is_empty() {
        Ok(())
    } else {
        Err(problems.join(", "))
    }
}

/// Applies thread settings to the calling thread.
#[derive(Debug)]
pub(crate) struct HostThreads {
    allowed: Vec<u32>,
}

impl HostThreads {
    /// A configurator that knows which CPUs the process may use (taken once, at start).
    pub(crate) fn new() -> HostThreads {
        HostThreads {
            allowed: allowed_cpus(),
        }
    }
}

impl ThreadConfigurator for HostThreads {
    fn configure_current(&self, s: &ThreadSettingsRef<'_>) -> Result<(), String> {
        let mut refused = Vec::new();
        if let Err(why) = bind_current(s.bind_cpu, &self.allowed) {
            refused.push(why);
        }
        match SchedPolicy::parse(s.sched_policy) {
            Ok(Some(policy)) => {
                if let Err(why) = policy.apply_to_current() {
                    refused.push(why);
                }
            }
            Ok(None) => {}
            Err(why) => refused.push(why),
        }
        if refused.is_empty() {
            Ok(())
        } else {
            Err(refused.join("; "))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn policies_parse_like_aimrt_but_strictly() {
        assert_eq!(SchedPolicy::parse(""), Ok(None));
        assert_eq!(
            SchedPolicy::parse("SCHED_OTHER"),
            Ok(Some(SchedPolicy::Other))
        );
        assert_eq!(
            SchedPolicy::parse("SCHED_FIFO:80"),
            Ok(Some(SchedPolicy::Fifo(80)))
        );
        assert_eq!(
            SchedPolicy::parse("SCHED_RR:1"),
            Ok(Some(SchedPolicy::RoundRobin(1)))
        );
        for bad in [
            "SCHED_FIFO",
            "SCHED_FIFO:",
            "SCHED_FOO:1",
            "SCHED_FIFO:0",
            "SCHED_FIFO:100",
            "SCHED_OTHER:5",
            "SCHED_FIFO:80abc",
        ] {
            let err = SchedPolicy::parse(bad).unwrap_err();
            assert!(err.contains(bad), "{bad}: {err}");
        }
    }

    fn in_thread<R: Send + 'static>(f: impl FnOnce() -> R + Send + 'static) -> R {
        std::thread::spawn(f).join().unwrap()
    }

    fn settings<'a>(policy: &'a str, cpus: &'a [u32]) -> ThreadSettingsRef<'a> {
        ThreadSettingsRef {
            name: "t",
            sched_policy: policy,
            bind_cpu: cpus,
            strict: false,
        }
    }

    #[test]
    fn binds_to_an_allowed_cpu() {
        let host = HostThreads::new();
        let cpu = host.allowed[0];
        let (result, now_allowed) = in_thread(move || {
            let r = host.configure_current(&settings("", &[cpu]));
            (r, allowed_cpus())
        });
        assert_eq!(result, Ok(()));
        assert_eq!(now_allowed, vec![cpu]);
    }

    #[test]
    fn a_cpu_outside_the_allowed_set_is_refused_with_the_reason() {
        let host = HostThreads::new();
        let outside = host.allowed.iter().max().unwrap() + 1;
        let err = in_thread(move || host.configure_current(&settings("", &[outside]))).unwrap_err();
        assert!(err.contains(&format!("[{outside}]")), "{err}");
        assert!(err.contains("not available"), "{err}");
    }

    #[test]
    fn sched_other_is_applied_and_fifo_either_holds_or_says_why() {
        let host = HostThreads::new();
        assert_eq!(
            in_thread(move || host.configure_current(&settings("SCHED_OTHER", &[]))),
            Ok(())
        );
        let host = HostThreads::new();
        let (result, policy) = in_thread(move || {
            let r = host.configure_current(&settings("SCHED_FIFO:10", &[]));
            (r, thread_schedule_policy_param(thread_native_id()).unwrap())
        });
        match result {
            // Granted (root, or an RT limit): the policy and priority really hold.
            Ok(()) => {
                assert_eq!(
                    policy.0,
                    ThreadSchedulePolicy::Realtime(RealtimeThreadSchedulePolicy::Fifo)
                );
                assert_eq!(policy.1.sched_priority, 10);
            }
            Err(why) => assert!(why.contains("SCHED_FIFO:10"), "{why}"),
        }
    }
}
