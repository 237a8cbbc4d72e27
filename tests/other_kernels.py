"""Run the numerical test modules again under other OpenBLAS kernels (`make test` does).

OpenBLAS picks its kernels by CPU, and they sum in different orders; a tolerance tuned to one
machine's order passes there and fails on the next. Forcing the generic (Prescott) kernels and,
where this CPU can run them, the Haswell (AVX2) and SkylakeX (AVX-512) ones makes such a
tolerance fail here first. A kernel set the CPU cannot execute is skipped (forcing it would
crash with an illegal instruction), and so is everything on a CPU that is not x86-64; so are
the tests marked `memory` (`DESELECT`).

    python tests/other_kernels.py tests/test_exact.py ...   # pytest arguments
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from pathlib import Path

#: OPENBLAS_CORETYPE -> the CPU flags its kernels need.
KERNELS = {"Prescott": set(), "Haswell": {"avx2", "fma"}, "SkylakeX": {"avx512f", "avx512bw"}}

#: What a kernel cannot change is not rerun: the tests marked `memory` check only tracemalloc
#: peaks (whole runs at two lengths, among the long-log modules' slowest tests), and a kernel's
#: order of sums allocates the same.
DESELECT = ["-m", "not memory"]


def cpu_flags() -> set[str]:
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return set()
    for line in text.splitlines():
        if line.startswith("flags"):
            return set(line.split(":", 1)[1].split())
    return set()


def main(args: list[str]) -> int:
    if platform.machine().lower() not in ("x86_64", "amd64"):
        print("other_kernels: not an x86-64 CPU, nothing to do")
        return 0
    flags = cpu_flags()
    worst = 0
    for name, need in KERNELS.items():
        if not need <= flags:
            print(
                f"other_kernels: skipping {name} (this CPU lacks {' '.join(sorted(need - flags))})"
            )
            continue
        print(f"other_kernels: OPENBLAS_CORETYPE={name}", flush=True)
        env = {**os.environ, "OPENBLAS_CORETYPE": name}
        cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *DESELECT, *args]
        worst = max(worst, subprocess.run(cmd, env=env).returncode)
    return worst


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
