//! `BenchmarkRpcClientModule`: AimRT's RPC benchmark client.

use std::sync::mpsc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use aimrt_plugin_api::{CoreRef, DynamicLatch, Error, ExecutorRef, Module, ModuleInfo, Task};
use aimrt_protocols::example::{ExampleServiceClient, GetFooDataReq};
use serde::Deserialize;

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct Plan {
    /// `bench` (back to back) or `fixed-freq` (`freq` calls a second per worker).
    perf_mode: String,
    /// Bytes of the request's `msg`.
    msg_size: usize,
    /// Workers, each on `client_executor_<i>`.
    parallel: usize,
    /// Calls per worker.
    msg_count: usize,
    #[serde(default)]
    freq: Option<f64>,
}

/// The largest request `msg_size` a plan may ask for (each worker holds one).
const MAX_MSG_SIZE: usize = 256 << 20;

/// The range of a fixed-freq plan's `freq` (calls a second per worker).
const FREQ_RANGE: std::ops::RangeInclusive<f64> = 0.001..=1e9;

impl Plan {
    /// Checks the plan against `max_parallel`; a bench plan's `freq` is dropped (AimRT
    /// reads none).
    fn check(&mut self, max_parallel: usize) -> Result<(), String> {
        match self.perf_mode.as_str() {
            "bench" => self.freq = None,
            "fixed-freq" => match self.freq {
                Some(f) if FREQ_RANGE.contains(&f) => {}
                _ => {
                    return Err(format!(
                        "a fixed-freq plan needs freq (calls a second per worker) in {} ..= {}",
                        FREQ_RANGE.start(),
                        FREQ_RANGE.end()
                    ))
                }
            },
            other => {
                return Err(format!(
                    "perf_mode is '{other}'; it must be bench or fixed-freq"
                ))
            }
        }
        if self.parallel == 0 || self.parallel > max_parallel {
            return Err(format!(
                "parallel is {}; it must be in 1 ..= max_parallel ({max_parallel})",
                self.parallel
            ));
        }
        if self.msg_size > MAX_MSG_SIZE {
            return Err(format!(
                "msg_size is {}; at most {MAX_MSG_SIZE} bytes",
                self.msg_size
            ));
        }
        Ok(())
    }
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct Config {
    max_parallel: usize,
    bench_plans: Vec<Plan>,
    #[serde(default)]
    service_name: Option<String>,
}

/// AimRT's RPC benchmark client. From `start`, on a thread of its own: it waits
/// for the server (a `GetFooData` call every second until one succeeds, warning
/// `Server is not available!!!` after each failure), then runs `bench_plans` one after
/// another, 1 s apart. Each plan's `parallel` workers call `GetFooData` `msg_count` times
/// each on `client_executor_<i>` (back to back, or at `freq` Hz), each call with a 3 s
/// timeout, and the module logs AimRT's `Benchmark plan <i> completed, report:` block.
#[derive(Debug, Default)]
pub struct BenchmarkRpcClientModule {
    setup: Option<Setup>,
    runner: Option<(DynamicLatch, JoinHandle<()>)>,
}

#[derive(Debug)]
struct Setup {
    plans: Vec<Plan>,
    executors: Vec<ExecutorRef>,
    client: ExampleServiceClient,
}

impl Module for BenchmarkRpcClientModule {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("BenchmarkRpcClientModule")
    }

    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let mut cfg: Config = core.config()?;
        for (i, p) in cfg.bench_plans.iter_mut().enumerate() {
            p.check(cfg.max_parallel)
                .map_err(|e| Error::msg(format!("bench_plans[{i}]: {e}")))?;
        }
        let executors = (0..cfg.max_parallel)
            .map(|i| core.executor(&format!("client_executor_{i}")))
            .collect::<Result<Vec<_>, _>>()?;
        let rpc = core.rpc()?;
        let client = match &cfg.service_name {
            Some(name) => ExampleServiceClient::register_as(&rpc, name),
            None => ExampleServiceClient::register(&rpc),
        }
        .map_err(|e| Error::msg(format!("RegisterClientFunc failed: {e}")))?;
        self.setup = Some(Setup {
            plans: cfg.bench_plans,
            executors,
            client,
        });
        tracing::info!("Init succeeded.");
        Ok(())
    }

    fn start(&mut self) -> Result<(), Error> {
        let Some(setup) = self.setup.take() else {
            return Ok(());
        };
        // At 1 while the module runs; `shutdown` counts it down to 0, waking every
        // `stop.wait_timeout` (true: stopped) at once.
        let run = DynamicLatch::new();
        run.try_add(1);
        let stop = run.clone();
        // The plans run on a thread of the module's own (AimRT's run as a coroutine on
        // `client_statistics_executor`, which blocks no thread of it). As a `Task`, the
        // loop keeps the module's identity: its logs are the module's.
        let task = Task::new(move || main_loop(&setup, &stop));
        let handle = std::thread::Builder::new()
            .name("rpc_bench".into())
            .spawn(move || {
                task.run("rpc_bench");
            })
            .map_err(|e| Error::msg(format!("cannot start the benchmark thread: {e}")))?;
        self.runner = Some((run, handle));
        tracing::info!("Start succeeded.");
        Ok(())
    }

    fn shutdown(&mut self) {
        if let Some((run, handle)) = self.runner.take() {
            let _ = run.count_down(1);
            // It ends within a call's 3 s timeout.
            let _ = handle.join();
        }
        tracing::info!("Shutdown succeeded.");
    }
}

fn main_loop(setup: &Setup, stop: &DynamicLatch) {
    tracing::info!("Start Bench.");
    // AimRT's WaitForServiceServer: a call every second until one succeeds.
    let get_foo = setup.client.get_foo_data();
    loop {
        if stop.wait_timeout(Duration::from_secs(1)) {
            return;
        }
        let mut ctx = get_foo.new_context();
        ctx.set_timeout(Some(CALL_TIMEOUT));
        match get_foo.call(&mut ctx, GetFooDataReq { msg: "abc".into() }) {
            Ok(_) => break,
            Err(e) => tracing::warn!("Server is not available!!! ({e})"),
        }
    }
    for (i, plan) in setup.plans.iter().enumerate() {
        if stop.count() == 0 {
            return;
        }
        match run_plan(setup, plan, stop) {
            Ok(report) => tracing::info!("Benchmark plan {i} completed, report:\n{report}"),
            Err(e) => tracing::error!("Benchmark plan {i} failed: {e}"),
        }
        if stop.wait_timeout(Duration::from_secs(1)) {
            return;
        }
    }
    tracing::info!("Bench completed.");
}

/// The timeout of every call, as AimRT's.
const CALL_TIMEOUT: Duration = Duration::from_secs(3);

/// Runs one plan; the report's lines, as AimRT's (latencies of the calls that succeeded).
fn run_plan(setup: &Setup, plan: &Plan, stop: &DynamicLatch) -> Result<String, String> {
    let (tx, rx) = mpsc::channel::<Vec<u64>>();
    let begin = Instant::now();
    for w in 0..plan.parallel {
        let (tx, stop) = (tx.clone(), stop.clone());
        let client = setup.client.clone();
        let plan = plan.clone();
        let period = plan.freq.map(|f| Duration::from_secs_f64(1.0 / f));
        setup.executors[w]
            .execute(move || {
                let get_foo = client.get_foo_data();
                let msg = "x".repeat(plan.msg_size);
                let mut latencies = Vec::with_capacity(plan.msg_count.min(1 << 20));
                let mut due = Instant::now();
                for _ in 0..plan.msg_count {
                    if stop.count() == 0 {
                        break;
                    }
                    if let Some(p) = period {
                        // On a fixed schedule; a slow call does not push the next back.
                        if stop.wait_timeout(due.saturating_duration_since(Instant::now())) {
                            break;
                        }
                        due += p;
                    }
                    let mut ctx = get_foo.new_context();
                    ctx.set_timeout(Some(CALL_TIMEOUT));
                    let t = Instant::now();
                    if get_foo
                        .call(&mut ctx, GetFooDataReq { msg: msg.clone() })
                        .is_ok()
                    {
                        latencies.push(u64::try_from(t.elapsed().as_nanos()).unwrap_or(u64::MAX));
                    }
                }
                let _ = tx.send(latencies);
            })
            .map_err(|e| format!("client_executor_{w} refused the worker: {e}"))?;
    }
    drop(tx);
    let mut all: Vec<u64> = rx.iter().flatten().collect();
    let total = begin.elapsed();
    Ok(report(plan, total, &mut all))
}

/// AimRT's report of a plan from the latencies (ns) of its successful calls; `n/a`
/// latencies when none succeeded (AimRT's reads an empty list).
fn report(plan: &Plan, total: Duration, ok: &mut [u64]) -> String {
    ok.sort_unstable();
    let correct = ok.len();
    let total_count = plan.msg_count.saturating_mul(plan.parallel);
    let error_rate = if total_count == 0 {
        0.0
    } else {
        (total_count - correct.min(total_count)) as f64 / total_count as f64 * 100.0
    };
    let us = |ns: u64| format!("{}", ns as f64 / 1000.0);
    let at = |p: f64| match correct {
        0 => "n/a".to_owned(),
        n => us(ok[((n as f64 * p) as usize).min(n - 1)]),
    };
    let avg = match correct {
        0 => "n/a".to_owned(),
        n => us((ok.iter().map(|&l| u128::from(l)).sum::<u128>() / n as u128) as u64),
    };
    let mut out = format!("mode: {}\n", plan.perf_mode);
    if let Some(freq) = plan.freq {
        out += &format!("freq: {freq}\n");
    }
    out += &format!(
        "msg size: {}\nparallel: {}\nmsg count per co: {}\ntotal count: {total_count}\ntotal time: {} ms\ncorrect count: {correct}\nerror rate: {error_rate} %\n",
        plan.msg_size,
        plan.parallel,
        plan.msg_count,
        total.as_millis(),
    );
    if plan.freq.is_none() {
        out += &format!(
            "qps: {}\n",
            total_count as f64 / total.as_secs_f64().max(1e-9)
        );
    }
    out += &format!(
        "min latency: {} us\nmax latency: {} us\navg latency: {avg} us\np90 latency: {} us\np99 latency: {} us\np999 latency: {} us\n",
        ok.first().map_or("n/a".to_owned(), |&l| us(l)),
        ok.last().map_or("n/a".to_owned(), |&l| us(l)),
        at(0.9),
        at(0.99),
        at(0.999),
    );
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn plan(freq: Option<f64>) -> Plan {
        Plan {
            perf_mode: if freq.is_some() {
                "fixed-freq"
            } else {
                "bench"
            }
            .into(),
            msg_size: 256,
            parallel: 2,
            msg_count: 3,
            freq,
        }
    }

    fn line<'a>(report: &'a str, key: &str) -> &'a str {
        report
            .lines()
            .find_map(|l| l.strip_prefix(key))
            .unwrap_or_else(|| panic!("no '{key}' in {report}"))
    }

    #[test]
    fn plans_that_would_panic_overflow_or_never_end_are_refused() {
        let mut ok = plan(Some(0.5));
        assert_eq!(ok.check(2), Ok(()));
        let mut bench = plan(None);
        bench.freq = Some(7.0);
        assert_eq!(bench.check(2), Ok(()));
        assert_eq!(bench.freq, None, "a bench plan reads no freq");
        for (change, says) in [
            (
                Box::new(|p: &mut Plan| p.freq = Some(1e-300)) as Box<dyn Fn(&mut Plan)>,
                "freq",
            ),
            (Box::new(|p: &mut Plan| p.freq = Some(f64::NAN)), "freq"),
            (Box::new(|p: &mut Plan| p.freq = None), "freq"),
            (
                Box::new(|p: &mut Plan| p.perf_mode = "fast".into()),
                "'fast'",
            ),
            (Box::new(|p: &mut Plan| p.parallel = 0), "parallel is 0"),
            (Box::new(|p: &mut Plan| p.parallel = 3), "max_parallel (2)"),
            (Box::new(|p: &mut Plan| p.msg_size = usize::MAX), "msg_size"),
        ] {
            let mut p = plan(Some(10.0));
            change(&mut p);
            let err = p.check(2).unwrap_err();
            assert!(err.contains(says), "{err}");
        }
    }

    #[test]
    fn reports_have_aimrts_lines_and_count_only_successful_calls() {
        // 6 calls, 4 succeeded: 1, 2, 3, 10 µs.
        let mut ok = vec![10_000, 1_000, 3_000, 2_000];
        let r = report(&plan(None), Duration::from_millis(2), &mut ok);
        let keys: Vec<&str> = r.lines().map(|l| l.split(": ").next().unwrap()).collect();
        assert_eq!(
            keys,
            [
                "mode",
                "msg size",
                "parallel",
                "msg count per co",
                "total count",
                "total time",
                "correct count",
                "error rate",
                "qps",
                "min latency",
                "max latency",
                "avg latency",
                "p90 latency",
                "p99 latency",
                "p999 latency"
            ]
        );
        assert_eq!(line(&r, "mode: "), "bench");
        assert_eq!(line(&r, "total count: "), "6");
        assert_eq!(line(&r, "total time: "), "2 ms");
        assert_eq!(line(&r, "correct count: "), "4");
        assert_eq!(line(&r, "error rate: "), "33.33333333333333 %");
        assert_eq!(line(&r, "qps: "), "3000");
        assert_eq!(line(&r, "min latency: "), "1 us");
        assert_eq!(line(&r, "avg latency: "), "4 us");
        assert_eq!(line(&r, "p90 latency: "), "10 us");
        let r = report(&plan(Some(1000.0)), Duration::from_millis(2), &mut ok);
        assert_eq!(line(&r, "mode: "), "fixed-freq");
        assert_eq!(line(&r, "freq: "), "1000");
        assert!(!r.contains("qps"), "{r}");
    }

    #[test]
    fn a_plan_where_no_call_succeeded_reports_no_latency() {
        let r = report(&plan(None), Duration::from_millis(5), &mut []);
        assert_eq!(line(&r, "correct count: "), "0");
        assert_eq!(line(&r, "error rate: "), "100 %");
        for key in ["min", "max", "avg", "p90", "p99", "p999"] {
            assert_eq!(line(&r, &format!("{key} latency: ")), "n/a us");
        }
    }
}
