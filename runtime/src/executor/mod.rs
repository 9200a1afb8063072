//! The executor manager: builds the configured executors in dependency order, looks them
//! up by name, and shuts them down in reverse order with a join timeout.

pub(crate) mod serial;

use std::collections::{BTreeMap, HashMap};
use std::sync::mpsc;
use std::time::Duration;

use aimrt_plugin_api::ffi::{RawExecutor, RawThreadFactory};

use crate::config::{Config, ExecutorEntry, ReportedOptions};
use crate::plugin::ExecutorType;
use crate::Error;
use aimrt_plugin_api::__private::did_you_mean;

/// Executors by name, in creation order.
#[derive(Debug, Default)]
pub(crate) struct ExecutorManager {
    created: Vec<(String, RawExecutor)>,
    by_name: HashMap<String, RawExecutor>,
    /// The options of each executor (JSON) as it read them, else as written, for the
    /// initialization report.
    options: HashMap<String, String>,
    /// The options each executor reported as it read them (ABI 1.8), for
    /// `--dump_cfg_file`.
    pub(crate) normalized_options: BTreeMap<String, serde_json::Value>,
    join_timeout: Duration,
}

impl ExecutorManager {
    /// Builds and starts every executor of `aimrt.executor.executors`. Bind keys may name
    /// executors declared later in the file; cycles and unknown names are refused.
    pub(crate) fn build(
        &mut self,
        config: &Config,
        types: &BTreeMap<String, ExecutorType>,
        reserved: &[&str],
        threads: RawThreadFactory,
    ) -> Result<(), Error> {
        let Some(section) = config.aimrt.executor.as_ref() else {
            return Ok(());
        };
        self.join_timeout = Duration::from_millis(section.join_timeout_ms);
        let entries = &section.executors;
        let err = |e: &ExecutorEntry, message: String| Error::Executor {
            executor: e.name.value.clone(),
            location: config.at(&e.name),
            message,
        };
        let mut index = HashMap::new();
        for (i, e) in entries.iter().enumerate() {
            let name = e.name.value.as_str();
            crate::config::check_name(name).map_err(|m| err(e, m))?;
            if reserved.contains(&name) {
                return Err(err(e, format!("the name '{name}' is taken by the runtime's main or guard thread; choose another name")));
            }
            if index.insert(name, i).is_some() {
                return Err(err(
                    e,
                    format!("duplicate executor name '{name}'; executor names must be unique"),
                ));
            }
            if !types.contains_key(&e.type_name.value) {
                let known: Vec<&str> = types.keys().map(String::as_str).collect();
                return Err(err(
                    e,
                    format!(
                        "unknown executor type '{}'{}; known types: {} (plugins add more)",
                        e.type_name.value,
                        did_you_mean(&e.type_name.value, known.iter().copied()),
                        known.join(", ")
                    ),
                ));
            }
        }
        // Resolve bind keys to entry indices.
        let mut binds: Vec<Vec<Option<usize>>> = Vec::with_capacity(entries.len());
        for e in entries {
            let ty = &types[&e.type_name.value];
            let mut row = Vec::new();
            for key in &ty.bind_keys {
                let target = e
                    .options
                    .as_ref()
                    .and_then(|o| o.value.get(key))
                    .and_then(|v| v.as_str())
                    .unwrap_or("");
                if target.is_empty() {
                    row.push(None);
                    continue;
                }
                match index.get(target) {
                    Some(&j) => row.push(Some(j)),
                    None => {
                        return Err(err(
                            e,
                            format!(
                                "option '{key}' names executor '{target}', which is not declared{}",
                                did_you_mean(target, index.keys().copied())
                            ),
                        ))
                    }
                }
            }
            binds.push(row);
        }
        for i in order(&binds).map_err(|cycle| {
            let names: Vec<&str> = cycle
                .iter()
                .map(|&i| entries[i].name.value.as_str())
                .collect();
            err(
                &entries[cycle[0]],
                format!(
                    "executors bind to each other in a cycle: {}",
                    names.join(" -> ")
                ),
            )
        })? {
            let e = &entries[i];
            let bound: Vec<RawExecutor> = binds[i]
                .iter()
                .map(|b| {
                    b.map_or(RawExecutor::null(), |j| {
                        self.by_name[&entries[j].name.value]
                    })
                })
                .collect();
            let (options, location) = config.options_of(e.options.as_ref(), &e.name);
            let ty = &types[&e.type_name.value];
            let (exec, reported) = ty
                .raw
                .create(&e.name.value, &options, &location, &bound, threads)
                .map_err(|m| err(e, m))?;
            let owner = format!("executor '{}'", e.name.value);
            // The report shows the options as the executor read them, where it said.
            let mut shown = options.clone();
            if let Some(value) = reported.and_then(|json| ReportedOptions::parse(&owner, &json)) {
                shown = value.to_string();
                self.normalized_options.insert(e.name.value.clone(), value);
            }
            self.created.push((e.name.value.clone(), exec));
            self.options.insert(e.name.value.clone(), shown);
            self.by_name.insert(e.name.value.clone(), exec);
            exec.start()
                .map_err(|m| err(e, format!("failed to start: {m}")))?;
            tracing::debug!(target: "aimrt", "executor '{}' ({}) created", e.name.value, e.type_name.value);
        }
        Ok(())
    }

    /// Adds a runtime-owned executor (main thread) that modules may look up.
    pub(crate) fn add_runtime_executor(&mut self, name: &str, exec: RawExecutor) {
        self.by_name.insert(name.to_owned(), exec);
    }

    /// Name, type, thread safe (Y/N), timers (Y/N) and options of every executor, in
    /// creation order.
    pub(crate) fn report_rows(&self) -> Vec<Vec<String>> {
        let yn = |b: bool| if b { "Y" } else { "N" }.to_owned();
        self.created
            .iter()
            .map(|(name, e)| {
                vec![
                    name.clone(),
                    e.type_name().to_owned(),
                    yn(e.thread_safe()),
                    yn(e.supports_timer_schedule()),
                    self.options.get(name).cloned().unwrap_or_default(),
                ]
            })
            .collect()
    }

    /// A snapshot of the name table, for module cores.
    pub(crate) fn table(&self) -> HashMap<String, RawExecutor> {
        self.by_name.clone()
    }

    /// Shuts executors down in reverse creation order, each with a join timeout; an
    /// executor that does not finish in time is reported and abandoned.
    ///
    /// No executor is freed: an [`ExecutorRef`](aimrt_plugin_api::ExecutorRef) is `Copy`,
    /// and a module, a plugin or an app may keep one past shutdown (a thread it did not
    /// join, a handle held after `run` returned). Such a call reaches the shut-down
    /// executor, which refuses work and still reports its stats, instead of freed memory.
    pub(crate) fn shutdown(&mut self) {
        let created = std::mem::take(&mut self.created);
        self.by_name.clear();
        for (name, exec) in created.into_iter().rev() {
            let (tx, rx) = mpsc::channel();
            let spawned = std::thread::Builder::new()
                .name("aimrt_shutdown".into())
                .spawn(move || {
                    exec.shutdown();
                    let _ = tx.send(());
                });
            let joined = spawned.is_ok() && rx.recv_timeout(self.join_timeout).is_ok();
            let s = exec.stats();
            if joined {
                tracing::info!(
                    target: "aimrt",
                    "executor '{name}' shut down: submitted {}, run {}, refused {}, panicked {}, dropped at shutdown {}",
                    s.submitted, s.run, s.refused, s.panicked, s.dropped_at_shutdown
                );
            } else {
                tracing::error!(
                    target: "aimrt",
                    "executor '{name}' did not finish within {} ms (a task never returned?); abandoned with {} tasks queued or running",
                    self.join_timeout.as_millis(), s.queue_depth
                );
            }
        }
    }
}

/// A build order where every executor comes after those it binds to, or a cycle.
fn order(binds: &[Vec<Option<usize>>]) -> Result<Vec<usize>, Vec<usize>> {
    #[derive(Clone, Copy, PartialEq)]
    enum Mark {
        New,
        Active,
        Done,
    }
    fn visit(
        i: usize,
        binds: &[Vec<Option<usize>>],
        marks: &mut [Mark],
        stack: &mut Vec<usize>,
        out: &mut Vec<usize>,
    ) -> Result<(), Vec<usize>> {
        match marks[i] {
            Mark::Done => return Ok(()),
            Mark::Active => {
                let start = stack.iter().position(|&s| s == i).unwrap_or(0);
                let mut cycle = stack[start..].to_vec();
                cycle.push(i);
                return Err(cycle);
            }
            Mark::New => {}
        }
        marks[i] = Mark::Active;
        stack.push(i);
        for j in binds[i].iter().flatten() {
            visit(*j, binds, marks, stack, out)?;
        }
        stack.pop();
        marks[i] = Mark::Done;
        out.push(i);
        Ok(())
    }
    let mut marks = vec![Mark::New; binds.len()];
    let mut out = Vec::with_capacity(binds.len());
    for i in 0..binds.len() {
        visit(i, binds, &mut marks, &mut Vec::new(), &mut out)?;
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::order;

    #[test]
    fn order_puts_bound_executors_first() {
        // 0 binds 2, 1 binds nothing, 2 binds 1
        assert_eq!(
            order(&[vec![Some(2)], vec![], vec![Some(1)]]).unwrap(),
            vec![1, 2, 0]
        );
    }

    #[test]
    fn order_reports_cycles() {
        assert_eq!(
            order(&[vec![Some(1)], vec![Some(0)]]).unwrap_err(),
            vec![0, 1, 0]
        );
        assert_eq!(order(&[vec![Some(0)]]).unwrap_err(), vec![0, 0]);
    }
}
