"""End-to-end benchmark of the `fusionlog` pipeline: the whole CLI, files and all.

Every fusionlog figure here is a `fusionlog run ...` child process, timed from spawn to exit
(interpreter start, imports, simulation, both MCAP files, the .rrd recording, summary.json), with
the child's own peak RSS from `os.wait4` (ru_maxrss of that process, not of this one; it is
spawned through a small launcher interpreter, see LAUNCHER). The run
command prints "simulate X s, estimate Y s, evaluate Z s"; those per-stage times are parsed.

Cases (the project's issue 6 targets):

1. Paper example: `fusionlog run pipeline/ajgl2009.toml` (M = 10^4, K = 20, seven architectures)
   against FilterPy's `KalmanFilter` running only the CKF in memory on the same z (read back from
   the sensors.mcap the run wrote; update at k = 0, predict + update after). FilterPy is timed on a
   subset of the runs and scaled linearly to M. The two are timed alternately, several times, and
   medians are compared. Target: fusionlog run >= 3x faster (issue 11; issue 6 asked 2x).
2. Estimation core: the JSON of `bench_core.py --json` (passed with --core-json; run_all.py does
   this). Target: every architecture >= 20x simdkalman's CKF throughput.
3. Scale: the paper's five architectures, K = 20, M = 10^5 and 10^6 (--quick: 10^4 and 10^5).
   Targets: peak RSS <= 2 GiB at the larger M, time(large)/time(small) <= 11.
4. Long log: one run, K = 100 000 (--quick: 2000), three sensors, seven architectures.
   Targets: wall < 60 s, >= 150 000 MCAP messages/s in every stage (messages written + read per
   second of stage time; counts from the files' summary statistics).
5. Every stage's bytes moved (sizes of the files it reads + writes) per second, against a plain
   numpy.save (+ fsync, as fusionlog's writer does) / numpy.load of arrays of the same shapes
   (truth, measurements, estimate means) in the same temporary folder, measured in the same run.

Outputs go to a temporary folder (default under /tmp) that is deleted afterwards; a case whose
outputs would not fit in the free space is skipped with a message.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
try:
    import fusionlog  # noqa: F401
except ImportError:  # running from a checkout without `pip install -e .`
    sys.path.insert(0, str(ROOT / "src"))

from bench_core import filterpy_ckf  # noqa: E402

from fusionlog.core.names import PAPER_ARCHITECTURES  # noqa: E402
from fusionlog.io.atomic import Outputs  # noqa: E402
from fusionlog.io.mcap import McapFile, McapWriter  # noqa: E402
from fusionlog.stages.common import scenario_from_file  # noqa: E402

SCENARIO = ROOT / "pipeline" / "ajgl2009.toml"
STAGES = ("simulate", "estimate", "evaluate")
STAGE_RE = re.compile(r"simulate ([\d.]+) s, estimate ([\d.]+) s, evaluate ([\d.]+) s")
OUTPUTS = ("sensors.mcap", "estimates.mcap", "evaluation.rrd", "summary.json")
MIB = 1024.0**2
GIB = 1024.0**3

# Targets of issue 6 (the paper example's raised to 3x by issue 11).
T_PAPER_SPEEDUP = 3.0
T_CORE_X_SIMDKALMAN = 20.0
T_SCALE_RSS_GIB = 2.0
T_SCALE_RATIO = 11.0
T_LONG_WALL_S = 60.0
T_MSGS_PER_S = 150_000.0


# --------------------------------------------------------------------------------------------
# Child processes


@dataclass
class Child:
    wall_s: float
    peak_rss_mib: float
    stdout: str
    stderr: str
    stages: dict[str, float] = field(default_factory=dict)

    @property
    def other_s(self) -> float:
        """Wall time outside the three stages: interpreter start, imports, loading, exit."""
        return self.wall_s - sum(self.stages.values())


def git_revision() -> str:
    """Commit of the checkout being measured (with "+dirty" for uncommitted changes in src/)."""
    try:
        rev = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--", "src"], cwd=ROOT, capture_output=True, text=True
        ).stdout.strip()
    except OSError:
        return "unknown"
    return (rev or "unknown") + ("+dirty" if dirty else "")


def fusionlog_cmd() -> list[str]:
    exe = Path(sys.executable).parent / "fusionlog"
    if exe.exists():
        return [str(exe)]
    found = shutil.which("fusionlog")
    return [found] if found else [sys.executable, "-m", "fusionlog.cli"]


# Runs the measured command as its own child and reports that child's wall time and peak RSS.
# Why a launcher: on Linux a child's ru_maxrss includes the high-water RSS of the process it was
# forked from (exec records the old address space's peak), so a command spawned straight from this
# benchmark would report at least this process's own peak (e.g. the 2 GiB numpy baseline arrays).
# The launcher is a fresh, small interpreter, so its child's figure is the command's own.
LAUNCHER = """
import json, os, subprocess, sys, time
t0 = time.perf_counter()
p = subprocess.Popen(sys.argv[2:])
_, status, usage = os.wait4(p.pid, 0)
wall = time.perf_counter() - t0
with open(sys.argv[1], "w") as f:
    json.dump({"wall": wall, "maxrss": usage.ru_maxrss, "rc": os.waitstatus_to_exitcode(status)}, f)
"""


def run_child(cmd: list[str], workdir: Path) -> Child:
    """Run cmd to completion: wall time from spawn to reaping and the command's own peak RSS."""
    out_path, err_path = workdir / ".child.out", workdir / ".child.err"
    info_path = workdir / ".child.json"
    launch = [sys.executable, "-c", LAUNCHER, str(info_path), *cmd]
    with open(out_path, "wb") as out, open(err_path, "wb") as err:
        subprocess.run(launch, stdout=out, stderr=err, stdin=subprocess.DEVNULL, cwd=ROOT)
    stdout, stderr = out_path.read_text(), err_path.read_text()
    info = json.loads(info_path.read_text())
    for p in (out_path, err_path, info_path):
        p.unlink()
    if info["rc"] != 0:
        raise RuntimeError(
            f"{' '.join(cmd)} exited with {info['rc']}:\n{stdout[-2000:]}{stderr[-2000:]}"
        )
    rss = info["maxrss"] / (MIB if sys.platform == "darwin" else 1024.0)
    child = Child(info["wall"], rss, stdout, stderr)
    m = STAGE_RE.search(stdout)
    if m:
        child.stages = dict(zip(STAGES, map(float, m.groups()), strict=True))
    return child


def fusionlog_run(
    out_dir: Path, runs: int | None = None, steps: int | None = None, archs: tuple[str, ...] = ()
) -> Child:
    cmd = [*fusionlog_cmd(), "run", str(SCENARIO), "--out-dir", str(out_dir), "--force"]
    if runs is not None:
        cmd += ["--runs", str(runs)]
    if steps is not None:
        cmd += ["--steps", str(steps)]
    for a in archs:
        cmd += ["--arch", a]
    return run_child(cmd, out_dir.parent)


def import_overhead(workdir: Path) -> tuple[float, float]:
    """(child wall s, import s) of a bare interpreter importing what `fusionlog run` imports."""
    code = (
        "import time; t = time.perf_counter(); import fusionlog.cli, fusionlog.scenario, "
        "fusionlog.stages.simulate, fusionlog.stages.estimate, fusionlog.stages.evaluate, "
        "fusionlog.report; print(time.perf_counter() - t)"
    )
    c = run_child([sys.executable, "-c", code], workdir)
    return c.wall_s, float(c.stdout.strip())


# --------------------------------------------------------------------------------------------
# Files


def sizes(out_dir: Path) -> dict[str, int]:
    return {name: (out_dir / name).stat().st_size for name in OUTPUTS}


def message_counts(path: Path) -> int:
    """Messages in an MCAP file, from its summary statistics (reads only the summary)."""
    return sum(McapFile(path).topics.values())


def stage_io(sz: dict[str, int], msgs: dict[str, int]) -> dict[str, dict[str, int]]:
    """Bytes and messages each stage reads and writes.

    simulate writes sensors.mcap; estimate reads sensors.mcap (every chunk: the sensor topics are
    interleaved with /truth) and writes estimates.mcap; evaluate reads both MCAP files and writes
    evaluation.rrd and summary.json. Messages read are all the messages of the files read: of
    sensors.mcap evaluate decodes only /truth (a quarter of them), reached through the chunks'
    message indexes, so its rate is that of getting through the files, not of decoding.
    """
    s, e = sz["sensors.mcap"], sz["estimates.mcap"]
    ms, me = msgs["sensors.mcap"], msgs["estimates.mcap"]
    out = sz["evaluation.rrd"] + sz["summary.json"]
    return {
        "simulate": {"read": 0, "written": s, "msgs_read": 0, "msgs_written": ms},
        "estimate": {"read": s, "written": e, "msgs_read": ms, "msgs_written": me},
        "evaluate": {"read": s + e, "written": out, "msgs_read": ms + me, "msgs_written": 0},
    }


def expected_bytes(runs: int, steps: int, n_archs: int, n: int = 2, m: int = 3) -> int:
    """Rough size of the outputs (payload doubles + 15 % for headers, indexes, the .rrd)."""
    return int(1.15 * runs * (steps + 1) * 8 * (n + m + n_archs * (n + (n * n if runs < 4 else 0))))


def enough_space(where: Path, need: int, label: str) -> bool:
    free = shutil.disk_usage(where).free
    if free < 1.2 * need + 512 * MIB:
        print(
            f"SKIPPED {label}: needs about {need / GIB:.2f} GiB in {where}, "
            f"only {free / GIB:.2f} GiB free"
        )
        return False
    return True


# --------------------------------------------------------------------------------------------
# numpy baseline: the same arrays through numpy.save / numpy.load on the same disk


def _save(path: Path, a: np.ndarray) -> float:
    t0 = time.perf_counter()
    with open(path, "wb") as f:
        np.save(f, a)
        f.flush()
        os.fsync(f.fileno())  # fusionlog's writer fsyncs every output file too
    return time.perf_counter() - t0


def _load(path: Path) -> float:
    t0 = time.perf_counter()
    a = np.load(path)
    a.sum()  # touch it (np.load reads eagerly; this is cheap next to the read)
    return time.perf_counter() - t0


def numpy_baseline(workdir: Path, runs: int, steps: int, n_archs: int, repeats: int) -> dict:
    """numpy's bytes/s for each stage's equivalent: simulate = save truth + z, estimate =
    load z + save the means, evaluate = load truth + the means. Median over repeats."""
    shapes = {
        "truth": (runs, steps + 1, 2),
        "z": (runs, steps + 1, 3),
        "means": (n_archs, runs, steps + 1, 2),
    }
    rng = np.random.default_rng(0)
    plan = {
        "simulate": [("save", "truth"), ("save", "z")],
        "estimate": [("load", "z"), ("save", "means")],
        "evaluate": [("load", "truth"), ("load", "means")],
    }
    times: dict[str, list[float]] = {s: [] for s in STAGES}
    nbytes: dict[str, int] = {}
    for _ in range(repeats):
        for stage, ops in plan.items():
            t = 0.0
            moved = 0
            for op, name in ops:
                path = workdir / f"{name}.npy"
                if op == "save":
                    a = rng.standard_normal(shapes[name])
                    t += _save(path, a)
                    del a
                else:
                    t += _load(path)
                moved += path.stat().st_size
            times[stage].append(t)
            nbytes[stage] = moved
    for name in shapes:
        (workdir / f"{name}.npy").unlink(missing_ok=True)
    return {
        s: {"bytes": nbytes[s], "s": statistics.median(times[s]), "times_s": times[s]}
        for s in STAGES
    }


def throughput_rows(case: str, stages: dict[str, float], io: dict, base: dict) -> list[dict]:
    rows = []
    for s in STAGES:
        t = stages[s]
        moved = io[s]["read"] + io[s]["written"]
        msgs = io[s]["msgs_read"] + io[s]["msgs_written"]
        np_rate = base[s]["bytes"] / base[s]["s"]
        rate = moved / t if t > 0 else float("inf")
        rows.append(
            {
                "case": case,
                "stage": s,
                "stage_s": t,
                "bytes": moved,
                "msgs_read": io[s]["msgs_read"],
                "msgs_written": io[s]["msgs_written"],
                "bytes_per_s": rate,
                "msgs_per_s": msgs / t if t > 0 else float("inf"),
                "numpy_bytes": base[s]["bytes"],
                "numpy_s": base[s]["s"],
                "numpy_bytes_per_s": np_rate,
                "vs_numpy": rate / np_rate,
            }
        )
    return rows


# --------------------------------------------------------------------------------------------
# Cases


def load_z(sensors: Path) -> tuple[object, np.ndarray]:
    """The filter model and every run's stacked measurements (M, K+1, m) of a sensors file."""
    mf = McapFile(sensors)
    system = scenario_from_file(mf).system
    topics = [f"/sensors/{s.name}" for s in system.sensors]
    parts = [data for _, _, data in mf.iter_run_blocks(topics, mf.runs())]
    z = np.concatenate([np.concatenate([d[t] for t in topics], axis=-1) for d in parts])
    return system, z


def load_ckf_means(estimates: Path, runs: int) -> np.ndarray:
    mf = McapFile(estimates)
    (_, _, data) = next(iter(mf.iter_run_blocks(["/estimates/CKF"], runs)))
    return data["/estimates/CKF"][0]


def case_paper(work: Path, repeats: int, fp_runs: int) -> dict:
    print(
        f"== 1. paper example: fusionlog run {SCENARIO.relative_to(ROOT)} "
        f"(its M, K and architectures) vs FilterPy CKF, {repeats} alternating repeats"
    )
    out = work / "paper"
    first = fusionlog_run(out)  # warm-up: page cache, .pyc files; also gives the data
    system, z = load_z(out / "sensors.mcap")
    M, K1, _ = z.shape
    fp_runs = min(fp_runs, M)
    fp_mean, _ = filterpy_ckf(system, z[:fp_runs])
    ours = load_ckf_means(out / "estimates.mcap", fp_runs)
    diff = float(np.max(np.abs(fp_mean - ours)))
    print(
        f"   FilterPy CKF vs estimates.mcap /estimates/CKF on {fp_runs} runs: max |diff| {diff:.1e}"
    )
    if not diff <= 1e-8 * float(np.max(np.abs(ours))):
        raise RuntimeError(f"FilterPy and fusionlog CKF disagree by {diff:g}")
    sz = sizes(out)
    msgs = {f: message_counts(out / f) for f in ("sensors.mcap", "estimates.mcap")}
    archs = json.loads((out / "summary.json").read_text())["architectures"]
    runs: list[Child] = []
    fp_times: list[float] = []
    zsub = np.ascontiguousarray(z[:fp_runs])
    for _ in range(repeats):
        runs.append(fusionlog_run(out))
        t0 = time.perf_counter()
        filterpy_ckf(system, zsub)
        fp_times.append((time.perf_counter() - t0) * M / fp_runs)
    imp_wall, imp_s = import_overhead(work)
    med = {
        "wall_s": statistics.median(c.wall_s for c in runs),
        "peak_rss_mib": statistics.median(c.peak_rss_mib for c in runs),
        **{s: statistics.median(c.stages[s] for c in runs) for s in STAGES},
        "other_s": statistics.median(c.other_s for c in runs),
    }
    fp = statistics.median(fp_times)
    res = {
        "runs": M,
        "steps": K1 - 1,
        "architectures": list(archs),
        "repeats": repeats,
        "fusionlog": med,
        "fusionlog_walls_s": [c.wall_s for c in runs],
        "warmup_wall_s": first.wall_s,
        "filterpy_s": fp,
        "filterpy_times_s": fp_times,
        "filterpy_timed_runs": fp_runs,
        "speedup": fp / med["wall_s"],
        "import_child_wall_s": imp_wall,
        "import_s": imp_s,
        "sizes": sz,
        "messages": msgs,
        "io": stage_io(sz, msgs),
    }
    walls = res["fusionlog_walls_s"]
    print(
        f"   fusionlog run walls: {', '.join(f'{w:.2f}' for w in walls)} s; "
        f"FilterPy (scaled): {', '.join(f'{t:.2f}' for t in fp_times)} s"
    )
    print()
    return res


def case_scale(work: Path, sizes_m: tuple[int, int], steps: int) -> dict:
    small, large = sizes_m
    print(
        f"== 3. scale: fusionlog run --runs {small} / {large}, K = {steps}, "
        f"archs {' '.join(PAPER_ARCHITECTURES)}"
    )
    res: dict = {"steps": steps, "archs": list(PAPER_ARCHITECTURES), "cases": {}}
    for M in sizes_m:
        need = expected_bytes(M, steps, len(PAPER_ARCHITECTURES))
        if not enough_space(work, need, f"scale M = {M}"):
            res["cases"][str(M)] = None
            continue
        out = work / f"scale{M}"
        c = fusionlog_run(out, runs=M, steps=steps, archs=PAPER_ARCHITECTURES)
        sz = sizes(out)
        msgs = {f: message_counts(out / f) for f in ("sensors.mcap", "estimates.mcap")}
        shutil.rmtree(out)
        print(
            f"   M = {M}: {c.wall_s:.2f} s, peak RSS {c.peak_rss_mib:.0f} MiB, outputs "
            f"{sum(sz.values()) / MIB:.0f} MiB (deleted); numpy baseline ..."
        )
        base = numpy_baseline(work, M, steps, len(PAPER_ARCHITECTURES), 1 if M > 200_000 else 3)
        res["cases"][str(M)] = {
            "runs": M,
            "wall_s": c.wall_s,
            "peak_rss_mib": c.peak_rss_mib,
            "stages": c.stages,
            "other_s": c.other_s,
            "sizes": sz,
            "messages": msgs,
            "io": stage_io(sz, msgs),
            "numpy": base,
        }
    a, b = res["cases"].get(str(small)), res["cases"].get(str(large))
    if a and b:
        res["ratio_wall"] = b["wall_s"] / a["wall_s"]
        res["ratio_stages"] = {s: b["stages"][s] / a["stages"][s] for s in STAGES}
    print()
    return res


def mcap_layer_rates(out: Path, work: Path) -> dict[str, dict[str, float]]:
    """Messages/s of fusionlog's MCAP layer alone, on the long log's own files: McapFile reading
    every topic (mcap's record reader, payload decoding, assembly into arrays) and McapWriter
    writing the same messages again (payload encoding, foxglove-sdk's writer, close + fsync).
    No estimation, metrics or recording: this is the I/O part of each stage's time."""
    res: dict[str, dict[str, float]] = {}
    for name in ("sensors.mcap", "estimates.mcap"):
        f = McapFile(out / name)
        topics = sorted(f.topics)
        n = sum(f.topics.values())
        t0 = time.perf_counter()
        data = f.read_all(topics)
        t_read = time.perf_counter() - t0
        times = f.times()
        copy = work / f"copy-{name}"
        t0 = time.perf_counter()
        # the way the stages write: through Outputs (temporary file, fsync, rename on commit)
        with Outputs([copy], force=True) as outs:
            with McapWriter(outs.open(copy)) as w:
                for k in range(len(times)):
                    for topic in topics:
                        d = data[topic]
                        if isinstance(d, tuple):
                            mean, cov = d
                            w.write_estimate(
                                topic,
                                k,
                                times[k],
                                0,
                                mean[:, k],
                                cov[k] if cov.ndim == 3 else cov[:, k],
                            )
                        else:
                            w.write_values(topic, k, times[k], 0, d[:, k])
            outs.commit()
        t_write = time.perf_counter() - t0
        copy.unlink()
        res[name] = {"messages": n, "read_per_s": n / t_read, "write_per_s": n / t_write}
        print(
            f"   MCAP layer, {name}: read {n / t_read:.0f} msgs/s, write {n / t_write:.0f} msgs/s"
        )
    return res


def case_long(work: Path, steps: int) -> dict:
    print(f"== 4. long log: fusionlog run --runs 1 --steps {steps} (scenario's architectures)")
    out = work / "long"
    c = fusionlog_run(out, runs=1, steps=steps)
    sz = sizes(out)
    msgs = {f: message_counts(out / f) for f in ("sensors.mcap", "estimates.mcap")}
    archs = json.loads((out / "summary.json").read_text())["architectures"]
    layer = mcap_layer_rates(out, work)
    shutil.rmtree(out)
    base = numpy_baseline(work, 1, steps, len(archs), 3)
    print(f"   {c.wall_s:.2f} s, peak RSS {c.peak_rss_mib:.0f} MiB")
    print()
    return {
        "steps": steps,
        "architectures": list(archs),
        "wall_s": c.wall_s,
        "peak_rss_mib": c.peak_rss_mib,
        "stages": c.stages,
        "other_s": c.other_s,
        "sizes": sz,
        "messages": msgs,
        "io": stage_io(sz, msgs),
        "mcap_layer": layer,
        "numpy": base,
    }


# --------------------------------------------------------------------------------------------
# Report


def status(ok: bool) -> str:
    return "met" if ok else "MISSED"


def print_report(res: dict) -> list[dict]:
    targets: list[dict] = []

    def target(name: str, measured: str, goal: str, ok: bool | None, note: str = "") -> None:
        targets.append({"target": name, "measured": measured, "goal": goal, "ok": ok, "note": note})

    # ---- 1 ----
    p = res.get("paper")
    if p:
        f = p["fusionlog"]
        print(
            f"1. Paper example: M = {p['runs']}, K = {p['steps']}, {len(p['architectures'])} "
            f"architectures ({' '.join(p['architectures'])}); medians of {p['repeats']}"
        )
        head = f"{'case':44s} {'wall s':>8s} {'peak RSS MiB':>13s} {'x fusionlog':>12s}"
        print(head)
        print("-" * len(head))
        print(
            f"{'fusionlog run (child: start, imports, I/O)':44s} {f['wall_s']:8.2f} "
            f"{f['peak_rss_mib']:13.0f} {1.0:12.2f}"
        )
        for s in STAGES:
            print(f"{'  ' + s + ' stage':44s} {f[s]:8.2f}")
        print(f"{'  rest (interpreter, imports, load, exit)':44s} {f['other_s']:8.2f}")
        print(
            f"{'  (bare child importing the stages)':44s} {p['import_child_wall_s']:8.2f}"
            f"{'':14s} {'':12s}  imports alone {p['import_s']:.2f} s"
        )
        print(
            f"{'FilterPy CKF only (in memory)':44s} {p['filterpy_s']:8.2f} {'':13s} "
            f"{p['filterpy_s'] / f['wall_s']:12.2f}  timed on {p['filterpy_timed_runs']} runs, "
            f"scaled x{p['runs'] / p['filterpy_timed_runs']:.4g}"
        )
        print()
        target(
            "paper: FilterPy CKF time / fusionlog run",
            f"{p['speedup']:.2f}x",
            f">= {T_PAPER_SPEEDUP:g}x",
            p["speedup"] >= T_PAPER_SPEEDUP,
        )

    # ---- 2 ----
    core = res.get("core")
    if core:
        rows = [
            r
            for r in core["results"]
            if r["name"].startswith("fusionlog ") and not r["name"].endswith("per-run")
        ]
        print(
            f"2. Estimation core (bench_core.py, M = {core['runs']}, K = {core['steps']}): "
            "throughput relative to simdkalman's CKF"
        )
        head = (
            f"{'architecture':14s} {'median s':>9s} {'plan ms':>8s} {'x simdkalman':>13s}  target"
        )
        print(head)
        print("-" * len(head))
        for r in rows:
            x = r["vs_simdkalman_ckf"]
            plan = f"{1e3 * r['plan_s']:8.2f}" if r.get("plan_s") is not None else f"{'':8s}"
            print(
                f"{r['name'].removeprefix('fusionlog '):14s} {r['median_s']:9.4f} {plan} "
                f"{x:13.2f}  {status(x >= T_CORE_X_SIMDKALMAN)}"
            )
        print()
        worst = min(rows, key=lambda r: r["vs_simdkalman_ckf"])
        below = [
            f"{r['name'].removeprefix('fusionlog ')} {r['vs_simdkalman_ckf']:.1f}x"
            for r in rows
            if r["vs_simdkalman_ckf"] < T_CORE_X_SIMDKALMAN
        ]
        target(
            f"core (M = {core['runs']}): every arch x simdkalman CKF",
            f"min {worst['vs_simdkalman_ckf']:.1f}x ({worst['name'].removeprefix('fusionlog ')})",
            f">= {T_CORE_X_SIMDKALMAN:g}x",
            not below,
            ("below: " + ", ".join(below)) if below else "",
        )
    else:
        print("2. Estimation core: not included (run benchmarks/run_all.py, or pass --core-json)")
        print()

    # ---- 3 ----
    sc = res.get("scale")
    if sc:
        print(
            f"3. Scale: K = {sc['steps']}, {' '.join(sc['archs'])}; one run each "
            "(outputs deleted afterwards)"
        )
        head = (
            f"{'runs':>9s} {'wall s':>8s} {'simulate':>9s} {'estimate':>9s} {'evaluate':>9s} "
            f"{'rest':>6s} {'peak RSS MiB':>13s} {'sensors MiB':>12s} {'estim. MiB':>11s} "
            f"{'rrd MiB':>8s}"
        )
        print(head)
        print("-" * len(head))
        cases = [c for c in sc["cases"].values() if c]
        for c in cases:
            st, sz = c["stages"], c["sizes"]
            print(
                f"{c['runs']:9d} {c['wall_s']:8.2f} {st['simulate']:9.2f} {st['estimate']:9.2f} "
                f"{st['evaluate']:9.2f} {c['other_s']:6.2f} {c['peak_rss_mib']:13.0f} "
                f"{sz['sensors.mcap'] / MIB:12.1f} {sz['estimates.mcap'] / MIB:11.1f} "
                f"{sz['evaluation.rrd'] / MIB:8.1f}"
            )
        if "ratio_wall" in sc:
            r = sc["ratio_stages"]
            print(
                f"{'ratio':>9s} {sc['ratio_wall']:8.2f} {r['simulate']:9.2f} "
                f"{r['estimate']:9.2f} {r['evaluate']:9.2f}   (larger M / smaller M; "
                f"{cases[1]['runs'] / cases[0]['runs']:g}x the runs)"
            )
        print()
        if cases:
            big = cases[-1]
            target(
                f"scale: peak RSS at M = {big['runs']}",
                f"{big['peak_rss_mib']:.0f} MiB",
                f"<= {T_SCALE_RSS_GIB:g} GiB",
                big["peak_rss_mib"] <= T_SCALE_RSS_GIB * 1024,
            )
        if "ratio_wall" in sc:
            target(
                "scale: time(large M) / time(small M)",
                f"{sc['ratio_wall']:.2f}",
                f"<= {T_SCALE_RATIO:g}",
                sc["ratio_wall"] <= T_SCALE_RATIO,
            )

    # ---- 4 ----
    lg = res.get("long")
    if lg:
        print(
            f"4. Long log: 1 run, K = {lg['steps']}, {len(lg['architectures'])} architectures: "
            f"wall {lg['wall_s']:.2f} s, peak RSS {lg['peak_rss_mib']:.0f} MiB, "
            f"rest (start, imports, exit) {lg['other_s']:.2f} s"
        )
        head = (
            f"{'stage':9s} {'s':>7s} {'msgs written':>13s} {'msgs read':>10s} "
            f"{'written/s':>10s} {'read/s':>10s} {'(w+r)/s':>10s}  target >= {T_MSGS_PER_S:.0f}/s"
        )
        print(head)
        print("-" * len(head))
        rates = []
        for s in STAGES:
            t, io = lg["stages"][s], lg["io"][s]
            w, r = io["msgs_written"], io["msgs_read"]
            rate = (w + r) / t
            rates.append((rate, s))
            print(
                f"{s:9s} {t:7.2f} {w:13d} {r:10d} {w / t:10.0f} {r / t:10.0f} {rate:10.0f}  "
                f"{status(rate >= T_MSGS_PER_S)}"
            )
        sizes_ = lg["sizes"]
        print(
            f"files: sensors {sizes_['sensors.mcap'] / MIB:.1f} MiB, estimates "
            f"{sizes_['estimates.mcap'] / MIB:.1f} MiB, evaluation.rrd "
            f"{sizes_['evaluation.rrd'] / MIB:.1f} MiB"
        )
        print()
        target(
            f"long log (K = {lg['steps']}): wall",
            f"{lg['wall_s']:.1f} s",
            f"< {T_LONG_WALL_S:g} s",
            lg["wall_s"] < T_LONG_WALL_S,
        )
        for name, r in lg.get("mcap_layer", {}).items():
            for what in ("write", "read"):
                v = r[f"{what}_per_s"]
                target(
                    f"long log: MCAP layer alone, {what} {name}",
                    f"{v:.0f}/s",
                    f">= {T_MSGS_PER_S:.0f}/s",
                    v >= T_MSGS_PER_S,
                )
        worst = min(rates)
        target(
            "long log: MCAP messages/s, slowest stage",
            f"{worst[0]:.0f}/s ({worst[1]})",
            f">= {T_MSGS_PER_S:.0f}/s",
            worst[0] >= T_MSGS_PER_S,
            ", ".join(f"{s} {r:.0f}/s" for r, s in rates),
        )

    # ---- 5 ----
    rows: list[dict] = []
    if p and "numpy" in p:
        rows += throughput_rows(
            f"paper M={p['runs']}", {s: p["fusionlog"][s] for s in STAGES}, p["io"], p["numpy"]
        )
    if sc:
        for c in sc["cases"].values():
            if c:
                rows += throughput_rows(f"scale M={c['runs']}", c["stages"], c["io"], c["numpy"])
    if lg:
        rows += throughput_rows(f"long K={lg['steps']}", lg["stages"], lg["io"], lg["numpy"])
    if rows:
        print(
            "5. Bytes moved per second of stage time (MCAP/.rrd files read + written) vs "
            "numpy.save(+fsync)/numpy.load of the same arrays in the same folder"
        )
        head = (
            f"{'case':14s} {'stage':9s} {'s':>7s} {'MiB moved':>10s} {'MiB/s':>8s} "
            f"{'msgs/s':>10s} {'numpy MiB':>10s} {'numpy MiB/s':>12s} {'vs numpy':>9s}"
        )
        print(head)
        print("-" * len(head))
        for r in rows:
            print(
                f"{r['case']:14s} {r['stage']:9s} {r['stage_s']:7.2f} {r['bytes'] / MIB:10.1f} "
                f"{r['bytes_per_s'] / MIB:8.1f} {r['msgs_per_s']:10.0f} "
                f"{r['numpy_bytes'] / MIB:10.1f} {r['numpy_bytes_per_s'] / MIB:12.1f} "
                f"{r['vs_numpy']:9.3f}"
            )
        print(
            "(simulate: write sensors.mcap vs save truth + z; estimate: read sensors.mcap + write "
            "estimates.mcap vs load z + save means;\n evaluate: read both MCAP files + write "
            ".rrd/summary vs load truth + means. Stage times are the run command's, 0.01 s "
            "resolution.)"
        )
        print()
    res["throughput"] = rows

    if targets:
        print("Targets (issue 6; the paper example's 3x from issue 11)")
        head = f"{'target':44s} {'measured':>22s} {'goal':>12s}  status"
        print(head)
        print("-" * len(head))
        for t in targets:
            st = "n/a" if t["ok"] is None else status(t["ok"])
            note = f"  {t['note']}" if t["note"] else ""
            print(f"{t['target']:44s} {t['measured']:>22s} {t['goal']:>12s}  {st}{note}")
        print()
    return targets


# --------------------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small sizes (about a minute)")
    ap.add_argument("--repeats", type=int, default=None, help="paper-example repeats (default 5)")
    ap.add_argument(
        "--filterpy-runs", type=int, default=None, help="runs FilterPy is timed on (default 1000)"
    )
    ap.add_argument("--scale-runs", type=int, nargs=2, default=None, metavar=("SMALL", "LARGE"))
    ap.add_argument("--long-steps", type=int, default=None, help="K of the long log")
    ap.add_argument(
        "--only",
        action="append",
        choices=("paper", "scale", "long"),
        help="run only these cases (repeatable)",
    )
    ap.add_argument("--core-json", type=Path, default=None, help="bench_core.py --json output")
    ap.add_argument("--tmp-dir", type=Path, default=Path(tempfile.gettempdir()))
    ap.add_argument("--json", type=Path, default=None, metavar="PATH", help="save the figures")
    args = ap.parse_args(argv)

    repeats = args.repeats or (2 if args.quick else 5)
    fp_runs = args.filterpy_runs or (100 if args.quick else 1000)
    scale_runs = tuple(args.scale_runs or ((10_000, 100_000) if args.quick else (10**5, 10**6)))
    long_steps = args.long_steps or (2000 if args.quick else 100_000)
    only = set(args.only or ("paper", "scale", "long"))

    print("fusionlog pipeline benchmark (whole `fusionlog run` child processes)")
    print(
        f"{time.strftime('%Y-%m-%d %H:%M')}, python {platform.python_version()}, numpy "
        f"{np.__version__}, {os.cpu_count()} CPUs, {platform.machine()}, "
        f"{platform.system()} {platform.release()}, fusionlog at commit {git_revision()}"
    )
    args.tmp_dir.mkdir(parents=True, exist_ok=True)
    du = shutil.disk_usage(args.tmp_dir)
    print(f"temporary folder under {args.tmp_dir}: {du.free / GIB:.1f} GiB free")
    print()

    res: dict = {
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
        "quick": args.quick,
        "commit": git_revision(),
        "platform": {
            "python": platform.python_version(),
            "numpy": np.__version__,
            "cpus": os.cpu_count(),
            "machine": platform.machine(),
            "system": f"{platform.system()} {platform.release()}",
        },
    }
    if args.core_json is not None:
        res["core"] = json.loads(args.core_json.read_text())
    work = Path(tempfile.mkdtemp(prefix="fusionlog-bench-", dir=args.tmp_dir))
    try:
        if "paper" in only:
            res["paper"] = case_paper(work, repeats, fp_runs)
            p = res["paper"]
            res["paper"]["numpy"] = numpy_baseline(
                work, p["runs"], p["steps"], len(p["architectures"]), 3
            )
        if "scale" in only:
            res["scale"] = case_scale(work, scale_runs, 20)
        if "long" in only:
            res["long"] = case_long(work, long_steps)
    finally:
        shutil.rmtree(work, ignore_errors=True)

    res["targets"] = print_report(res)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(res, indent=2, default=_jsonable) + "\n")
        print(f"figures saved to {args.json}")
    return 0


def _jsonable(o: object) -> object:
    if isinstance(o, Child):
        return asdict(o)
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


if __name__ == "__main__":
    raise SystemExit(main())
