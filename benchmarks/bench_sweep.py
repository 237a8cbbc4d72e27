"""Benchmark of `fusionlog sweep` on Dask (issue 15): 1 worker against 2, the overhead of a
task, and what a 100-node cluster would do with a 10^8-run study.

1. **Sweep: this process, 1 and 2 workers** (issue 23). `fusionlog sweep
   pipeline/ajgl2009.toml --vary scenario.dt=0.5,1,2,4 --runs 200000` (4 grid points, the
   scenario's seven architectures) as child processes with `--workers 0`, `1` and `2`, in
   turn, several times; medians of the whole command (spawn to exit), of its CPU seconds
   (user + system of it and every process it reaped: the workers too) and of the phases the
   command prints (cluster start, tasks, outputs, stop). The tables must be identical.
   Targets: 1 worker no slower than 1.1x this process, 2 workers >= 1.5x faster than this
   process. The CPU seconds a worker adds (1 worker minus this process, 2 minus 1) are the
   per-worker overhead; and the same sweep at 20 000 runs without --workers (the default
   chosen from the size of the work) against --workers 0 and 2. `--base TREE` runs the
   sweeps of TREE/src too, in the same rounds (before and after under the same load).
2. **Per-task overhead** (scheduling + transfer of the arguments and the result), on a
   LocalCluster of one worker started here: tasks that run `block_sums` on 8 runs (a real
   result, the size of any block's: the sums do not grow with the runs) one at a time (the
   round trip) and through the executor's window (amortised), each minus the seconds the
   worker reports for the task itself; and the pickled sizes of a task's arguments and result.
3. **Per-block cost**: `block_sums` of the default block (about a million run-steps) in this
   process, with the eight architectures of the registry, and its seconds per run.
4. **A 100-node cluster and the 10^8-run study** (10^6 runs x 100 grid points x 8
   architectures), on paper from 2 and 3: tasks, bytes moved, expected time.

    .venv/bin/python benchmarks/bench_sweep.py                 # about 3 minutes here
    .venv/bin/python benchmarks/bench_sweep.py --quick         # 2 x 10^4 runs, one repeat
    .venv/bin/python benchmarks/bench_sweep.py --json out.json
    .venv/bin/python benchmarks/bench_sweep.py --sweep-only --base /tmp/base  # before/after, 1.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import pickle
import platform
import re
import resource
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = ROOT / "pipeline" / "ajgl2009.toml"
FUSIONLOG = Path(sys.executable).parent / "fusionlog"
TIMING = re.compile(
    r": ([\d.]+) s \(start ([\d.]+) s, (\d+) tasks ([\d.]+) s, "
    r"outputs ([\d.]+) s, stop ([\d.]+) s\)"
)
#: The sweep of issue 23 and its targets: 1 worker at most 1.1x this process's wall time,
#: 2 workers at least 1.5x faster than this process.
VARY = "scenario.dt=0.5,1,2,4"
T_ONE_WORKER = 1.1
T_TWO_WORKERS = 1.5
STUDY_RUNS, STUDY_POINTS, STUDY_ARCHS, NODES = 10**6, 100, 8, 100


def sweep_once(
    workers: int | None, runs: int, out: Path, src: Path | None = None
) -> dict[str, float]:
    """One `fusionlog sweep` child process: its wall time, its CPU seconds (with every process
    it reaped: a LocalCluster's workers) and the phases it prints; `workers` None: the
    default; `src` a tree's src/ first on the path (bytecode caching on, as installed)."""
    cmd = [str(FUSIONLOG), "sweep", str(SCENARIO), "--vary", VARY, "--runs", str(runs),
           "--out-dir", str(out), "--force"]  # fmt: skip
    if workers is not None:
        cmd += ["--workers", str(workers)]
    env = {**os.environ, "RERUN_ANALYTICS": "0"}
    if src is not None:
        env["PYTHONPATH"] = str(src)
        env.pop("PYTHONDONTWRITEBYTECODE", None)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if res.returncode != 0:
        raise SystemExit(f"sweep failed ({res.returncode}): {res.stderr}")
    m = TIMING.search(res.stdout)
    if m is None:
        raise SystemExit(f"no timing line in: {res.stdout[-300:]}")
    total, start, n, tasks, outputs, stop = (float(g) for g in m.groups())
    return {"wall": wall, "cpu": cpu, "command": total, "start": start, "tasks_n": n,
            "tasks": tasks, "outputs": outputs, "stop": stop}  # fmt: skip


def bench_workers(
    runs: int,
    repeats: int,
    tmp: Path,
    counts: tuple[int | None, ...] = (0, 1, 2),
    trees: dict[str, Path | None] | None = None,
) -> dict:
    """The sweep with each worker count of `counts` (None: the default) in turn, `repeats`
    times; medians per count, and ratios to this process (--workers 0). With `trees` (name ->
    src/), every tree's command runs in the same rounds (the trees' order alternating from
    round to round); the first tree's figures are the main ones, the others' under "trees"."""
    import pyarrow.parquet as pq

    def name(w: int | None) -> str:
        return "default" if w is None else str(w)

    trees = trees or {"HEAD": None}
    times = {t: {name(w): [] for w in counts} for t in trees}
    for r in range(repeats):
        for w in counts:
            order = list(trees) if r % 2 == 0 else list(trees)[::-1]
            for tree in order:
                t = sweep_once(w, runs, tmp / f"{tree}-w{name(w)}", trees[tree])
                times[tree][name(w)].append(t)
                print(f"  repeat {r + 1}: {tree} --workers {name(w)}: {t['wall']:.2f} s, CPU "
                      f"{t['cpu']:.2f} s (start {t['start']:.2f} s, tasks {t['tasks']:.2f} s), "
                      f"load {os.getloadavg()[0]:.1f}", flush=True)  # fmt: skip
    tables = [
        pq.read_table(tmp / f"{t}-w{name(w)}" / "sweep.parquet") for t in trees for w in counts
    ]
    same = all(t.equals(tables[0]) for t in tables[1:])
    per_tree = {}
    for tree, ts_of in times.items():
        med = {
            w: {k: statistics.median(t[k] for t in ts) for k in ts[0]} for w, ts in ts_of.items()
        }
        # every ratio is of medians of repeats taken in turn: a disturbance of the shared
        # machine hits all counts alike
        ratios = (
            {w: med["0"]["wall"] / med[w]["wall"] for w in med if w != "0"} if "0" in med else {}
        )
        per_tree[tree] = {"median": med, "all": ts_of, "speedup_vs_in_process": ratios}
    first = per_tree[next(iter(trees))]
    return {
        "vary": VARY,
        "runs_per_point": runs,
        **first,  # > 1 in speedup_vs_in_process: faster than --workers 0
        "trees": per_tree,
        "identical_tables": same,
    }


def bench_overhead(n_tasks: int) -> dict:
    from fusionlog.scenario import load_scenario
    from fusionlog.stages.distributed import DaskExecutor, on_worker
    from fusionlog.stages.montecarlo import Job, block_sums

    logging.getLogger("distributed").setLevel(logging.ERROR)
    sc = load_scenario(SCENARIO)
    job = Job(sc, tuple(sc.architectures), uuid.uuid4().hex)
    sample = block_sums(job, 0, 8)
    arg_bytes = len(pickle.dumps((job, 0, 8), protocol=5))
    result_bytes = len(pickle.dumps(sample, protocol=5))
    with DaskExecutor(workers=1) as ex:
        client = ex._client  # the benchmark looks inside: one task at a time
        # as the executor submits a task: with the worker's plan caches
        client.submit(on_worker, block_sums, job, 0, 8, pure=False).result()  # warm: plans
        lat, own = [], []
        for _ in range(n_tasks):
            t0 = time.perf_counter()
            r = client.submit(on_worker, block_sums, job, 0, 8, pure=False).result()
            lat.append(time.perf_counter() - t0)
            own.append(r.seconds)
        t0 = time.perf_counter()
        results = list(ex.map([(block_sums, (job, 0, 8))] * n_tasks, "overhead"))
        wall = time.perf_counter() - t0
    worker_s = sum(r.seconds for r in results)
    return {
        "tasks": n_tasks,
        "arg_bytes": arg_bytes,
        "result_bytes": result_bytes,
        "roundtrip_s": statistics.median(lat),
        "roundtrip_overhead_s": statistics.median(a - b for a, b in zip(lat, own, strict=True)),
        "task_compute_s": statistics.median(own),
        "pipelined_overhead_s": (wall - worker_s) / n_tasks,
    }


def bench_block() -> dict:
    from fusionlog.core.names import STATE_ARCHITECTURES
    from fusionlog.driver import JobPlans
    from fusionlog.scenario import load_scenario, scenario_with
    from fusionlog.stages.montecarlo import Job, block_sums, blocks, point_expected

    plans = JobPlans()  # as an executor keeps them: the first block compiles
    sc = scenario_with(load_scenario(SCENARIO), runs=STUDY_RUNS)
    job = Job(sc, tuple(STATE_ARCHITECTURES), "bench-block")
    parts = blocks(sc)
    off, n = parts[1]
    block_sums(job, *parts[0], plans=plans)  # warm: plans, workspace
    secs = []
    for _ in range(3):
        secs.append(block_sums(job, off, n, plans=plans).seconds)
    t0 = time.perf_counter()
    point_expected(Job(sc, job.archs, "bench-exact"), plans=plans)
    exact = time.perf_counter() - t0
    result = block_sums(job, 0, 8, plans=plans)
    return {
        "architectures": len(job.archs),
        "block_runs": n,
        "blocks_per_point": len(parts),
        "block_s": statistics.median(secs),
        "per_run_s": statistics.median(secs) / n,
        "exact_point_s": exact,
        "result_bytes": len(pickle.dumps(result, protocol=5)),
        "arg_bytes": len(pickle.dumps((job, off, n), protocol=5)),
    }


def study(block: dict, over: dict, cores_per_node: int) -> dict:
    """The 10^8-run study on NODES nodes of `cores_per_node` single-threaded workers."""
    workers = NODES * cores_per_node
    tasks_blocks = STUDY_POINTS * block["blocks_per_point"]
    tasks = tasks_blocks + STUDY_POINTS  # one exact analysis per point
    moved = tasks_blocks * (block["arg_bytes"] + block["result_bytes"])
    compute = STUDY_POINTS * (STUDY_RUNS * block["per_run_s"] + block["exact_point_s"])
    per_worker = math.ceil(tasks / workers)
    # each worker runs its share back to back; the overhead of a task is paid per task
    t = per_worker * (block["block_s"] + over["pipelined_overhead_s"])
    return {
        "workers": workers,
        "tasks": tasks,
        "bytes_moved": moved,
        "cpu_seconds": compute,
        "tasks_per_worker": per_worker,
        "expected_s": t,
        "one_worker_s": compute,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="2 x 10^4 runs per point, one repeat")
    ap.add_argument("--runs", type=int, default=None, help="runs per grid point (2 x 10^5)")
    ap.add_argument("--repeats", type=int, default=None, help="alternating repeats (3)")
    ap.add_argument("--overhead-tasks", type=int, default=200)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--sweep-only", action="store_true", help="only 1. (the executors)")
    ap.add_argument("--base", type=Path, default=None, help="also a baseline tree (its src/), "
                    "in the same rounds (1. only)")  # fmt: skip
    args = ap.parse_args(argv)
    trees = {"HEAD": ROOT / "src"} | ({"base": args.base / "src"} if args.base else {})
    runs = args.runs or (20_000 if args.quick else 200_000)
    repeats = args.repeats or (1 if args.quick else 3)
    out: dict = {"machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                             "load_before": os.getloadavg()}}  # fmt: skip

    print(f"1. sweep --vary {VARY} --runs {runs}: --workers 0 (this process), 1, 2 "
          f"({repeats} repeats in turn; load average {os.getloadavg()[0]:.1f})")  # fmt: skip
    with tempfile.TemporaryDirectory(prefix="fusionlog-bench-sweep-") as tmp:
        w = out["workers"] = bench_workers(runs, repeats, Path(tmp), trees=trees)
        small = runs // 10
        print(f"   the same at {small} runs per point: the default (no --workers) vs 0 and 2")
        head = {"HEAD": trees["HEAD"]}
        out["default"] = bench_workers(small, repeats, Path(tmp), (None, 0, 2), head)
    ok = True
    for tree, tw in w["trees"].items():
        med = tw["median"]
        for k in ("0", "1", "2"):
            m = med[k]
            print(f"  {tree} --workers {k}, medians: wall {m['wall']:.2f} s, CPU "
                  f"{m['cpu']:.2f} s = start {m['start']:.2f} + {int(m['tasks_n'])} tasks "
                  f"{m['tasks']:.2f} + outputs {m['outputs']:.2f} + stop {m['stop']:.2f} + "
                  "interpreter/imports")  # fmt: skip
        one = med["1"]["wall"] / med["0"]["wall"]
        two = tw["speedup_vs_in_process"]["2"]
        if tree == "HEAD":  # the exit status: this tree's targets
            ok = one <= T_ONE_WORKER and two >= T_TWO_WORKERS
        print(f"  {tree}: 1 worker / this process: {one:.2f}x wall (target <= {T_ONE_WORKER}x: "
              f"{'met' if one <= T_ONE_WORKER else 'MISSED'}); this process / 2 workers: "
              f"{two:.2f}x (target >= {T_TWO_WORKERS}x: "
              f"{'met' if two >= T_TWO_WORKERS else 'MISSED'})")  # fmt: skip
        print(
            f"  {tree}: CPU a worker adds: the first {med['1']['cpu'] - med['0']['cpu']:.2f} s "
            f"(its start, Dask in this process), the second "
            f"{med['2']['cpu'] - med['1']['cpu']:.2f} s"
        )
    print(f"  tables identical: {w['identical_tables']}")
    d = out["default"]["median"]
    print(f"  {small} runs per point: default {d['default']['wall']:.2f} s, --workers 0 "
          f"{d['0']['wall']:.2f} s, --workers 2 {d['2']['wall']:.2f} s; load average "
          f"{os.getloadavg()[0]:.1f}")  # fmt: skip

    if args.sweep_only:
        if args.json is not None:
            args.json.write_text(json.dumps(out, indent=2, default=str))
        return 0 if ok else 1
    print(f"2. per-task overhead, LocalCluster of 1 worker, {args.overhead_tasks} tasks")
    o = out["overhead"] = bench_overhead(args.overhead_tasks)
    print(f"  round trip {1e3 * o['roundtrip_s']:.2f} ms, of which the task itself "
          f"{1e3 * o['task_compute_s']:.2f} ms: overhead {1e3 * o['roundtrip_overhead_s']:.2f} ms "
          f"one at a time, {1e3 * o['pipelined_overhead_s']:.2f} ms amortised through the "
          f"window; arguments {o['arg_bytes']} B, result {o['result_bytes']} B")  # fmt: skip

    print("3. per-block cost, this process, the registry's 8 architectures")
    b = out["block"] = bench_block()
    print(f"  block of {b['block_runs']} runs: {b['block_s']:.3f} s "
          f"({1e6 * b['per_run_s']:.2f} us per run), {b['blocks_per_point']} blocks per 10^6-run "
          f"point; exact analysis of a point {b['exact_point_s']:.3f} s; arguments "
          f"{b['arg_bytes']} B, result {b['result_bytes']} B")  # fmt: skip

    print(f"4. the 10^8-run study ({STUDY_RUNS} runs x {STUDY_POINTS} points x {STUDY_ARCHS} "
          f"architectures) on {NODES} nodes")  # fmt: skip
    out["study"] = {}
    for cores in (2, 32):
        s = out["study"][cores] = study(b, o, cores)
        print(f"  {cores} cores per node: {s['workers']} workers, {s['tasks']} tasks "
              f"({s['tasks_per_worker']} per worker), {s['bytes_moved'] / 1e6:.1f} MB moved, "
              f"{s['cpu_seconds'] / 3600:.2f} CPU-hours -> about {s['expected_s']:.1f} s "
              f"(plus the cluster's start)")  # fmt: skip
    out["machine"]["load_after"] = os.getloadavg()
    if args.json is not None:
        args.json.write_text(json.dumps(out, indent=2, default=str))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
