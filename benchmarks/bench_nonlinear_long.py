"""A long one-run nonlinear log (issue 34, "Hour-long logs"): each architecture's estimate of one
run of the radar scenario, per instant, side by side with FilterPy's EKF loop on the same log.

The log: `pipeline/radar_tracking.toml` (two range-bearing radars, constant-velocity target,
n = 4, m = 4), one run of `--instants` instants simulated in this process (`core.simulate`).

fusionlog: each architecture of the scenario (CKF, HKF, MSC-GMF, MSC, SKF, CI, AVG, FBS) through
`core.nonlinear.long_log.estimate_blocks`, the path a one-run log longer than a block of time
takes in `fusionlog run` (its filters carried from block to block, FBS's forward pass
recomputed per block), in blocks of `--block` instants, the readings read from memory; one
architecture at a time, so that each one's time per instant is its own. Nothing is written.

FilterPy: `ExtendedKalmanFilter` on the same readings (`bench_nonlinear.filterpy_per_step`: the
two radars stacked, plain-Python Jacobian and measurement functions on floats, FilterPy's best
case), per instant. The ratio is fusionlog's time per architecture-instant over FilterPy's per
instant: one filter against one filter for CKF, SKF and FBS's forward pass; HKF, MSC-GMF, MSC,
CI and AVG run two local filters and a fusion per instant.

Times are CPU seconds of this process (time.process_time: what the load of a shared machine
moves less than the wall time); `--repeats` alternate repeats, medians. `uptime` is printed
before and after.

    .venv/bin/python benchmarks/bench_nonlinear_long.py [--instants 5000] [--repeats 3]
        [--filter EKF|UKF] [--block 2000] [--arch CKF ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
try:
    import fusionlog  # noqa: F401
except ImportError:  # running from a checkout without `pip install -e .`
    sys.path.insert(0, str(ROOT / "src"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_nonlinear import filterpy_per_step  # noqa: E402

from fusionlog.core.nonlinear.long_log import estimate_blocks  # noqa: E402
from fusionlog.core.simulate import simulate  # noqa: E402
from fusionlog.scenario import load_scenario  # noqa: E402

SCENARIO = ROOT / "pipeline" / "radar_tracking.toml"


def one_run_log(instants: int, filt: str):
    """The scenario's system (with local filter `filt`), one run's readings (1, K+1, m) and
    its instants."""
    sc = load_scenario(SCENARIO, runs=1, steps=instants - 1)
    system = dataclasses.replace(sc.system, filter=filt)
    times = np.arange(instants) * system.dt
    _, z = simulate(system.on_times(times), instants - 1, sc.seed, 0, 1)
    return sc, system, z, times


def fusionlog_per_instant(system, arch: str, z: np.ndarray, times: np.ndarray, block: int):
    """CPU seconds per instant of `arch` on the one-run log z (1, K+1, m) in blocks."""
    read = lambda a, b: z[:, a:b]  # noqa: E731
    t = time.process_time()
    for _ in estimate_blocks(system, [arch], read, times, block):
        pass
    return (time.process_time() - t) / z.shape[1]


def filterpy_cpu_per_instant(system, z: np.ndarray) -> float:
    """FilterPy's EKF per instant on z (1, K+1, m), in CPU seconds."""
    t = time.process_time()
    filterpy_per_step(system, z)
    return (time.process_time() - t) / z.shape[1]


def _uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--instants", type=int, default=5000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--block", type=int, default=2000, help="instants per block of time")
    ap.add_argument("--filter", choices=["EKF", "UKF"], default="EKF")
    ap.add_argument("--arch", action="append", help="architectures (default: the scenario's)")
    args = ap.parse_args(argv)

    sc, system, z, times = one_run_log(args.instants, args.filter)
    archs = args.arch or list(sc.architectures)
    print(f"uptime before: {_uptime()}")
    ours: dict[str, list[float]] = {a: [] for a in archs}
    theirs: list[float] = []
    filterpy_per_step(system, z[:, :10])  # warm-up: FilterPy's import
    for _ in range(args.repeats):
        theirs.append(filterpy_cpu_per_instant(system, z))
        for a in archs:
            ours[a].append(fusionlog_per_instant(system, a, z, times, args.block))
    fp = statistics.median(theirs)
    print(f"radar_tracking, {args.filter} locals, one run of {args.instants} instants, blocks "
          f"of {args.block}; CPU us per instant, medians of {args.repeats}")  # fmt: skip
    print(f"  FilterPy EKF (one filter)  {fp * 1e6:8.1f}   ({_fmt(theirs)})")
    for a in archs:
        t = statistics.median(ours[a])
        print(f"  {a:<26} {t * 1e6:8.1f}   ({_fmt(ours[a])})   ratio {t / fp:5.1f}x")
    total = sum(statistics.median(v) for v in ours.values())
    print(f"  all {len(archs)} architectures      {total * 1e6:8.1f} per instant "
          f"(-> {total * 1e6:.0f} s per 10^6 instants)")  # fmt: skip
    print(f"uptime after: {_uptime()}")
    return 0


def _fmt(values: list[float]) -> str:
    return ", ".join(f"{v * 1e6:.1f}" for v in values)


if __name__ == "__main__":
    raise SystemExit(main())
