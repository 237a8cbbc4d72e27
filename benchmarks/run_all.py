"""Run every benchmark in one process tree and print their tables: the estimation core
(`bench_core.py`) and then the whole pipeline (`bench_pipeline.py`), which also lists the core's
figures against the issue-6 targets.

    .venv/bin/python benchmarks/run_all.py            # full sizes (about 2.5 minutes on 2 cores)
    .venv/bin/python benchmarks/run_all.py --quick    # small sizes, about a minute
    .venv/bin/python benchmarks/run_all.py --json bench.json   # also save every figure

--quick keeps the core benchmark at M = 10^4 (the size its target is stated for) with fewer
repeats, and runs the pipeline at 10^4 / 10^5 runs and a K = 2000 long log.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small sizes (about a minute)")
    ap.add_argument("--json", type=Path, default=None, metavar="PATH", help="save every figure")
    ap.add_argument("--tmp-dir", type=Path, default=None, help="where outputs are written")
    args = ap.parse_args(argv)

    py = sys.executable
    with tempfile.TemporaryDirectory(prefix="fusionlog-run-all-") as tmp:
        core_json = Path(tmp) / "core.json"
        pipe_json = Path(tmp) / "pipeline.json"
        core = [py, str(HERE / "bench_core.py"), "--json", str(core_json)]
        if args.quick:
            core += ["--repeats", "3", "--filterpy-runs", "100"]
        pipe = [py, str(HERE / "bench_pipeline.py"), "--core-json", str(core_json)]
        if args.json is not None:
            pipe += ["--json", str(pipe_json)]
        if args.quick:
            pipe.append("--quick")
        if args.tmp_dir is not None:
            pipe += ["--tmp-dir", str(args.tmp_dir)]

        print("#" * 100)
        print("# bench_core.py: the estimation core against FilterPy and simdkalman, in memory")
        print("#" * 100, flush=True)
        rc = subprocess.call(core)
        if rc != 0:
            print(f"bench_core.py failed with status {rc}", file=sys.stderr)
            return rc
        print()
        print("#" * 100)
        print("# bench_pipeline.py: whole `fusionlog run` processes, files and all")
        print("#" * 100, flush=True)
        rc = subprocess.call(pipe)
        if rc != 0:
            print(f"bench_pipeline.py failed with status {rc}", file=sys.stderr)
            return rc
        if args.json is not None:
            out = {
                "core": json.loads(core_json.read_text()),
                "pipeline": json.loads(pipe_json.read_text()),
            }
            out["pipeline"].pop("core", None)  # the same figures as "core"
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(out, indent=2) + "\n")
            print(f"all figures saved to {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
