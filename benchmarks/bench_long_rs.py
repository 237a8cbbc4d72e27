"""A long one-run log whose sensor carries its R per message (issue 34, rsgrow): `estimate` and
`evaluate` of 10^5 and 10^6 instants, each timed by `/usr/bin/time`.

    .venv/bin/python benchmarks/bench_long_rs.py --sizes 100000 1000000

The log: the paper's scenario (pipeline/ajgl2009.toml, three position sensors, the seven
architectures) simulated as one run (`fusionlog simulate --runs 1 --steps N`), then written again
with sensor s1's readings drawn with a variance r_k = exp(U(-1, 1)) of its own at every instant,
carried in each message's `covariance` field (DESIGN.md "MCAP files"), as an imported recording
whose messages carry their covariance does. The filters and the exact analysis then take the
stacked R of eq. (31) per instant (`System.Rs`): no steady plans, the plan-free path in blocks
of time. Each command is a child process under `nice -n 5`, timed by
`/usr/bin/time -f "%e s %U u %M KB"` (wall, user CPU, peak RSS).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "pipeline" / "ajgl2009.toml"
TOPICS = ["/truth", "/sensors/s1", "/sensors/s2", "/sensors/s3"]


def with_message_r(src: Path, out: Path, seed: int = 34, block: int = 1 << 16) -> None:
    """`src` (a one-run simulation of the paper's scenario) written to `out` with sensor s1's
    readings redrawn with a variance of their own per message, carried in its covariance."""
    from fusionlog.io.mcap import LAYOUT_META, VALUES, McapFile, McapWriter
    from fusionlog.io.mcap.run_steps import RunColumn

    mf = McapFile(src)
    times, rng = mf.times(), np.random.default_rng(seed)
    with open(out, "wb") as f, McapWriter(f) as w:
        for name, meta in mf.metadata.items():
            if name != LAYOUT_META:
                w.add_metadata(name, meta)
        for k0, k1, data in mf.iter_time_blocks(TOPICS, block):
            x = data["/truth"][0]
            r = np.exp(rng.uniform(-1.0, 1.0, k1 - k0))
            z1 = x[:, :1] + np.sqrt(r)[:, None] * rng.standard_normal((k1 - k0, 1))
            cols = [
                RunColumn("/truth", VALUES, x),
                RunColumn("/sensors/s1", VALUES, z1, r[:, None, None]),
                RunColumn("/sensors/s2", VALUES, data["/sensors/s2"][0]),
                RunColumn("/sensors/s3", VALUES, data["/sensors/s3"][0]),
            ]
            w.write_run_steps(k0, times[k0:k1], cols)


def _timed(args: list[str]) -> str:
    cmd = ["nice", "-n", "5", "/usr/bin/time", "-f", "%e s %U u %M KB", *args]
    got = subprocess.run(cmd, capture_output=True, text=True)
    if got.returncode:
        sys.exit(f"{' '.join(args)}: exit {got.returncode}\n{got.stderr}")
    return got.stderr.strip().splitlines()[-1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="*", default=[100_000, 1_000_000])
    ap.add_argument("--logs", type=Path, help="keep the sensors files here (made once)")
    args = ap.parse_args()
    exe = str(Path(sys.executable).parent / "fusionlog")
    with tempfile.TemporaryDirectory(prefix="bench-long-rs-") as tmp:
        for n in args.sizes:
            d, logs = Path(tmp), args.logs or Path(tmp)
            log = logs / f"sensors_{n}.mcap"
            if not log.exists():
                sim = d / "sim.mcap"
                subprocess.run(
                    [exe, "simulate", str(PAPER), "-o", str(sim), "--runs", "1",
                     "--steps", str(n - 1), "--force"],
                    check=True, capture_output=True,
                )  # fmt: skip
                with_message_r(sim, log)
            est, ev = d / "estimates.mcap", d / "evaluation.rrd"
            t_est = _timed([exe, "estimate", str(log), "-o", str(est), "--force"])
            t_ev = _timed([exe, "evaluate", str(log), str(est), "-o", str(ev), "--force"])
            print(f"{n} instants: estimate {t_est}; evaluate {t_ev}", flush=True)


if __name__ == "__main__":
    main()
