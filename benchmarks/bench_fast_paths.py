"""Every fast path against the plain reference path it stands in for, on the workload it serves
(benchmarks/README.md "Fast paths"): a fast path is kept only where it is at least 1.5x faster.

    .venv/bin/python benchmarks/bench_fast_paths.py              # 7 repeats of each
    .venv/bin/python benchmarks/bench_fast_paths.py --repeats 3 --long-steps 20000

The plain paths are what ``FUSIONLOG_REFERENCE_PATHS=1`` forces (`fusionlog.core.reference`);
each figure is the median wall time of `--repeats` calls in this process, after one untimed
call, with the switch off (fast) and on (plain) in turn, and the two answers compared ("agree":
the largest difference relative to the largest entry):

1. one run estimated without plans (`core.architectures.replay`): `estimate_block` of
   replay_robot's imported log (one run, 2,292 instants, its seven architectures), a fresh
   plan cache each call (what `fusionlog estimate` of a recorded log does);
2. the exact analysis of one recorded log without plans (`core.exact_replay`): the expected
   values of those architectures on that log, the truth the filters' model (what `fusionlog
   evaluate` of a recorded log does), against the plans' analysis (`core.exact.analyse`);
3. canonical protobuf messages decoded by a regex and column-wise (`io.mcap.wire`,
   `io.mcap.columns`): reading every sensor topic of a long one-run log (`fusionlog simulate
   --runs 1 --steps N` of the paper's example: a message per topic and instant), against
   decoding field by field.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SWITCH = "FUSIONLOG_REFERENCE_PATHS"


def timed(fn: Callable[[], Any], repeats: int, plain: bool) -> tuple[float, Any]:
    """Median wall seconds of `repeats` calls after one untimed call, the switch set by
    `plain`; and the last answer."""
    os.environ[SWITCH] = "1" if plain else "0"
    try:
        out = fn()
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            out = fn()
            times.append(time.perf_counter() - t0)
    finally:
        os.environ.pop(SWITCH, None)
    return statistics.median(times), out


def cli(*args: str | Path) -> None:
    from click.testing import CliRunner

    from fusionlog.cli import main

    res = CliRunner().invoke(main, [str(a) for a in args])
    if res.exit_code != 0:
        raise SystemExit(f"fusionlog {' '.join(map(str, args))}: {res.output}")


def replay_log(tmp: Path):
    """replay_robot imported: (sensors file, the filter model on its instants, z, archs)."""
    from fusionlog.io.mcap import McapFile
    from fusionlog.stages.common import scenario_from_file
    from fusionlog.stages.noise import with_message_covariances

    path = tmp / "replay.mcap"
    cli("import", ROOT / "pipeline" / "replay_robot.toml", "-o", path)
    mf = McapFile(path)
    sc = scenario_from_file(mf)
    system = with_message_covariances(sc.system.on_times(mf.times()), mf)
    topics = [f"/sensors/{s.name}" for s in system.sensors]
    z = np.concatenate([mf.read_all([t])[t] for t in topics], axis=-1)
    return path, system, z, list(sc.architectures)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--long-steps", type=int, default=100_000, help="instants of the long log")
    ap.add_argument("--json", type=Path, default=None, help="save the rows")
    ap.add_argument("--cases", default="1,2,3", help="which fast paths (numbers, comma-separated)")
    args = ap.parse_args(argv)

    from fusionlog.core.routes import shared_expected
    from fusionlog.driver import PlanCache, estimate_block
    from fusionlog.io.mcap import McapFile

    rows = []
    with tempfile.TemporaryDirectory(prefix="fusionlog-fast-paths-") as tmp:
        path, system, z, archs = replay_log(Path(tmp))  # (small: made for every case)
        K = z.shape[1] - 1

        def estimate() -> dict[str, np.ndarray]:
            cache = PlanCache(system, K, one_run=True)
            block = estimate_block(system, archs, z, cache=cache)
            return {a: e.mean for a, e in block.estimates.items()}

        present = ~np.isnan(z[0])

        def exact() -> dict[str, np.ndarray]:
            # the evaluator's plan cache: plans built only where the plans' analysis runs
            cache = PlanCache(system, K)
            route = "plans" if os.environ.get(SWITCH) == "1" else "one-log"
            of = shared_expected(
                route, system, system, archs, present, K, "trace", lambda a: cache.plan(a, present)
            )
            return {a: of(a).mse for a in archs}

        long_log = Path(tmp) / "long.mcap"
        cli("simulate", ROOT / "pipeline" / "ajgl2009.toml", "-o", long_log, "--runs", "1",
            "--steps", str(args.long_steps))  # fmt: skip

        def read() -> dict[str, np.ndarray]:
            mf = McapFile(long_log)
            topics = sorted(t for t in mf.topics if t.startswith("/sensors/"))
            return mf.read_all(topics)

        cases = [
            ("one run without plans (core/architectures/replay.py)",
             f"estimate_block, replay_robot: 1 run, {K + 1} instants, {len(archs)} architectures",
             estimate),
            ("exact analysis of one log without plans (core/exact_replay.py)",
             f"expected values, replay_robot: 1 run, {K + 1} instants, {len(archs)} architectures",
             exact),
            ("regex / column-wise decoding (io/mcap/wire.py, columns.py)",
             f"read every sensor topic of simulate --runs 1 --steps {args.long_steps}",
             read),
        ]  # fmt: skip
        print(f"{'fast path':<66} {'plain s':>9} {'fast s':>9} {'ratio':>7}  agree", flush=True)
        chosen = [cases[int(i) - 1] for i in args.cases.split(",")]
        for name, workload, fn in chosen:
            plain, a = timed(fn, args.repeats, plain=True)
            fast, b = timed(fn, args.repeats, plain=False)
            # the largest difference relative to the largest entry, per array
            agree = max(
                float(np.nanmax(np.abs(a[k] - b[k])) / np.nanmax(np.abs(a[k])))
                if np.size(a[k])
                else 0.0
                for k in a
            )
            ratio = plain / fast
            rows.append(
                {"fast_path": name, "workload": workload, "plain_s": plain, "fast_s": fast,
                 "ratio": ratio, "max_rel_diff": agree}
            )  # fmt: skip
            print(f"{name:<66} {plain:9.4f} {fast:9.4f} {ratio:6.2f}x  {agree:.1e}", flush=True)
            print(f"    workload: {workload}")
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
