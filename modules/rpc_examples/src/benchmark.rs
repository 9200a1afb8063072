//! `BenchmarkRpcClientModule`: AimRT's RPC benchmark client.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use aimrt_plugin_api::{CoreRef, Error, ExecutorRef, LogLevel, Logger, Module, ModuleInfo};
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

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct Config {
    max_parallel: usize,
    bench_plans: Vec<Plan>,
    #[serde(default)]
    service_name: Option<String>,
}

/// Runs `bench_plans` one after another from `start`: each plan's `parallel` workers call
/// `GetFooData` `msg_count` times each on `client_executor_<i>` (back to back, or at
/// `freq` Hz), and the module logs AimRT's `Benchmark plan <i> completed, report:` block.
#[derive(Debug, Default)]
pub struct BenchmarkRpcClientModule {
    setup: Option<Setup>,
    runner: Option<(Arc<AtomicBool>, JoinHandle<()>)>,
}

#[derive(Debug)]
struct Setup {
    plans: Vec<Plan>,
    executors: Vec<ExecutorRef>,
    client: ExampleServiceClient,
    /// The module's logger: the plans run on a thread of the module's own.
    logger: Logger,
}

impl Module for BenchmarkRpcClientModule {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("BenchmarkRpcClientModule")
    }

    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let cfg: Config = core.config()?;
        for (i, p) in cfg.bench_plans.iter().enumerate() {
            if p.perf_mode != "bench" && p.perf_mode != "fixed-freq" {
                return Err(Error::msg(format!(
                    "bench_plans[{i}].perf_mode is '{}'; it must be bench or fixed-freq",
                    p.perf_mode
                )));
            }
            if p.parallel == 0 || p.parallel > cfg.max_parallel {
                return Err(Error::msg(format!(
                    "bench_plans[{i}].parallel is {}; it must be in 1 ..= max_parallel ({})",
                    p.parallel, cfg.max_parallel
                )));
            }
            if p.perf_mode == "fixed-freq" && !p.freq.is_some_and(|f| f.is_finite() && f > 0.0) {
                return Err(Error::msg(format!(
                    "bench_plans[{i}] is fixed-freq and needs a positive freq (calls per second per worker)"
                )));
            }
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
            logger: core.logger(),
        });
        tracing::info!("Init succeeded.");
        Ok(())
    }

    fn start(&mut self) -> Result<(), Error> {
        let Some(setup) = self.setup.take() else {
            return Ok(());
        };
        let run = Arc::new(AtomicBool::new(true));
        let running = run.clone();
        let handle = std::thread::Builder::new()
            .name("rpc_bench".into())
            .spawn(move || {
                for (i, plan) in setup.plans.iter().enumerate() {
                    if !running.load(Ordering::SeqCst) {
                        break;
                    }
                    match run_plan(&setup, plan, &running) {
                        Ok(report) => setup.logger.log(
                            LogLevel::Info,
                            &format!("Benchmark plan {i} completed, report:\n{report}"),
                        ),
                        Err(e) => setup
                            .logger
                            .log(LogLevel::Error, &format!("Benchmark plan {i} failed: {e}")),
                    }
                }
                setup.logger.log(LogLevel::Info, "Benchmark completed.");
            })
            .map_err(|e| Error::msg(format!("cannot start the benchmark thread: {e}")))?;
        self.runner = Some((run, handle));
        tracing::info!("Start succeeded.");
        Ok(())
    }

    fn shutdown(&mut self) {
        if let Some((run, handle)) = self.runner.take() {
            run.store(false, Ordering::SeqCst);
            let _ = handle.join();
        }
        tracing::info!("Shutdown succeeded.");
    }
}

/// Runs one plan; the report lines.
fn run_plan(setup: &Setup, plan: &Plan, running: &Arc<AtomicBool>) -> Result<String, String> {
    let (tx, rx) = mpsc::channel::<(Vec<f64>, usize)>();
    let begin = Instant::now();
    for w in 0..plan.parallel {
        let (tx, running) = (tx.clone(), running.clone());
        let client = setup.client.clone();
        let plan = plan.clone();
        let period = plan.freq.map(|f| Duration::from_secs_f64(1.0 / f));
        setup.executors[w]
            .execute(move || {
                let get_foo = client.get_foo_data();
                let msg = "x".repeat(plan.msg_size);
                let mut latencies = Vec::with_capacity(plan.msg_count);
                let mut errors = 0;
                let start = Instant::now();
                for n in 0..plan.msg_count {
                    if !running.load(Ordering::SeqCst) {
                        break;
                    }
                    if let Some(p) = period {
                        let due = start + p * n as u32;
                        let now = Instant::now();
                        if due > now {
                            std::thread::sleep(due - now);
                        }
                    }
                    let mut ctx = get_foo.new_context();
                    ctx.set_timeout(Some(Duration::from_secs(3)));
                    let t = Instant::now();
                    let r = get_foo.call(&mut ctx, GetFooDataReq { msg: msg.clone() });
                    latencies.push(t.elapsed().as_secs_f64() * 1e6);
                    if r.is_err() {
                        errors += 1;
                    }
                }
                let _ = tx.send((latencies, errors));
            })
            .map_err(|e| format!("client_executor_{w} refused the worker: {e}"))?;
    }
    drop(tx);
    let mut all = Vec::new();
    let mut errors = 0;
    for (lat, e) in rx.iter() {
        all.extend(lat);
        errors += e;
    }
    let total = begin.elapsed();
    if all.is_empty() {
        return Err("no call was made".into());
    }
    all.sort_by(f64::total_cmp);
    let pct = |p: f64| all[((all.len() as f64 * p) as usize).min(all.len() - 1)];
    let avg = all.iter().sum::<f64>() / all.len() as f64;
    Ok(format!(
        "perf mode: {}\nmsg size: {}\nparallel: {}\nmsg count per worker: {}\ntotal count: {}\ntotal time: {:.3} ms\nerror rate: {:.2} %\nqps: {:.0}\nmin latency: {:.3} us\nmax latency: {:.3} us\navg latency: {:.3} us\np90 latency: {:.3} us\np99 latency: {:.3} us\np999 latency: {:.3} us",
        plan.perf_mode,
        plan.msg_size,
        plan.parallel,
        plan.msg_count,
        all.len(),
        total.as_secs_f64() * 1e3,
        errors as f64 * 100.0 / all.len() as f64,
        all.len() as f64 / total.as_secs_f64(),
        all[0],
        all[all.len() - 1],
        avg,
        pct(0.90),
        pct(0.99),
        pct(0.999),
    ))
}
