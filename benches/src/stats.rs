//! Summaries: median, min, max, percentiles, paired ratios; and the quiet gate.

use std::time::{Duration, Instant};

/// How much a scenario measures: `--quick`, and `--rounds N` in place of its own count of
/// measured rounds (a warm-up round, where the scenario has one, still comes first).
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct Scale {
    pub(crate) quick: bool,
    pub(crate) rounds: Option<usize>,
}

impl Scale {
    /// The measured rounds: `--rounds`, else `quick` or `full`.
    pub(crate) fn rounds(self, quick: usize, full: usize) -> usize {
        self.rounds.unwrap_or(if self.quick { quick } else { full })
    }
}

/// Median, min and max of `v`.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub(crate) struct Summary {
    pub(crate) median: f64,
    pub(crate) min: f64,
    pub(crate) max: f64,
}

impl Summary {
    /// No figures.
    pub(crate) fn none() -> Summary {
        summary(&[])
    }
}

pub(crate) fn summary(v: &[f64]) -> Summary {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    if s.is_empty() {
        return Summary {
            median: f64::NAN,
            min: f64::NAN,
            max: f64::NAN,
        };
    }
    let mid = s.len() / 2;
    let median = if s.len() % 2 == 1 {
        s[mid]
    } else {
        (s[mid - 1] + s[mid]) / 2.0
    };
    Summary {
        median,
        min: s[0],
        max: s[s.len() - 1],
    }
}

/// The `p`-th percentile (0..=100) of sorted `s`.
pub(crate) fn percentile(s: &[f64], p: f64) -> f64 {
    if s.is_empty() {
        return f64::NAN;
    }
    let idx = ((p / 100.0) * (s.len() - 1) as f64).round() as usize;
    s[idx.min(s.len() - 1)]
}

/// Ratios of candidate to baseline, round by round.
pub(crate) fn paired(candidate: &[f64], baseline: &[f64]) -> Summary {
    let r: Vec<f64> = candidate.iter().zip(baseline).map(|(c, b)| c / b).collect();
    summary(&r)
}

fn cpu_jiffies() -> Option<(u64, u64)> {
    // (busy, total) over all CPUs from /proc/stat.
    let text = std::fs::read_to_string("/proc/stat").ok()?;
    let line = text.lines().next()?;
    let v: Vec<u64> = line
        .split_whitespace()
        .skip(1)
        .filter_map(|x| x.parse().ok())
        .collect();
    let total: u64 = v.iter().sum();
    let idle = v.get(3).copied().unwrap_or(0) + v.get(4).copied().unwrap_or(0);
    Some((total - idle, total))
}

/// Seconds of CPU this process has used.
pub(crate) fn process_cpu() -> f64 {
    nix::time::clock_gettime(nix::time::ClockId::CLOCK_PROCESS_CPUTIME_ID)
        .map(|t| t.tv_sec() as f64 + t.tv_nsec() as f64 * 1e-9)
        .unwrap_or(0.0)
}

/// Cores used by other processes over `window`.
pub(crate) fn foreign_load(window: Duration) -> f64 {
    // /proc/stat counts in USER_HZ, which Linux fixes at 100 for user space.
    let ticks = 100.0;
    let (Some((b0, _)), c0, t0) = (cpu_jiffies(), process_cpu(), Instant::now()) else {
        return 0.0;
    };
    std::thread::sleep(window);
    let Some((b1, _)) = cpu_jiffies() else {
        return 0.0;
    };
    let secs = t0.elapsed().as_secs_f64();
    let busy = (b1 - b0) as f64 / ticks;
    let own = process_cpu() - c0;
    ((busy - own) / secs).max(0.0)
}

/// Runs a candidate and its baseline back to back, the candidate first in even rounds
/// and the baseline first in odd ones, so neither always meets the machine the other
/// just warmed or loaded.
pub(crate) fn alternate<A, B, E>(
    round: usize,
    candidate: impl FnOnce() -> Result<A, E>,
    baseline: impl FnOnce() -> Result<B, E>,
) -> Result<(A, B), E> {
    if round % 2 == 0 {
        let a = candidate()?;
        Ok((a, baseline()?))
    } else {
        let b = baseline()?;
        Ok((candidate()?, b))
    }
}

/// Waits (up to `max_wait`) until other processes use under 0.15 core; returns the last
/// measured foreign load.
pub(crate) fn quiet_gate(max_wait: Duration) -> f64 {
    let end = Instant::now() + max_wait;
    loop {
        let load = foreign_load(Duration::from_millis(300));
        if load < 0.15 || Instant::now() >= end {
            return load;
        }
    }
}

/// Every target that missed in this run, as "what: measured vs bound" lines.
static MISSES: std::sync::Mutex<Vec<String>> = std::sync::Mutex::new(Vec::new());

/// Records whether a target holds (a miss is remembered for `--enforce`) and returns the
/// table cell: `yes` or `**no**`.
pub(crate) fn verdict(holds: bool, what: impl FnOnce() -> String) -> &'static str {
    if holds {
        "yes"
    } else {
        MISSES
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .push(what());
        "**no**"
    }
}

/// The targets that missed so far.
pub(crate) fn misses() -> Vec<String> {
    MISSES.lock().unwrap_or_else(|e| e.into_inner()).clone()
}
