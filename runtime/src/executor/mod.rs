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
        let budget = ThreadBudget::of_this_machine();
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
            if let Some(threads) = process_threads().filter(|&n| n > budget.threads) {
                return Err(err(e, format!(
                    "the process runs {threads} threads once this executor has started, more than the {} this machine allows (vm.max_map_count {} / 8: each thread takes about four memory maps, and past the OS's limit a new thread cannot get its memory and the process aborts); ask for fewer threads (thread_num) or fewer executors",
                    budget.threads, budget.max_map_count
                )));
            }
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

/// How many threads the process may run once an executor has started. Each thread takes
/// about four memory maps (its stack and the signal stack, each with a guard page), and
/// the kernel allows `vm.max_map_count` maps (65 530 by default). Past that, a new
/// thread's signal stack cannot be mapped and Rust's runtime aborts the process inside
/// the thread's start, which no error path can catch: forty pools of 1 000 threads died
/// that way at about 16 000 threads. An eighth of the maps leaves room for the heap,
/// libraries and threads that plugins start themselves.
struct ThreadBudget {
    max_map_count: usize,
    threads: usize,
}

impl ThreadBudget {
    fn of_this_machine() -> ThreadBudget {
        let max_map_count = std::fs::read_to_string("/proc/sys/vm/max_map_count")
            .ok()
            .and_then(|s| s.trim().parse().ok())
            .unwrap_or(65_530);
        ThreadBudget {
            max_map_count,
            threads: (max_map_count / 8).max(64),
        }
    }
}

/// The threads this process runs now (`Threads:` of `/proc/self/status`).
fn process_threads() -> Option<usize> {
    std::fs::read_to_string("/proc/self/status")
        .ok()?
        .lines()
        .find_map(|l| l.strip_prefix("Threads:"))?
        .trim()
        .parse()
        .ok()
}

/// A build order where every executor comes after those it binds to, or a cycle. A walk
/// with a stack of its own, not recursion: a config may chain 200 000 executors, one
/// bound to the next, and a recursive walk overflowed the main thread's stack.
fn order(binds: &[Vec<Option<usize>>]) -> Result<Vec<usize>, Vec<usize>> {
    #[derive(Clone, Copy, PartialEq)]
    enum Mark {
        New,
        Active,
        Done,
    }
    let mut marks = vec![Mark::New; binds.len()];
    let mut out = Vec::with_capacity(binds.len());
    // The executors being walked, each with the index of its next bind to follow.
    let mut path: Vec<(usize, usize)> = Vec::new();
    for root in 0..binds.len() {
        if marks[root] != Mark::New {
            continue;
        }
        marks[root] = Mark::Active;
        path.push((root, 0));
        while let Some(top) = path.last_mut() {
            let (i, next) = *top;
            let Some(bind) = binds[i].get(next) else {
                marks[i] = Mark::Done;
                out.push(i);
                path.pop();
                continue;
            };
            top.1 += 1;
            let Some(j) = *bind else { continue };
            match marks[j] {
                Mark::Done => {}
                Mark::Active => {
                    let start = path.iter().position(|&(s, _)| s == j).unwrap_or(0);
                    let mut cycle: Vec<usize> = path[start..].iter().map(|&(s, _)| s).collect();
                    cycle.push(j);
                    return Err(cycle);
                }
                Mark::New => {
                    marks[j] = Mark::Active;
                    path.push((j, 0));
                }
            }
        }
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
        // 3 binds nothing and 0; 0 binds 1, which binds 2, which binds 0.
        assert_eq!(
            order(&[
                vec![Some(1)],
                vec![None, Some(2)],
                vec![Some(0)],
                vec![None, Some(0)]
            ])
            .unwrap_err(),
            vec![0, 1, 2, 0]
        );
    }

    #[test]
    fn a_chain_of_a_million_executors_is_ordered_without_recursion() {
        let n = 1_000_000;
        let binds: Vec<Vec<Option<usize>>> =
            (0..n).map(|i| vec![(i + 1 < n).then_some(i + 1)]).collect();
        let got = order(&binds).unwrap();
        assert!(got.iter().copied().eq((0..n).rev()));
        // The same chain closed into a cycle is named whole.
        let mut binds = binds;
        binds[n - 1] = vec![Some(0)];
        let cycle = order(&binds).unwrap_err();
        assert_eq!(cycle.len(), n + 1);
        assert_eq!((cycle[0], cycle[n - 1], cycle[n]), (0, n - 1, 0));
    }
}
