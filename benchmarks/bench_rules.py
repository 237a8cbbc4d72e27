"""CPU time of the fusion-rule architectures' `estimate` (plan compile included), per workload.

Data: the paper's example (`ajgl2009()`), K = 20, M = 10^4 runs from `simulate(..., seed=1)`:
``shared`` the complete data (one plan for every run), ``per-run`` the same with every
measurement dropped with probability 0.1 (per-run plans on history nodes), ``noprior-per-run``
that data with the model's prior removed (the local filters start in information form). Each
line is the median CPU time (`time.process_time`, this process only) of N calls after one
warm-up. Compare two checkouts by running this script from each in turn, alternately:

    PYTHONPATH=src .venv/bin/python benchmarks/bench_rules.py --repeats 5
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

import numpy as np

from fusionlog.core.architectures import estimate
from fusionlog.core.model import ajgl2009
from fusionlog.core.simulate import simulate
from fusionlog.memory import keep_freed_memory


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--arch", action="append", default=None, help="default: the five rules")
    args = ap.parse_args(argv)
    keep_freed_memory()  # as the fusionlog command does
    system = ajgl2009()
    _, z = simulate(system, 20, 1, 0, 10_000)
    dropped = z.copy()
    dropped[np.random.default_rng(3).random(z.shape) < 0.1] = np.nan
    cases = {
        "shared": (system, z),
        "per-run": (system, dropped),
        "noprior-per-run": (dataclasses.replace(system, prior=None), dropped),
    }
    for arch in args.arch or ["MSC-GMF", "MSC", "CI", "AVG", "ICI"]:
        for case, (s, data) in cases.items():
            estimate(s, data, arch)  # warm-up
            times = []
            for _ in range(args.repeats):
                t0 = time.process_time()
                estimate(s, data, arch)
                times.append(time.process_time() - t0)
            print(f"{arch:8s} {case:16s} {statistics.median(times):.4f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
