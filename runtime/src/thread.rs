//! The runtime's thread factory: every executor thread is configured through it.

use aimrt_plugin_api::{ThreadConfigurator, ThreadSettingsRef};

/// Applies thread settings to the calling thread. The name is set by the spawning side;
/// scheduling policy and CPU binding are validated here.
#[derive(Debug, Default)]
pub(crate) struct HostThreads;

impl ThreadConfigurator for HostThreads {
    fn configure_current(&self, s: &ThreadSettingsRef<'_>) -> Result<(), String> {
        let mut refused = Vec::new();
        if !s.sched_policy.is_empty() && s.sched_policy != "SCHED_OTHER" {
            refused.push(format!("thread_sched_policy '{}' is not applied (scheduling policies arrive with the standard executors)", s.sched_policy));
        }
        if !s.bind_cpu.is_empty() {
            refused.push(format!("thread_bind_cpu {:?} is not applied (CPU binding arrives with the standard executors)", s.bind_cpu));
        }
        if refused.is_empty() {
            Ok(())
        } else {
            Err(refused.join("; "))
        }
    }
}
