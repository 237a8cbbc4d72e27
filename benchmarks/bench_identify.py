"""`fusionlog identify` (issue 32): the time to identify four noise parameters from 2,000 runs x
31 instants, next to statsmodels' `MLEModel.fit` on the same model.

Model: constant velocity (Ts = 1, n0 = 0.3), two position sensors with correlated noise
(R1 = 0.5, R2 = 2, cross-covariance 0.3), prior N([0, 1], diag(4, 1)). Parameters:
sensors.s1.R, sensors.s2.R, correlations.0.cov, model.n0, from the file's values 1, 1, 0, 0.16.

statsmodels has no batch over runs: it is timed on one run of the same data (31 instants),
and so is fusionlog (its one-run path, `core.likelihood_one`): two ratios, the same run
against the same run, and per run (fusionlog's time on 2,000 / 2,000 against statsmodels' on
one); medians of the repeats. The estimates of both on that one run are printed side by side
(they maximise the same likelihood: same values to the optimisers' tolerance).

    .venv/bin/python benchmarks/bench_identify.py [--runs 2000] [--repeats 3]
"""

from __future__ import annotations

import argparse
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np

import fusionlog as fl

SCENARIO = """
[scenario]
name = "bench_identify"
description = "constant velocity, two correlated position sensors"
steps = 30
runs = {runs}
seed = 1
dt = 1.0
state_names = ["position", "velocity"]
[model]
kind = "constant-velocity"
n0 = {n0}
[prior]
mean = [0.0, 1.0]
cov = [[4.0, 0.0], [0.0, 1.0]]
[[sensors]]
name = "s1"
H = [[1.0, 0.0]]
R = {r1}
[[sensors]]
name = "s2"
H = [[1.0, 0.0]]
R = {r2}
[[correlations]]
sensors = ["s1", "s2"]
cov = [[{c}]]
[estimate]
architectures = ["CKF"]
"""
KEYS = ["sensors.s1.R", "sensors.s2.R", "correlations.0.cov", "model.n0"]


def statsmodels_fit(y: np.ndarray) -> tuple[np.ndarray, float]:
    """statsmodels' MLE of (R1, R2, c, n0) on one run y (K+1, 2), and its time."""
    from statsmodels.tsa.statespace.mlemodel import MLEModel

    class CV(MLEModel):
        def __init__(self, endog):
            super().__init__(endog, k_states=2)
            self["design"] = np.array([[1.0, 0.0], [1.0, 0.0]])
            self["transition"] = np.array([[1.0, 1.0], [0.0, 1.0]])
            self["selection"] = np.eye(2)
            self.initialize_known(np.array([0.0, 1.0]), np.diag([4.0, 1.0]))

        @property
        def start_params(self):
            return np.array([1.0, 1.0, 0.0, 0.16])

        def transform_params(self, u):
            return np.array([np.exp(u[0]), np.exp(u[1]), u[2], np.exp(u[3])])

        def untransform_params(self, p):
            return np.array([np.log(p[0]), np.log(p[1]), p[2], np.log(p[3])])

        def update(self, params, **kwargs):
            params = super().update(params, **kwargs)
            r1, r2, c, n0 = params
            self["obs_cov"] = np.array([[r1, c], [c, r2]])
            self["state_cov"] = n0 * np.array([[1 / 3, 1 / 2], [1 / 2, 1.0]])

    t0 = time.perf_counter()
    res = CV(y).fit(disp=False, maxiter=500)
    return np.asarray(res.params), time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=2000)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        truth = Path(d, "truth.toml")
        truth.write_text(textwrap.dedent(SCENARIO.format(runs=args.runs, n0=0.3, r1=0.5, r2=2.0,
                                                         c=0.3)))  # fmt: skip
        model = Path(d, "model.toml")
        model.write_text(textwrap.dedent(SCENARIO.format(runs=args.runs, n0=0.16, r1=1.0,
                                                         r2=1.0, c=0.0)))  # fmt: skip
        sim = fl.simulate(fl.load(truth))
        sc = fl.load(model)
        fl.identify(sc, fl.simulate(fl.load(truth), runs=50), KEYS, cost=False)  # warm imports
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            res = fl.identify(sc, sim, KEYS, cost=False)
            times.append(time.perf_counter() - t0)
        ours = float(np.median(times))
        print(f"fusionlog identify, {args.runs} runs x 31 instants, 4 parameters: "
              f"median {ours:.2f} s ({_spread(times)}), {res.iterations} iterations")  # fmt: skip
        for k in KEYS:
            v, se = (float(np.ravel(a)[0]) for a in (res.values[k], res.stderr[k]))
            print(f"  {k:<20} {v:.4f} +- {se:.4f}")
        one = fl.simulate(fl.load(truth), runs=1, seed=2)
        y = np.concatenate([one.measurements["s1"][0], one.measurements["s2"][0]], axis=1)
        statsmodels_fit(y)  # warm its imports and compiled filters too
        sm_times, sm = [], None
        for _ in range(args.repeats):
            sm, t = statsmodels_fit(y)
            sm_times.append(t)
        theirs = float(np.median(sm_times))
        one_times = []
        for _ in range(args.repeats):  # the one-run path (`core.likelihood_one`)
            t0 = time.perf_counter()
            ours_one = fl.identify(sc, one, KEYS, cost=False)
            one_times.append(time.perf_counter() - t0)
        mine = float(np.median(one_times))
        print(f"statsmodels MLEModel.fit, one run of 31 instants: median {theirs * 1e3:.1f} ms "
              f"({_spread(sm_times)})")  # fmt: skip
        print(f"fusionlog identify, the same run: median {mine * 1e3:.1f} ms "
              f"({_spread(one_times)}), {ours_one.iterations} iterations: ratio "
              f"{theirs / mine:.1f}x")  # fmt: skip
        print(f"per run: fusionlog {ours / args.runs * 1e3:.2f} ms, statsmodels "
              f"{theirs * 1e3:.1f} ms: ratio {theirs / (ours / args.runs):.0f}x")  # fmt: skip
        print("one run, both optimisers (same likelihood):")
        for k, v in zip(KEYS, sm, strict=True):
            got = float(np.ravel(ours_one.values[k])[0])
            print(f"  {k:<20} fusionlog {got:.5f}  statsmodels {v:.5f}")


def _spread(times: list[float]) -> str:
    return f"min {min(times):.3g} s, max {max(times):.3g} s, {len(times)} repeats"


if __name__ == "__main__":
    main()
