//! Where a side of a two-process scenario spends its time, thread by thread, from the
//! kernel's scheduler statistics (`/proc/<pid>/task/<tid>/schedstat`: nanoseconds on a
//! CPU, nanoseconds runnable but waiting for one, and times scheduled) and each thread's
//! name (`comm`). Read around a measured phase, of this process or of a child.

use std::collections::BTreeMap;

/// One thread at one moment.
#[derive(Debug, Clone)]
pub(crate) struct Thread {
    name: String,
    run_ns: u64,
    wait_ns: u64,
    slices: u64,
}

/// Every thread of a process at one moment, by thread id.
pub(crate) type Snapshot = BTreeMap<u64, Thread>;

/// The threads of `pid` (this process: `None`). A thread that ended between listing and
/// reading, or a kernel without schedstat, is left out: an empty snapshot says nothing
/// could be read.
pub(crate) fn snapshot(pid: Option<u32>) -> Snapshot {
    let dir = match pid {
        Some(pid) => format!("/proc/{pid}/task"),
        None => "/proc/self/task".to_owned(),
    };
    let mut out = Snapshot::new();
    let Ok(entries) = std::fs::read_dir(&dir) else {
        return out;
    };
    for e in entries.flatten() {
        let Some(tid) = e.file_name().to_str().and_then(|t| t.parse().ok()) else {
            continue;
        };
        let read = |f: &str| std::fs::read_to_string(e.path().join(f)).ok();
        let (Some(name), Some(stat)) = (read("comm"), read("schedstat")) else {
            continue;
        };
        let mut n = stat.split_whitespace().map(|v| v.parse::<u64>().ok());
        if let (Some(Some(run_ns)), Some(Some(wait_ns)), Some(Some(slices))) =
            (n.next(), n.next(), n.next())
        {
            out.insert(
                tid,
                Thread {
                    name: name.trim().to_owned(),
                    run_ns,
                    wait_ns,
                    slices,
                },
            );
        }
    }
    out
}

/// The id of the calling thread (from `/proc/thread-self`), if it can be read.
pub(crate) fn this_thread() -> Option<u64> {
    let link = std::fs::read_link("/proc/thread-self").ok()?;
    link.file_name()?.to_str()?.parse().ok()
}

/// Time a message of one group of threads.
#[derive(Debug, Clone, Copy, Default, serde::Serialize)]
pub(crate) struct Cost {
    /// µs on a CPU.
    pub(crate) run_us: f64,
    /// µs runnable but waiting for a CPU.
    pub(crate) wait_us: f64,
    /// Times scheduled onto a CPU.
    pub(crate) slices: f64,
}

/// A side's time a message: the thread that publishes and waits for the echoes, zenoh's
/// receive threads (`rx-*`), its transmit threads (`tx-*`), and every other thread.
#[derive(Debug, Clone, Copy, Default, serde::Serialize)]
pub(crate) struct SideCost {
    pub(crate) publisher: Cost,
    pub(crate) rx: Cost,
    pub(crate) tx: Cost,
    pub(crate) other: Cost,
}

/// What each group of threads did between `before` and `after`, a message of `n`;
/// `publisher` is the id of the thread that published. A thread that started in between
/// counts from zero. `None` when either snapshot is empty.
pub(crate) fn cost(
    before: &Snapshot,
    after: &Snapshot,
    publisher: u64,
    n: u64,
) -> Option<SideCost> {
    if before.is_empty() || after.is_empty() || n == 0 {
        return None;
    }
    // Sums in ns and slices per group (publisher, rx, tx, other), divided once at the end.
    let mut sums = [[0u64; 3]; 4];
    for (tid, a) in after {
        let b = before.get(tid);
        let since = |now: u64, then: fn(&Thread) -> u64| now.saturating_sub(b.map_or(0, then));
        let group = if *tid == publisher {
            0
        } else if a.name.starts_with("rx-") {
            1
        } else if a.name.starts_with("tx-") {
            2
        } else {
            3
        };
        sums[group][0] += since(a.run_ns, |t| t.run_ns);
        sums[group][1] += since(a.wait_ns, |t| t.wait_ns);
        sums[group][2] += since(a.slices, |t| t.slices);
    }
    let n = n as f64;
    let [publisher, rx, tx, other] = sums.map(|[run, wait, slices]| Cost {
        run_us: run as f64 / (1e3 * n),
        wait_us: wait as f64 / (1e3 * n),
        slices: slices as f64 / n,
    });
    let side = SideCost {
        publisher,
        rx,
        tx,
        other,
    };
    Some(side)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn thread(name: &str, run_ns: u64, wait_ns: u64, slices: u64) -> Thread {
        Thread {
            name: name.into(),
            run_ns,
            wait_ns,
            slices,
        }
    }

    #[test]
    fn threads_are_grouped_by_role_and_counted_a_message() {
        let before = Snapshot::from([
            (10, thread("ping", 1_000, 0, 1)),
            (11, thread("rx-0", 5_000, 100, 3)),
            (12, thread("tx-0", 0, 0, 0)),
        ]);
        let after = Snapshot::from([
            (10, thread("ping", 21_000, 2_000, 11)),
            (11, thread("rx-0", 15_000, 100, 7)),
            (12, thread("tx-0", 4_000, 0, 2)),
            (13, thread("rx-1", 10_000, 0, 2)),
            (14, thread("aimrt_log", 2_000, 0, 1)),
        ]);
        let c = cost(&before, &after, 10, 10).unwrap();
        assert_eq!(
            (c.publisher.run_us, c.publisher.wait_us, c.publisher.slices),
            (2.0, 0.2, 1.0)
        );
        // rx-0's difference and the new rx-1 from zero.
        assert_eq!((c.rx.run_us, c.rx.wait_us, c.rx.slices), (2.0, 0.0, 0.6));
        assert_eq!((c.tx.run_us, c.tx.slices), (0.4, 0.2));
        assert_eq!(c.other.run_us, 0.2);
        assert!(cost(&Snapshot::new(), &after, 10, 10).is_none());
    }

    #[test]
    fn this_process_and_this_thread_can_be_read() {
        let me = this_thread().expect("/proc/thread-self");
        let now = snapshot(None);
        let mine = now
            .get(&me)
            .expect("this thread in its own process's snapshot");
        assert!(mine.slices > 0, "{mine:?}");
        assert!(snapshot(Some(u32::MAX)).is_empty());
    }
}
