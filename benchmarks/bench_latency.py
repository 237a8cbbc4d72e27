"""What late measurements cost (issue 30): the estimate of 10^4 runs of `pipeline/latency.toml`
(the paper's example, s3 late) under each policy, against the same runs with every sensor on
time.

    .venv/bin/python benchmarks/bench_latency.py                    # 10^4 runs, 2 s late
    .venv/bin/python benchmarks/bench_latency.py --runs 2000 --latency 5 --repeats 3

Timed, the fastest of `--repeats` (a shared machine only adds time), for each architecture:
`driver.estimate_block` of the runs with a fresh plan cache (compiling the plan and applying it,
what `fusionlog estimate` does per block), and the exact analysis of its plan
(`core.exact.analyse`, what the evaluation adds). The simulation is not timed. Random delays
(`--random`: s3's latency uniform in [0, 2 x latency]) make every run's plan its own.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _best(fn, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=10_000)
    ap.add_argument("--latency", type=float, default=2.0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--random", action="store_true")
    args = ap.parse_args()

    import fusionlog as fl
    from fusionlog.core.exact import analyse
    from fusionlog.core.timing import SensorTiming
    from fusionlog.driver import PlanCache, estimate_block

    sc = fl.load(ROOT / "pipeline" / "latency.toml")
    sim = fl.simulate(sc, runs=args.runs)
    z = sim.z
    lat = (0.0, 2 * args.latency) if args.random else (args.latency, args.latency)
    s3 = dataclasses.replace(sc.system.sensors[2], timing=SensorTiming(latency=lat))
    late_sys = dataclasses.replace(sc.system, sensors=(*sc.system.sensors[:2], s3))
    on_time = dataclasses.replace(
        sc.system, sensors=(*sc.system.sensors[:2], dataclasses.replace(s3, timing=SensorTiming()))
    )
    from fusionlog.core.latency import draw_arrivals

    arrivals = draw_arrivals(late_sys, sim.times, sc.seed, 0, args.runs)
    K = len(sim.times) - 1
    print(
        f"pipeline/latency.toml: {args.runs} runs x {K + 1} instants, s3 "
        + (
            f"latency uniform in [0, {2 * args.latency:g}] s"
            if args.random
            else f"{args.latency:g} s late"
        )  # fmt: skip
    )
    cols = ("estimate s", "ratio", "exact s", "ratio")
    print(f"{'policy':10s} {'arch':7s} " + " ".join(f"{c:>10s}" for c in cols))
    base: dict[str, tuple[float, float]] = {}
    for late in ("on time", "reprocess", "retrodict", "neglect"):
        system = on_time if late == "on time" else dataclasses.replace(late_sys, late=late)
        for arch in ("CKF", "SKF:s3", "MSC"):

            def estimate(system=system, arch=arch) -> PlanCache:
                cache = PlanCache(system, K, clock=sim.times)
                cache.arrivals = arrivals
                estimate_block(system, [arch], z, cache=cache)
                return cache

            t_est = _best(estimate, args.repeats)
            cache = estimate()
            plan = cache.block_plans([arch], z)[0][arch]
            t_ex = _best(lambda plan=plan, system=system: analyse(plan, system), args.repeats)
            if late == "on time":
                base[arch] = (t_est, t_ex)
            b = base.get(arch, (np.nan, np.nan))
            figures = (t_est, t_est / b[0], t_ex, t_ex / b[1])
            print(f"{late:10s} {arch:7s} " + " ".join(f"{f:10.3f}" for f in figures))


if __name__ == "__main__":
    main()
