//! Scenario `scaling` (`--threads 1,2,4,8,16`): burst throughput of the pools and their
//! baselines with N workers, fed by one producer and by N producers, for a many-core
//! machine. Not part of the default run: it is asked for with `--threads`.

use std::time::Instant;

use crate::pools::{self, CondvarPool, CrossbeamPool, Take, Target, MAX_Q};
use crate::throughput::Done;

/// The targets with `n` workers: (name, how to build one).
fn targets(n: usize) -> Vec<(String, Box<dyn Fn() -> Target>)> {
    let mut out: Vec<(String, Box<dyn Fn() -> Target>)> = vec![
        (
            format!("crossbeam({n})"),
            Box::new(move || Target::Crossbeam(CrossbeamPool::new(n))),
        ),
        (
            format!("swap queue({n}) [AimRT model]"),
            Box::new(move || Target::Condvar(CondvarPool::new(n, Take::Batch))),
        ),
    ];
    for ty in ["asio_thread", "tbb_thread"] {
        out.push((
            format!("{ty}({n})"),
            Box::new(move || {
                // asio_thread has no queue_threshold; tbb_thread's is raised out of the way.
                let options = match ty {
                    "tbb_thread" => format!(r#"{{"thread_num": {n}, {MAX_Q}}}"#),
                    _ => format!(r#"{{"thread_num": {n}}}"#),
                };
                let e = pools::executor(ty, "scaling", &options, vec![]);
                Target::Executor(e, vec![e])
            }),
        ));
    }
    if n == 1 {
        out.push(("simple_thread".to_owned(), Box::new(pools::simple_thread)));
    }
    out
}

/// Tasks per second: `producers` threads each submit `per_producer` tiny tasks at once.
fn burst(t: &Target, producers: usize, per_producer: usize) -> f64 {
    let total = producers * per_producer;
    let (done, rx) = Done::new(total);
    let start = Instant::now();
    std::thread::scope(|s| {
        for _ in 0..producers {
            let done = done.clone();
            s.spawn(move || {
                for _ in 0..per_producer {
                    let d = done.clone();
                    t.submit(move || d.one());
                }
            });
        }
    });
    rx.recv_timeout(std::time::Duration::from_secs(120))
        .expect("scaling: tasks did not complete within 120 s");
    total as f64 / start.elapsed().as_secs_f64()
}

/// One row per (workers, producers): the median of `rounds` rates per target, M tasks/s.
pub(crate) fn run(threads: &[usize], tasks: usize, rounds: usize) -> (String, serde_json::Value) {
    use std::fmt::Write as _;
    let mut md = String::from(
        "\n### Scaling: burst, M tasks/s (median of rounds)\n\n| workers | producers | target | M tasks/s |\n|---|---|---|---|\n",
    );
    let mut rows = Vec::new();
    for &n in threads {
        for producers in if n == 1 { vec![1] } else { vec![1, n] } {
            for (name, make) in targets(n) {
                let mut rates: Vec<f64> = (0..rounds)
                    .map(|_| {
                        let t = make();
                        burst(&t, producers, 10_000 / producers + 1);
                        let r = burst(&t, producers, tasks / producers);
                        t.stop();
                        r
                    })
                    .collect();
                rates.sort_by(f64::total_cmp);
                let median = rates[rates.len() / 2] / 1e6;
                let _ = writeln!(md, "| {n} | {producers} | {name} | {median:.2} |");
                rows.push(serde_json::json!({
                    "workers": n, "producers": producers, "target": name, "m_tasks_per_s": median
                }));
            }
        }
    }
    (md, serde_json::Value::Array(rows))
}
