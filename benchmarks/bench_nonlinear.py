"""The CKF with EKF local filters on the radar scenario (issue 21): the whole `fusionlog estimate`
against FilterPy's `ExtendedKalmanFilter` run per run, side by side.

fusionlog: `fusionlog estimate SENSORS.mcap -o ESTIMATES.mcap --arch CKF` as a child process, on
the sensors file `fusionlog simulate pipeline/radar_tracking.toml --runs 10000` wrote (M = 10^4,
K = 30: 31 instants), timed from spawn to exit: interpreter start, imports, reading the sensors
file, the filter, writing every run's mean and covariance at every instant, fsync and rename.
The child runs with bytecode caching in a temporary folder (PYTHONPYCACHEPREFIX; a warm-up run
fills it), as an installed package would: a checkout run with PYTHONDONTWRITEBYTECODE would
otherwise recompile fusionlog's sources at every start.

FilterPy: `ExtendedKalmanFilter` on the same measurements (read back from the same file), one run
at a time: predict (k >= 1) and update with both radars stacked, with plain-Python Jacobian and
measurement functions of the two radars (math on floats: FilterPy's best case, about a third of
the time of the same functions on numpy arrays) and a residual that wraps the bearings. Timed on
a subset of the runs and reported per run-step; its time for M runs is that times M (K + 1).

The two are run alternately, `--repeats` times; the table shows the medians and the ratio
FilterPy(M runs) / fusionlog estimate. Target: >= 20.

    .venv/bin/python benchmarks/bench_nonlinear.py [--runs 10000] [--repeats 5]
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
try:
    import fusionlog  # noqa: F401
except ImportError:  # running from a checkout without `pip install -e .`
    sys.path.insert(0, str(ROOT / "src"))

from fusionlog.io.mcap import McapFile  # noqa: E402
from fusionlog.scenario import load_scenario  # noqa: E402

SCENARIO = ROOT / "pipeline" / "radar_tracking.toml"
TARGET = 20.0


def _fusionlog(*args: str, env: dict[str, str]) -> float:
    """Seconds from spawn to exit of `fusionlog ARGS` (the CLI's module as a child process)."""
    cmd = [sys.executable, "-m", "fusionlog.cli", *args]
    t = time.perf_counter()
    subprocess.run(cmd, check=True, env=env, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t


def _radar_functions(system):
    """HJacobian, Hx and the residual of the two stacked range-bearing radars, in plain Python."""
    places = [tuple(float(v) for v in s.position) for s in system.sensors]
    ix, iy = system.sensors[0].idx
    n = system.n

    def H(x):
        out = np.zeros((2 * len(places), n))
        px_, py_ = x[ix, 0], x[iy, 0]
        for i, (px, py) in enumerate(places):
            dx, dy = px_ - px, py_ - py
            r2 = dx * dx + dy * dy
            r = math.sqrt(r2)
            out[2 * i, ix], out[2 * i, iy] = dx / r, dy / r
            out[2 * i + 1, ix], out[2 * i + 1, iy] = -dy / r2, dx / r2
        return out

    def hx(x):
        out = np.empty((2 * len(places), 1))
        px_, py_ = x[ix, 0], x[iy, 0]
        for i, (px, py) in enumerate(places):
            dx, dy = px_ - px, py_ - py
            out[2 * i, 0], out[2 * i + 1, 0] = math.hypot(dx, dy), math.atan2(dy, dx)
        return out

    def residual(a, b):
        d = a - b
        for i in range(1, d.shape[0], 2):
            d[i, 0] = math.pi - (math.pi - d[i, 0]) % (2 * math.pi)
        return d

    return H, hx, residual


def filterpy_per_step(system, z: np.ndarray) -> float:
    """Seconds per run-step of FilterPy's EKF on the runs of z (runs, K+1, m)."""
    from filterpy.kalman import ExtendedKalmanFilter

    H, hx, residual = _radar_functions(system)
    F, Q, R = system.F, system.Q, system.R
    runs, K1, m = z.shape
    t = time.perf_counter()
    for r in range(runs):
        ekf = ExtendedKalmanFilter(dim_x=system.n, dim_z=m)
        ekf.x, ekf.P = system.prior.mean[:, None].copy(), system.prior.cov.copy()
        ekf.F, ekf.Q, ekf.R = F, Q, R
        for k in range(K1):
            if k:
                ekf.predict()
            ekf.update(z[r, k][:, None], H, hx, R=R, residual=residual)
    return (time.perf_counter() - t) / (runs * K1)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=10_000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--filterpy-runs", type=int, default=200, help="runs FilterPy is timed on")
    args = ap.parse_args(argv)

    system = load_scenario(SCENARIO).system
    with tempfile.TemporaryDirectory(prefix="fusionlog-bench-nl-") as tmp:
        env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
        env["PYTHONPYCACHEPREFIX"] = str(Path(tmp) / "pycache")
        env["PYTHONPATH"] = os.pathsep.join([str(ROOT / "src"), env.get("PYTHONPATH", "")])
        sensors, est = Path(tmp) / "sensors.mcap", Path(tmp) / "estimates.mcap"
        _fusionlog("simulate", str(SCENARIO), "-o", str(sensors), "--runs", str(args.runs),
                   env=env)  # fmt: skip
        mf = McapFile(sensors)
        data = next(mf.iter_run_blocks([f"/sensors/{s.name}" for s in system.sensors], 10**9))
        z = np.concatenate(list(data[2].values()), axis=-1)
        K1 = z.shape[1]
        estimate = ["estimate", str(sensors), "-o", str(est), "--arch", "CKF", "--force"]
        _fusionlog(*estimate, env=env)  # warm-up: the bytecode cache
        ours, theirs = [], []
        for _ in range(args.repeats):
            ours.append(_fusionlog(*estimate, env=env))
            theirs.append(filterpy_per_step(system, z[: args.filterpy_runs]))
    fl = statistics.median(ours)
    fp_step = statistics.median(theirs)
    fp = fp_step * args.runs * K1
    ratio = fp / fl
    print(f"radar_tracking, CKF with EKF locals: M = {args.runs} runs x {K1} instants")
    print(f"  fusionlog estimate (whole command)   median {fl:7.3f} s   runs {_fmt(ours)}")
    print(f"  FilterPy EKF per run-step           median {fp_step * 1e6:7.1f} us  "
          f"({_fmt([t * 1e6 for t in theirs], 1)} us)")  # fmt: skip
    print(f"  FilterPy for M runs (scaled)         {fp:7.2f} s")
    verdict = "met" if ratio >= TARGET else "NOT met"
    print(f"  ratio {ratio:.1f}x  (target >= {TARGET:.0f}x: {verdict})")
    return 0


def _fmt(values: list[float], digits: int = 3) -> str:
    return ", ".join(f"{v:.{digits}f}" for v in values)


if __name__ == "__main__":
    raise SystemExit(main())
