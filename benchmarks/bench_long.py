"""Hour-long logs (issue 34): one run of 10^5, 10^6 and 4*10^6 instants through `fusionlog run`
with the paper's seven architectures, in blocks of time, beside FilterPy's KF loop on the
same log; and a 10^6-row recorded CSV replayed.

    .venv/bin/python benchmarks/bench_long.py                       # 1e5, 1e6, 4e6 + CSV
    .venv/bin/python benchmarks/bench_long.py --sizes 100000 --no-csv

Each `fusionlog run` is a child process under `nice -n 5` (the machine is shared) timed by
`/usr/bin/time -f "%e %M %U %S"`: wall time, peak RSS (max resident set size of the command)
and CPU time (user + system: what the load of a shared machine moves less).
The sizes of its four outputs are read afterwards. The FilterPy loop is the centralised KF
(one filter, three sensors stacked: predict, update) over the sensors file's readings, read in
blocks of time; it is timed on the first `--filterpy-instants` instants (default 10^5) and
extrapolated per instant to the longer logs (it is linear in the instants; the table says
which figures are extrapolated). The ratio of peak memory between 4*10^6 and 10^6 instants
says whether memory is flat. `uptime` is printed before and after: the load of the shared
machine moves the times, not the memory.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "pipeline" / "ajgl2009.toml"
OUTPUTS = ("sensors.mcap", "estimates.mcap", "evaluation.rrd", "summary.json")


def _uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def _fusionlog_run(args: list[str], out: Path) -> dict:
    """`fusionlog run ARGS --out-dir OUT --force` as a niced child: seconds, peak RSS (bytes),
    the stage seconds it prints and its outputs' sizes."""
    exe = Path(sys.executable).with_name("fusionlog")
    cmd = ["nice", "-n", "5", "/usr/bin/time", "-f", "%e %M %U %S", str(exe), "run", *args]
    cmd += ["--out-dir", str(out), "--force"]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)}: exit {res.returncode}\n{res.stderr}")
    wall, kb, user, system = res.stderr.strip().splitlines()[-1].split()
    stages = res.stdout.strip().splitlines()[-1].split(" -> ")[0]
    sizes = {name: (out / name).stat().st_size for name in OUTPUTS}
    return {
        "seconds": float(wall),
        "cpu_seconds": float(user) + float(system),  # what a shared machine's load moves less
        "peak_rss": int(kb) * 1024,
        "stages": stages,
        "sizes": sizes,
    }


def filterpy_per_instant(sensors: Path, instants: int) -> float:
    """Seconds per instant of FilterPy's `KalmanFilter` stepping through the first `instants`
    instants of the sensors file (the paper's model: F, Q of eq. 42, H the three sensors)."""
    from filterpy.kalman import KalmanFilter

    from fusionlog.io.mcap import McapFile
    from fusionlog.scenario import load_scenario as load

    sc = load(PAPER)
    s = sc.system
    kf = KalmanFilter(dim_x=s.n, dim_z=s.m)
    kf.F, kf.Q, kf.H, kf.R = s.F, s.GQG, s.linear_measurement(), s.R
    kf.x, kf.P = s.prior.mean.copy(), s.prior.cov.copy()
    mf = McapFile(sensors)
    topics = [f"/sensors/{x.name}" for x in s.sensors]
    done, seconds = 0, 0.0
    for k0, k1, data in mf.iter_time_blocks(topics, 1 << 16):
        z = np.concatenate([data[t][0] for t in topics], axis=-1)[: instants - k0]
        t0 = time.perf_counter()
        for k in range(len(z)):
            if k0 + k:
                kf.predict()
            kf.update(z[k])
        seconds += time.perf_counter() - t0
        done = k0 + len(z)
        if done >= instants or k1 >= instants:
            break
    return seconds / done


def write_csv_replay(folder: Path, rows: int, irregular: bool = False) -> Path:
    """A recorded log of `rows` instants at 200 Hz (time in ns; two position sensors a, b and
    the truth p, v) and its replay file: the paper's seven architectures on a constant-velocity
    model with a prior, truth at every instant (NIS, exact values, metrics). `irregular`: each
    interval 5 ms +- 40 %, each sensor's reading missing (an empty cell) at 5 % of the
    instants, and a partial truth (the position p alone)."""
    rng = np.random.default_rng(34)
    t = np.arange(rows, dtype=np.int64) * 5_000_000
    if irregular:
        t = np.cumsum(np.round(5_000_000 * (1 + 0.4 * rng.uniform(-1, 1, rows)))).astype(np.int64)
    v = 0.01 * np.cumsum(rng.normal(size=rows))
    p = 1.0 + np.cumsum(v) * 0.005
    cols = [t, p + rng.normal(size=rows), p + rng.normal(size=rows), p, v]
    if irregular:
        for c in cols[1:3]:
            c[rng.random(rows) < 0.05] = np.nan
    with open(folder / "log.csv", "w") as f:
        f.write("time,a,b,p,v\n")
        for i in range(0, rows, 100_000):
            block = [c[i : i + 100_000] for c in cols]
            f.write(
                "\n".join(
                    f"{a},{b:.6f},{c:.6f},{d:.9f},{e:.9f}"
                    for a, b, c, d, e in zip(*block, strict=True)
                )
                + "\n"
            )
    replay = folder / "replay.toml"
    sensors = "".join(
        f'[[sensors]]\nname = "{x}"\nsource = "log.csv"\nvalues = ["{x}"]\ntime_unit = "ns"\n'
        "H = [[1.0, 0.0]]\nR = 1.0\n"
        for x in "ab"
    )
    truth = '"p"' if irregular else '"p", "v"'
    replay.write_text(
        '[scenario]\nname = "long_csv"\nstate_names = ["p", "v"]\n'
        '[model]\nkind = "constant-velocity"\nn0 = 0.5\n'
        "[prior]\nmean = [1.0, 0.0]\ncov = [[1.0, 0.0], [0.0, 1.0]]\n" + sensors
        + f'[truth]\nsource = "log.csv"\nvalues = [{truth}]\nstates = [{truth}]\n'
        'time_unit = "ns"\nmatch = "exact"\n'
        '[estimate]\narchitectures = ["CKF", "HKF", "MSC-GMF", "MSC", "SKF", "CI", "FBS"]\n'
    )  # fmt: skip
    return replay


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="*", default=[100_000, 1_000_000, 4_000_000])
    ap.add_argument("--filterpy-instants", type=int, default=100_000)
    ap.add_argument("--csv-rows", type=int, default=1_000_000)
    ap.add_argument("--no-csv", action="store_true")
    ap.add_argument(
        "--irregular-csv",
        action="store_true",
        help="also the irregular CSV replay (missing readings, partial truth)",
    )
    ap.add_argument("--dir", type=Path, default=None, help="where the outputs go (default tmp)")
    ap.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = ap.parse_args()
    base = args.dir or Path(tempfile.mkdtemp(prefix="fusionlog-bench-long-"))
    print(f"load before: {_uptime()}", flush=True)
    results: dict = {"runs": {}}
    per_instant, measured_on = None, 0
    for N in args.sizes:
        out = base / f"paper-{N}"
        r = _fusionlog_run([str(PAPER), "--runs", "1", "--steps", str(N - 1)], out)
        r["load"] = _uptime().split("load average:")[-1].strip()  # at its end
        if per_instant is None:
            per_instant = filterpy_per_instant(out / "sensors.mcap", min(N, args.filterpy_instants))
            measured_on = min(N, args.filterpy_instants)
        r["filterpy_seconds"] = per_instant * N
        r["filterpy_extrapolated"] = N > measured_on
        results["runs"][N] = r
        for name in OUTPUTS[:2]:
            (out / name).unlink()  # 4e6 instants: 1.3 GB of MCAP (the recording is kept)
        print(N, json.dumps(r), flush=True)
    results["filterpy_per_instant"] = per_instant
    results["filterpy_measured_on"] = measured_on
    if not args.no_csv:
        folder = base / "csv"
        folder.mkdir(parents=True, exist_ok=True)
        replay = write_csv_replay(folder, args.csv_rows)
        results["csv"] = _fusionlog_run([str(replay)], folder / "out")
        print("csv", json.dumps(results["csv"]), flush=True)
    if args.irregular_csv:
        folder = base / "csv-irregular"
        folder.mkdir(parents=True, exist_ok=True)
        replay = write_csv_replay(folder, args.csv_rows, irregular=True)
        results["csv_irregular"] = _fusionlog_run([str(replay)], folder / "out")
        print("csv_irregular", json.dumps(results["csv_irregular"]), flush=True)
    runs = results["runs"]
    if 1_000_000 in runs and 4_000_000 in runs:
        results["peak_ratio_4e6_1e6"] = runs[4_000_000]["peak_rss"] / runs[1_000_000]["peak_rss"]
    results["load_after"] = _uptime()
    print(f"load after: {results['load_after']}")
    _table(results)
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))


def _table(results: dict) -> None:
    mb = 1e6
    print("\n| instants | wall time | CPU time | peak RSS | evaluation.rrd | estimates.mcap"
          " | sensors.mcap | FilterPy KF loop (CKF only) |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|")
    for N, r in results["runs"].items():
        s = r["sizes"]
        fp = f"{r['filterpy_seconds']:.1f} s" + (
            " (extrapolated)" if r["filterpy_extrapolated"] else ""
        )
        print(f"| {N:,} | {r['seconds']:.1f} s | {r['cpu_seconds']:.1f} s | "
              f"{r['peak_rss'] / 2**30:.2f} GiB | "
              f"{s['evaluation.rrd'] / mb:.0f} MB | {s['estimates.mcap'] / mb:.0f} MB | "
              f"{s['sensors.mcap'] / mb:.0f} MB | {fp} |")  # fmt: skip
    for key, name in (("csv", "CSV replay"), ("csv_irregular", "irregular CSV replay")):
        if key not in results:
            continue
        r, s = results[key], results[key]["sizes"]
        print(f"| {name} | {r['seconds']:.1f} s | {r['cpu_seconds']:.1f} s | "
              f"{r['peak_rss'] / 2**30:.2f} GiB | "
              f"{s['evaluation.rrd'] / mb:.0f} MB | {s['estimates.mcap'] / mb:.0f} MB | "
              f"{s['sensors.mcap'] / mb:.0f} MB | |")  # fmt: skip
    if "peak_ratio_4e6_1e6" in results:
        print(f"\npeak RSS 4e6 / 1e6: {results['peak_ratio_4e6_1e6']:.3f}")


if __name__ == "__main__":
    main()
