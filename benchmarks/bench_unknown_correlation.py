"""The rules that do not know the correlation, per run (benchmarks/README.md "Unknown
correlation"): EI and ICI against CI on per-run plans (dropouts), the estimates and the exact
analysis, as ratios to CI's time.

    .venv/bin/python benchmarks/bench_unknown_correlation.py             # M = 2000, 5 repeats
    .venv/bin/python benchmarks/bench_unknown_correlation.py --runs 500 --repeats 3

The workload is pipeline/unknown_correlation.toml (three local filters, one losing a fifth of
its measurements, K = 30): each run has its own pattern, so every rule is evaluated once per
measurement history (`HistoryNodes`) and the exact analysis once per node. Per architecture:
`build_plan` on the runs' masks (the rule at every node), `run_plan` (the estimates), and
`core.exact.analyse` (each run's exact statistics, with the bound check's ratio). Each figure
is the median wall time of `--repeats` rounds, the tasks interleaved (`interleaved`).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

import fusionlog as fl
from fusionlog.core.architectures import build_plan, run_plan
from fusionlog.core.exact import analyse

ROOT = Path(__file__).resolve().parents[1]
ARCHS = ("CI", "ICI", "EI")


def interleaved(tasks: dict[str, Callable[[], Any]], repeats: int) -> dict[str, float]:
    """Median wall seconds of each task over `repeats` rounds, each round timing every task
    once in turn (after one untimed round): a machine shared with other work slows the tasks
    of a round alike, so the ratios hold better than the seconds."""
    for fn in tasks.values():
        fn()
    times: dict[str, list[float]] = {k: [] for k in tasks}
    for _ in range(repeats):
        for k, fn in tasks.items():
            t0 = time.perf_counter()
            fn()
            times[k].append(time.perf_counter() - t0)
    return {k: statistics.median(v) for k, v in times.items()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=2000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)

    sc = fl.load(ROOT / "pipeline" / "unknown_correlation.toml")
    sim = fl.simulate(sc, runs=args.runs)
    z = np.concatenate([sim.measurements[s.name] for s in sc.system.sensors], axis=-1)
    system = sc.system.on_times(sim.times)
    K = z.shape[1] - 1
    present = ~np.isnan(z)
    tasks: dict[str, Callable[[], Any]] = {}
    for a in ARCHS:
        plan = build_plan(system, a, K, present, history_nodes=True)
        full = build_plan(system, a, K, present)
        tasks[a, "plan"] = lambda a=a: build_plan(system, a, K, present, history_nodes=True)
        tasks[a, "estimate"] = lambda p=plan: run_plan(p, z)
        tasks[a, "exact"] = lambda p=full: analyse(p, system).bound
    med = interleaved(tasks, args.repeats)
    out = {a: {k: med[a, k] for k in ("plan", "estimate", "exact")} for a in ARCHS}
    print(f"{sc.name}: M = {args.runs} runs with their own patterns, K = {K}; median of "
          f"{args.repeats} (seconds, and the ratio to CI's)")  # fmt: skip
    print(f"{'':6}{'plan':>16}{'estimate':>18}{'exact + bound':>20}")
    for a in ARCHS:
        cells = [f"{out[a][k]:8.3f} ({out[a][k] / out['CI'][k]:4.2f}x)" for k in out[a]]
        print(f"{a:<6}" + "".join(f"{c:>18}" for c in cells))
    if args.json is not None:
        args.json.write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
