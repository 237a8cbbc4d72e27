"""The plan-free replay's per-instant recursions (issue 34): the numpy loops they were (written
out here as the reference, as `replay_filters` had them before numba) beside the compiled
kernels that replaced them (`core/architectures/replay_kernels.py`), per instant; and what
numba costs a process: importing it, compiling the kernels into an empty cache, loading them
from the cache.

    .venv/bin/python benchmarks/bench_replay_kernels.py                 # 20 000 instants
    .venv/bin/python benchmarks/bench_replay_kernels.py --instants 5000 --repeats 3

The bank is the paper's seven architectures' filters on the irregular CSV replay's model
(bench_long.write_csv_replay: constant velocity, two position sensors; 6 slots: the CKF, two
locals, HKF's fused prediction and two local updates) and on the paper's (4 states, three
sensors: 8 slots); 5 % of the readings missing. Medians of `--repeats` runs, each in this
process after one untimed call (the kernels compiled or loaded first). Run it under
`nice -n 5` on a shared machine; the ratio moves less with the load than the times.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from fusionlog.core.architectures.replay_filters import (
    Slots,
    backward_information,
    information,
    masked_rows,
    run_bank,
)


def numpy_run_bank(slots, P0, Fs, Qs, Hm, Rm):
    """The reference: run_bank's loop as numpy calls on the batch of slots (before numba),
    P (K+1, B, n, n) only (the gains and I - K H were kept the same way)."""
    K1, B, m, n = Hm.shape
    src, h = slots.src, slots.hkf
    S = B - h - 1 if h is not None else 0
    mm, eye = np.matmul, np.eye(n)
    P_out = np.empty((K1, B, n, n))
    KT_out = np.empty((K1, B, m, n))
    IKH_out = np.empty((K1, B, n, n))
    KH = np.empty((B, n, n))
    Pc = np.array(np.broadcast_to(P0, (slots.carried, n, n)))
    for k in range(K1):
        if k:
            A = mm(mm(Fs[k - 1], Pc), Fs[k - 1].T)
            A += Qs[k - 1]
            Pp = 0.5 * (A + A.swapaxes(-1, -2))
        else:
            Pp = Pc
        Pb = Pp[src]
        H, R = Hm[k], Rm[k]
        HP = mm(H, Pb)
        Sk = mm(HP, H.swapaxes(-1, -2)) + R
        X = KT_out[k] = np.linalg.solve(0.5 * (Sk + Sk.swapaxes(-1, -2)), HP)
        K, IKH, P = X.swapaxes(-1, -2), IKH_out[k], P_out[k]
        mm(K, H, out=KH)
        np.subtract(eye, KH, out=IKH)
        A = mm(mm(IKH, Pb), IKH.swapaxes(-1, -2)) + mm(mm(K, R), X)
        np.add(A, A.swapaxes(-1, -2), out=P)
        P *= 0.5
        if h is None:
            Pc = P
            continue
        Yi = np.linalg.inv(P[h:])
        Y = 0.5 * (Yi + Yi.swapaxes(-1, -2))
        Yf = Y[0] * (1.0 - S) + Y[1:].sum(axis=0)
        Pi = np.linalg.inv(Yf)
        P[h] = 0.5 * (Pi + Pi.T)
        Pc = P[: h + 1]
    return P_out


def numpy_backward(W, Fs, Qs):
    """The reference: backward_information's loop as numpy calls (before numba)."""
    K1, n = W.shape[0], W.shape[-1]
    eye = np.eye(n)
    L, Smat = np.empty((K1 - 1, n, n)), np.zeros((K1, n, n))
    Sk = Smat[-1]
    for k in range(K1 - 2, -1, -1):
        A = Sk + W[k + 1]
        Splus = 0.5 * (A + A.T)
        Lk = L[k] = np.linalg.solve((eye + Splus @ Qs[k]).T, Fs[k]).T
        A = Lk @ Splus @ Fs[k]
        Sk = Smat[k] = 0.5 * (A + A.T)
    return L, Smat


def _bank(n: int, sizes: list[int], K1: int, rng):
    """A random stable model with sensors of `sizes` on irregular intervals, 5 % missing: the
    slots of the seven architectures and their masked H, R, with F, Q per interval."""
    m, S = sum(sizes), len(sizes)
    Fs = np.eye(n) + 0.01 * rng.normal(size=(K1 - 1, n, n))
    A = rng.normal(size=(K1 - 1, n, n))
    Qs = 0.01 * (A @ A.swapaxes(-1, -2) + np.eye(n))
    H = rng.normal(size=(m, n))
    R = np.broadcast_to(np.eye(m), (K1, m, m)) * (0.5 + rng.random(K1))[:, None, None]
    rows = np.zeros((S, m), bool)
    at = 0
    for j, d in enumerate(sizes):
        rows[j, at : at + d] = True
        at += d
    use = np.array([np.ones(m, bool), *rows, np.zeros(m, bool), *rows])
    src = np.array([0, *range(1, S + 1), *[S + 1] * (S + 1)])
    slots = Slots(use, src, S + 2, S + 1)
    present = rng.random((K1, m)) > 0.05
    Hm, Rm = masked_rows(H, R, present[:, None, :] & use[None])
    return slots, np.eye(n), Fs, Qs, Hm, Rm


def _median(f, repeats: int) -> float:
    f()  # compiled or loaded, caches warm
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        f()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def _process_costs() -> dict[str, float]:
    """Seconds a fresh process spends importing numba, then compiling (an empty cache) or
    loading (the cache just written) the kernels on their first call."""
    code = (
        "import time, numpy as np; t0 = time.perf_counter(); import numba; "
        "t1 = time.perf_counter(); "
        "import bench_replay_kernels as b; "
        "import fusionlog.core.architectures.replay_filters as f; "
        "rng = np.random.default_rng(0); "
        "x = b._bank(2, [1, 1], 50, rng); W = np.tile(np.eye(2), (50, 1, 1)); "
        "t2 = time.perf_counter(); f.run_bank(*x); f.backward_information(W, x[2], x[3]); "
        "f.backward_means(np.tile(np.eye(2), (49, 1, 1)), np.ones((50, 2))); "
        "f.affine_recursion(np.ones((50, 1, 2, 2)), np.ones((50, 1, 2)), np.ones((1, 2))); "
        "f.joint_recursion(np.ones((50, 2, 2)), np.ones((50, 2, 2)), np.eye(2)); "
        "print(t1 - t0, time.perf_counter() - t2)"
    )
    out = {}
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache}
        env["PYTHONPATH"] = os.pathsep.join([os.path.dirname(__file__), env.get("PYTHONPATH", "")])
        for what in ("compile", "load"):
            res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                                 text=True, check=True)  # fmt: skip
            imp, first = map(float, res.stdout.split())
            out["import numba"] = imp
            out[f"first calls ({what})"] = first
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--instants", type=int, default=20_000)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    rng = np.random.default_rng(34)
    K1 = args.instants
    print(f"{K1} instants, medians of {args.repeats}")
    print("| recursion | model | numpy loop, us/instant | numba, us/instant | ratio |")
    print("|---|---|---|---|---|")
    for name, n, sizes in (("irregular CSV", 2, [1, 1]), ("paper", 4, [2, 2, 2])):
        slots, P0, Fs, Qs, Hm, Rm = _bank(n, sizes, K1, rng)
        x = (slots, P0, Fs, Qs, Hm, Rm)
        old = _median(lambda x=x: numpy_run_bank(*x), args.repeats)
        new = _median(lambda x=x: run_bank(*x), args.repeats)
        print(f"| run_bank ({len(slots.src)} slots) | {name} | {old / K1 * 1e6:.2f} | "
              f"{new / K1 * 1e6:.3f} | {old / new:.0f} |")  # fmt: skip
        W, _ = information(Hm[:, 0], Rm[:, 0], np.zeros((K1, Hm.shape[2])))
        x = (W, Fs, Qs)
        old = _median(lambda x=x: numpy_backward(*x), args.repeats)
        new = _median(lambda x=x: backward_information(*x), args.repeats)
        print(f"| backward_information | {name} | {old / K1 * 1e6:.2f} | {new / K1 * 1e6:.3f} | "
              f"{old / new:.0f} |")  # fmt: skip
    for what, seconds in _process_costs().items():
        print(f"{what}: {seconds:.2f} s")


if __name__ == "__main__":
    main()
