"""Probe, not product: would a compiled per-run kernel earn its place (issue 23)?

Issue 23 asks every architecture's per-run path (data with dropouts) for >= 3x simdkalman's CKF.
MSC-GMF, CI and AVG carry the local filters' joint error covariance J of eq. (35), (S n) x (S n)
per run and step, and GMF solves with it (eqs. 6-7): several times the CKF's arithmetic, done by
numpy calls over lanes of runs that are at numpy's floor (benchmarks/README.md). This script
measures the alternative the project's dependency rules allow, numba: MSC-GMF of the paper's
example written as one compiled kernel over blocks of runs (the runs innermost, so the compiler
vectorises over them), no grouping by history, scalar sensors, every local with a prior.

It prints, side by side on the bench_core data (M = 10^4, K = 20, 10 % dropouts):
  * the kernel's warm time, and its agreement with fusionlog's MSC-GMF on the run-steps where J is
    regular (the kernel has no least-squares fallback for a singular J: the paper's example is
    singular at k = 0, where every local shares the prior, and after a step two sensors both miss);
  * fusionlog's MSC-GMF and simdkalman's CKF on the same data;
  * what a fresh process pays before the kernel's first call: `import numba`, and the first call
    (compiling on the first run on a machine, loading numba's on-disk cache afterwards).

Needs numba, which fusionlog does not depend on: `pip install numba` into a scratch environment
with this checkout on PYTHONPATH (`PYTHONPATH=src python benchmarks/probe_compiled.py`). The
figures and the conclusion are in benchmarks/README.md (issue 23).
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "src"))


FIRST_CALL = """
import sys, time
t0 = time.perf_counter()
import numba  # noqa: F401
t1 = time.perf_counter()
sys.path.insert(0, {here!r})
import numpy as np
import probe_gmf_kernel
z = np.ones((2, 3, 3)); F = np.eye(2); H = np.ones((3, 2)); R = np.ones(3); x0 = np.zeros(2)
probe_gmf_kernel.msc_gmf(z, F, F, H, R, x0, F, np.empty((2, 3, 2)), np.empty((2, 3, 2, 2)),
                     np.empty((2, 3), dtype=np.bool_))
t2 = time.perf_counter()
print(t1 - t0, t2 - t1)
"""


def median(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def main() -> int:
    # numba's cache of the kernel goes to a folder of this run (read when numba is imported)
    with tempfile.TemporaryDirectory(prefix="fusionlog-probe-") as folder:
        os.environ["NUMBA_CACHE_DIR"] = str(Path(folder) / "cache")
        try:
            import numba
        except ImportError:
            print("numba is not installed: this probe needs it (see the module docstring)")
            return 0
        return probe(numba.__version__)


def probe(numba_version: str) -> int:
    import simdkalman  # noqa: F401
    from bench_core import drop, simdkalman_ckf, simdkalman_filter

    from fusionlog.core.architectures import estimate, registry
    from fusionlog.core.model import ajgl2009
    from fusionlog.core.simulate import simulate

    system = ajgl2009()
    _, z = simulate(system, 20, 1, 0, 10_000)
    zd = drop(z, 0.1, 1)
    M, K1, S = zd.shape
    n = system.n
    H = np.vstack([s.H for s in system.sensors])
    R = np.array([float(s.R[0, 0]) for s in system.sensors])
    firsts = []
    for _ in range(3):  # the first compiles (the cache is empty), the others load the cache
        out = subprocess.run(
            [sys.executable, "-c", FIRST_CALL.format(here=str(HERE))],
            capture_output=True, text=True, check=True,
        )  # fmt: skip
        firsts.append(tuple(float(v) for v in out.stdout.split()))
    import probe_gmf_kernel as kernel_module

    ox, oP = np.empty((M, K1, n)), np.empty((M, K1, n, n))
    regular = np.empty((M, K1), dtype=np.bool_)
    args = (zd, system.F, system.GQG, H, R, system.prior.mean, system.prior.cov)

    def kernel():
        kernel_module.msc_gmf(*args, ox, oP, regular)

    t_kernel = median(kernel, 7)

    def ours():
        getattr(registry, "forget_grouping", lambda: None)()  # (a tree with the cache)
        return estimate(system, zd, "MSC-GMF")

    t_ours = median(ours, 7)
    skf = simdkalman_filter(system)
    t_sk = median(lambda: simdkalman_ckf(skf, system, zd), 7)
    ref = ours()
    d_mean = np.abs(ox - ref.mean)[regular].max() / np.abs(ref.mean).max()
    d_cov = np.abs(oP - ref.cov)[regular].max() / np.abs(ref.cov[regular]).max()
    print(f"numba {numba_version}, numpy {np.__version__}; M = {M}, K = {K1 - 1}, "
          f"{100 * np.isnan(zd).mean():.1f} % missing; load {os.getloadavg()[0]:.1f}")  # fmt: skip
    print(f"agreement with fusionlog's MSC-GMF on the {100 * regular.mean():.1f} % run-steps "
          f"with a regular J: means {d_mean:.1e}, covariances {d_cov:.1e} (relative)")  # fmt: skip
    print(f"{'':34s}{'median s':>10s}{'x simdkalman CKF':>18s}")
    for name, t in (
        ("compiled kernel (warm)", t_kernel),
        ("fusionlog MSC-GMF (numpy lanes)", t_ours),
        ("simdkalman CKF", t_sk),
    ):
        print(f"{name:34s}{t:10.4f}{t_sk / t:18.2f}")
    comp, load = firsts[0], statistics.median(f[1] for f in firsts[1:])
    imp = statistics.median(f[0] for f in firsts)
    print(f"a fresh process before the first call: import numba {imp:.3f} s; first call "
          f"{comp[1]:.2f} s compiling (once per machine), {load:.3f} s from the cache")  # fmt: skip
    total = t_kernel + imp + load
    print(f"kernel + import + cache load {total:.3f} s against numpy {t_ours:.3f} s")
    return 0 if d_mean < 1e-9 and d_cov < 1e-9 else 1


if __name__ == "__main__":
    sys.exit(main())
