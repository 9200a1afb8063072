#!/usr/bin/env python3
"""Gathers issue 21's targets from the JSON files of several `aimrt-bench` runs into one
markdown table (a value in bold misses its bound in that run).

    python3 benches/scripts/targets.py run1.json run2.json run3.json
"""
import json
import sys

EXECS = ["simple_thread", "asio_thread(2)", "tbb_thread(2)", "asio_strand"]


def rows(run):
    out = {}
    for shape in ["burst", "drain", "work_1us"]:
        for r in run.get(f"throughput_{shape}", {}).get("paired_ratios", []):
            if r.get("target") is None:
                continue
            key = f"{shape}: {r['candidate']} ÷ {r['baseline'].split(' [')[0]}"
            out[key] = (r["ratio"]["median"], f">= {r['target']}", r["ratio"]["median"] >= r["target"], f"{r['ratio']['median']:.2f}")
    for cond, table in run.get("wake_latency_us", {}).items():
        base = table["condvar(1)"]["p50"]
        for e in EXECS:
            p = table[e]["p50"]
            out[f"wake {cond}: {e} p50 ÷ condvar"] = (p / base, "<= 1.2", p <= 1.2 * base, f"{p / base:.2f} ({p:.1f}/{base:.1f})")
    for label, table in run.get("timer_overshoot_us", {}).items():
        base = table["timerfd timer thread"]
        for e in ["asio_thread(1)", "asio_strand"]:
            t = table[e]
            out[f"timer {label}: {e} p50"] = (t["p50"], "<= timerfd + 5", t["p50"] <= base["p50"] + 5, f"{t['p50']:.1f} (timerfd {base['p50']:.1f})")
            out[f"timer {label}: {e} p99"] = (t["p99"], "<= timerfd × 1.2", t["p99"] <= base["p99"] * 1.2, f"{t['p99']:.1f} (timerfd {base['p99']:.1f})")
        for name, t in table.items():
            if name in ("asio_thread(1)", "asio_strand") or name.startswith("time_wheel"):
                out[f"timer {label}: {name} min"] = (t["min"], ">= 0", t["min"] >= 0, f"{t['min']:.1f}")
    for name, v in run.get("idle_cpu_percent", {}).items():
        out[f"idle {name} %"] = (v, "<= 1", v <= 1.0, f"{v:.3f}")
    alloc = run.get("allocations", {})
    if alloc:
        out["alloc Task::new"] = (alloc["task_new"], "0", alloc["task_new"] == 0, str(alloc["task_new"]))
        for name, v in alloc["per_execute"].items():
            out[f"alloc per execute {name}"] = (v, "<= 0.05", v <= 0.05, f"{v:.4f}")
    abi = run.get("abi")
    if abi:
        a = abi["added_ns_per_execute"]["median"]
        out["abi added ns/execute"] = (a, "<= 5", a <= 5, f"{a:+.1f}")
        r = abi["burst_ratio_so_over_linked"]["median"]
        out["abi .so/linked burst"] = (r, ">= 0.9", r >= 0.9, f"{r:.2f}")
    out["refused"] = (run.get("refused", 0), "0", run.get("refused", 0) == 0, str(run.get("refused", 0)))
    return out


def main():
    runs = [rows(json.load(open(p))) for p in sys.argv[1:]]
    keys = list(runs[0].keys())
    head = " | ".join(f"run {i + 1}" for i in range(len(runs)))
    print(f"| target | {head} | bound |\n|---|{'---|' * len(runs)}---|")
    misses = 0
    for k in keys:
        cells = []
        for r in runs:
            if k not in r:
                cells.append("—")
                continue
            _, _, ok, text = r[k]
            cells.append(text if ok else f"**{text}**")
            misses += 0 if ok else 1
        print(f"| {k} | {' | '.join(cells)} | {runs[0][k][1]} |")
    print(f"\nMisses: {misses}")


if __name__ == "__main__":
    main()
