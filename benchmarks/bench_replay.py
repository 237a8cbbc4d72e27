"""A single replayed log: fusionlog's estimate stage against FilterPy's KF stepping through the
same instants in a Python loop (issue 22, item 6).

    .venv/bin/python benchmarks/bench_replay.py                     # pipeline/replay_robot.toml
    .venv/bin/python benchmarks/bench_replay.py --replay FILE.toml --repeats 5

What is timed, per instant and architecture (the fastest of `--repeats`, a shared machine only
adds time):

- `fusionlog estimate`: the command in this process on the imported sensors file (read, plan,
  apply, write estimates.mcap), for the replay's architectures together, divided by
  instants x architectures; and each architecture alone (`--arch A`).
- the core alone: `core.architectures.estimate` on the arrays (plan + apply), per architecture.
- FilterPy 1.4.5 `KalmanFilter`: at every instant predict with the exact discretisation of the
  interval (F, Q of the constant-velocity model) and update with each sensor that measures
  then (its H, its message's R): the loop a user would write. Its estimates are checked against
  fusionlog's CKF (relative 1e-8) before anything is timed.

The import (reading the recorded files) is timed apart: it is the same for every architecture.
`--cpu` times this process's CPU time (user + sys) instead of the wall clock: on a machine
shared with other work it moves less (the figures are then printed as "CPU").
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


#: The clock: wall time, or with --cpu this process's CPU time (user + sys), which other
#: sessions' load on a shared machine moves less.
CLOCK = time.perf_counter


def _best(fn, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = CLOCK()
        fn()
        best = min(best, CLOCK() - t0)
    return best


def _cli(*args: str) -> None:
    from click.testing import CliRunner

    from fusionlog.cli import main

    res = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)
    if res.exit_code != 0:
        raise SystemExit(res.output)


def _filterpy_inputs(sensors: Path):
    """(times s (K+1,), [(H, [(row, z, R)] per instant)], n, q, prior) from the sensors file."""
    from fusionlog.io.mcap import McapFile
    from fusionlog.stages.common import scenario_from_file
    from fusionlog.stages.noise import with_message_covariances

    mf = McapFile(sensors)
    sc = scenario_from_file(mf)
    times = mf.times()
    system = with_message_covariances(sc.system.on_times(times), mf)
    topics = [f"/sensors/{s.name}" for s in system.sensors]
    z = np.concatenate([mf.read_all([t])[t] for t in topics], axis=-1)[0]
    return sc, system, times, z


def filterpy_loop(system, times: np.ndarray, z: np.ndarray):
    """FilterPy's KF: predict over each interval, update with the sensors measuring then."""
    from filterpy.kalman import KalmanFilter

    from fusionlog.core.timing import van_loan

    A, Qc = system.continuous
    dts = np.diff(times)
    uniq, where = np.unique(dts, return_inverse=True)
    Fu, Qu = van_loan(A, Qc, uniq)
    H = system.linear_measurement()
    sl = system.sensor_slices
    R0 = system.R
    Rs = system.Rs if system.Rs is not None else np.broadcast_to(R0, (len(times), *R0.shape))
    n = system.n
    kf = KalmanFilter(dim_x=n, dim_z=1)
    kf.x, kf.P = system.prior.mean.copy(), system.prior.cov.copy()
    present = ~np.isnan(z)
    means = np.empty((len(times), n))
    for k in range(len(times)):
        if k:
            kf.predict(F=Fu[where[k - 1]], Q=Qu[where[k - 1]])
        for s in sl:
            if present[k, s.start]:
                kf.dim_z = s.stop - s.start
                kf.update(z[k, s], R=Rs[k][s, s], H=H[s])
        means[k] = kf.x
    return means


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--replay", type=Path, default=ROOT / "pipeline" / "replay_robot.toml")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--cpu", action="store_true", help="CPU time (user + sys) instead of wall")
    args = ap.parse_args(argv)
    if args.cpu:
        global CLOCK
        CLOCK = time.process_time
    from fusionlog.core.architectures import estimate
    from fusionlog.scenario import load_scenario

    archs = list(load_scenario(args.replay).architectures)
    with tempfile.TemporaryDirectory() as d:
        sensors = Path(d) / "s.mcap"
        t_import = _best(lambda: _cli("import", args.replay, "-o", sensors, "--force"), 1)
        sc, system, times, z = _filterpy_inputs(sensors)
        K1 = len(times)
        ckf = estimate(system, z[None], "CKF").mean[0]
        ref = filterpy_loop(system, times, z)
        err = np.abs(ref - ckf).max() / np.abs(ckf).max()
        if err > 1e-8:
            print(f"MISMATCH: FilterPy vs CKF, max relative difference {err:.2e}")
            return 1
        t_fp = _best(lambda: filterpy_loop(system, times, z), args.repeats)
        est = Path(d) / "e.mcap"
        arch_args = [x for a in archs for x in ("--arch", a)]
        t_all = _best(lambda: _cli("estimate", sensors, "-o", est, "--force", *arch_args),
                      args.repeats)  # fmt: skip
        print(f"{args.replay.name}: {K1} instants, {len(archs)} architectures; import "
              f"{t_import:.2f} s (not below); {'CPU' if args.cpu else 'wall'} time")  # fmt: skip
        print(f"FilterPy KF loop (one filter)          {1e6 * t_fp / K1:8.1f} µs per instant")
        print(f"fusionlog estimate, {len(archs)} architectures   "
              f"{1e6 * t_all / (K1 * len(archs)):8.1f} µs per instant and architecture "
              f"({t_all:.2f} s)")  # fmt: skip
        print(f"{'architecture':14s} {'estimate µs':>12s} {'core µs':>10s}  (per instant)")
        for a in archs:
            t_cmd = _best(lambda a=a: _cli("estimate", sensors, "-o", est, "--force", "--arch", a),
                          args.repeats)  # fmt: skip
            t_core = _best(lambda a=a: estimate(system, z[None], a), args.repeats)
            print(f"{a:14s} {1e6 * t_cmd / K1:12.1f} {1e6 * t_core / K1:10.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
