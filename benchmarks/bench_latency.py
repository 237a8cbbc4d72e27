"""What late measurements cost (issue 30): the estimate of 10^4 runs of `pipeline/latency.toml`
(the paper's example, s3 late) under each policy, against the same runs with every sensor on
time.

    .venv/bin/python benchmarks/bench_latency.py                    # 10^4 runs, 2 s late
    .venv/bin/python benchmarks/bench_latency.py --runs 2000 --latency 5 --repeats 3
    .venv/bin/python benchmarks/bench_latency.py --horizons 1000,10000,100000 --runs 1

`--horizons`: the plan's memory and time against the horizon K (s3 `--latency` s late,
fixed): for each K, the plan's distinct arrays (bytes; the steady shortcut repeats one step's
map, so they stop growing once it triggers), the time to build it and to estimate `--runs`
runs with it (readings drawn at random: the time does not depend on their values).

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
    ap.add_argument("--horizons", type=str, default="")
    ap.add_argument("--archs", type=str, default="CKF,HKF,MSC")
    args = ap.parse_args()
    if args.horizons:
        horizons(args)
        return

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
    from fusionlog.core.late_policy import draw_arrivals

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


def plan_bytes(plan) -> int:
    """The bytes of a plan's distinct step arrays (a repeated map counted once)."""
    seen: dict[int, int] = {}
    for st in plan.steps:
        for a in (st.T, st.U, st.O, st.P, st.D):
            a = getattr(a, "blocks", a)  # a BlockDiagonal's blocks
            if isinstance(a, np.ndarray):
                seen[id(a)] = a.nbytes
    return sum(seen.values())


def horizons(args) -> None:
    import fusionlog as fl
    from fusionlog.core.timing import SensorTiming
    from fusionlog.driver import PlanCache, estimate_block

    sc = fl.load(ROOT / "pipeline" / "latency.toml")
    s3 = dataclasses.replace(
        sc.system.sensors[2], timing=SensorTiming(latency=(args.latency, args.latency))
    )
    system = dataclasses.replace(sc.system, sensors=(*sc.system.sensors[:2], s3))
    rng = np.random.default_rng(0)
    print(f"pipeline/latency.toml, s3 {args.latency:g} s late, {args.runs} run(s)")
    print(f"{'arch':7s} {'K':>8s} {'plan MiB':>9s} {'steps':>7s} {'build s':>8s} {'est. s':>8s}")
    for K in (int(k) for k in args.horizons.split(",")):
        times = np.arange(K + 1) * system.dt
        z = 100 + rng.normal(size=(args.runs, K + 1, system.m))
        for arch in args.archs.split(","):
            cache = PlanCache(system, K, clock=times)
            t0 = time.perf_counter()
            plan = cache.plan(arch)
            t_build = time.perf_counter() - t0
            distinct = len({id(st) for st in plan.steps})
            t_est = _best(lambda a=arch, c=cache, z=z: estimate_block(system, [a], z, cache=c), 1)
            mib = plan_bytes(plan) / 2**20
            print(f"{arch:7s} {K:8d} {mib:9.2f} {distinct:7d} {t_build:8.2f} {t_est:8.2f}")


if __name__ == "__main__":
    main()
