"""Where users wait (issue 23): whole `fusionlog` commands against in-memory competitors, side
by side in one run.

1. **Dropouts.** `fusionlog estimate` of the paper's example with 20 % random dropouts
   (`pipeline/ajgl2009_dropout.toml` with every sensor's `dropout = 0.2`, M = 10^4, K = 20;
   CKF, HKF, MSC, MSC-GMF, SKF) as a whole process: interpreter start, imports, reading
   sensors.mcap, per-run plans, writing estimates.mcap. Against simdkalman's CKF in this
   process, warm, on the same z (read back from that sensors.mcap; NaN = missing). Target:
   the command at least as fast (ratio simdkalman / command >= 1).
2. **Start-up.** `fusionlog run pipeline/ajgl2009.toml` (the whole paper run: simulate,
   estimate with seven architectures, evaluate into the .rrd) against FilterPy's CKF loop
   (`bench_core.filterpy_ckf`) on the same z, timed on --filterpy-runs runs and scaled to M.
   Target: >= 4x.

Each round runs every command once, in turn (the competitors in this process); the figures are
medians over --repeats rounds, of the wall time and of the CPU seconds (user + system of the
child and of every process it reaped). `--base TREE` runs the commands from `TREE/src` too
(PYTHONPATH), in the same rounds: before and after in one run, under the same load. Children
run with bytecode caching on (a warm-up round writes the .pyc files first), as an installed
copy does. The load average is printed with every round.

    python benchmarks/bench_waits.py [--repeats 5] [--base /tmp/base23] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from importlib.metadata import version
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
try:
    import fusionlog  # noqa: F401
except ImportError:  # running from a checkout without `pip install -e .`
    sys.path.insert(0, str(ROOT / "src"))

from bench_core import filterpy_ckf, simdkalman_ckf, simdkalman_filter  # noqa: E402
from bench_pipeline import load_z  # noqa: E402

FUSIONLOG = Path(sys.executable).parent / "fusionlog"
DROPOUT = 0.2
ESTIMATE_ARCHS = ("CKF", "HKF", "MSC", "MSC-GMF", "SKF")
T_DROPOUT = 1.0
T_PAPER = 4.0


def child(cmd: list[str], src: Path) -> tuple[float, float]:
    """(wall s, CPU s) of one command run with `src` first on the path."""
    env = {**os.environ, "PYTHONPATH": str(src), "RERUN_ANALYTICS": "0"}
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    res = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=ROOT)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if res.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({res.returncode}): {res.stderr[-2000:]}")
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def in_process(fn) -> tuple[float, float]:
    t0, c0 = time.perf_counter(), time.process_time()
    fn()
    return time.perf_counter() - t0, time.process_time() - c0


def dropout_scenario(work: Path) -> Path:
    text = (ROOT / "pipeline" / "ajgl2009_dropout.toml").read_text()
    text = text.replace("dropout = 0.1 ", f"dropout = {DROPOUT} ")
    assert text.count(f"dropout = {DROPOUT} ") == 3, "the scenario's sensors changed"
    path = work / "ajgl2009_dropout20.toml"
    path.write_text(text.replace('name = "ajgl2009_dropout"', 'name = "ajgl2009_dropout20"'))
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5, help="rounds (default 5)")
    ap.add_argument("--filterpy-runs", type=int, default=1000)
    ap.add_argument("--base", type=Path, default=None, help="a baseline tree (its src/)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    trees = {"HEAD": ROOT / "src"} | ({"base": args.base / "src"} if args.base else {})
    with tempfile.TemporaryDirectory(prefix="fusionlog-bench-waits-") as tmp:
        work = Path(tmp)
        sensors = work / "sensors.mcap"
        subprocess.run([str(FUSIONLOG), "simulate", str(dropout_scenario(work)), "-o",
                        str(sensors)], check=True, capture_output=True)  # fmt: skip
        system, zd = load_z(sensors)
        paper = work / "paper"
        child([str(FUSIONLOG), "run", str(ROOT / "pipeline" / "ajgl2009.toml"), "--out-dir",
               str(paper), "--force"], trees["HEAD"])  # fmt: skip
        psys, zp = load_z(paper / "sensors.mcap")
        zf = zp[: args.filterpy_runs]
        scale = len(zp) / len(zf)
        skf = simdkalman_filter(system)
        cmds = {}
        for tree, src in trees.items():
            est = [str(FUSIONLOG), "estimate", str(sensors), "-o", str(work / f"e_{tree}.mcap"),
                   "--force"] + [x for a in ESTIMATE_ARCHS for x in ("--arch", a)]  # fmt: skip
            run = [str(FUSIONLOG), "run", str(ROOT / "pipeline" / "ajgl2009.toml"),
                   "--out-dir", str(work / f"run_{tree}"), "--force"]  # fmt: skip
            cmds[f"estimate {tree}"] = lambda c=est, s=src: child(c, s)
            cmds[f"run {tree}"] = lambda c=run, s=src: child(c, s)
        cmds["simdkalman CKF"] = lambda: in_process(lambda: simdkalman_ckf(skf, system, zd))
        cmds["FilterPy CKF"] = lambda: tuple(
            t * scale for t in in_process(lambda: filterpy_ckf(psys, zf))
        )
        print(f"python {sys.version.split()[0]}, simdkalman {version('simdkalman')}, filterpy "
              f"{version('filterpy')}, {os.cpu_count()} CPUs; z {zd.shape}, "
              f"{100 * float(np.isnan(zd).mean()):.1f} % missing; FilterPy timed on "
              f"{len(zf)} runs, scaled x{scale:g}")  # fmt: skip
        for fn in cmds.values():  # warm-up round: .pyc files, page cache
            fn()
        times: dict[str, list[tuple[float, float]]] = {k: [] for k in cmds}
        loads = []
        for r in range(args.repeats):
            for name, fn in cmds.items():
                times[name].append(fn())
            loads.append(os.getloadavg()[0])
            print(f"  round {r + 1}: " + ", ".join(f"{k} {v[-1][0]:.2f} s" for k, v in
                                                    times.items())
                  + f"; load {loads[-1]:.1f}", flush=True)  # fmt: skip
    med = {k: (statistics.median(w for w, _ in v), statistics.median(c for _, c in v))
           for k, v in times.items()}  # fmt: skip
    print(f"\nmedians of {args.repeats} rounds (load average {min(loads):.1f}-{max(loads):.1f} "
          f"on {os.cpu_count()} CPUs)")  # fmt: skip
    print(f"{'case':22s} {'wall s':>8s} {'CPU s':>8s}")
    for k, (w, c) in med.items():
        print(f"{k:22s} {w:8.3f} {c:8.3f}")
    out = {"median": med, "all": times, "loads": loads, "targets": {}}
    for tree in trees:
        d = med["simdkalman CKF"][0] / med[f"estimate {tree}"][0]
        p = med["FilterPy CKF"][0] / med[f"run {tree}"][0]
        out["targets"][tree] = {"dropout_ratio": d, "paper_ratio": p}
        print(f"{tree}: dropouts simdkalman / estimate {d:.2f}x (target >= {T_DROPOUT:g}x: "
              f"{'met' if d >= T_DROPOUT else 'MISSED'}); paper FilterPy / run {p:.2f}x (target "
              f">= {T_PAPER:g}x: {'met' if p >= T_PAPER else 'MISSED'})")  # fmt: skip
    if args.json is not None:
        args.json.write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
