"""The reference switch: ``FUSIONLOG_REFERENCE_PATHS=1`` in the environment sends every kept
fast path to its plain reference path (benchmarks/README.md "Fast paths" lists each, the
workload it serves and what it gains there): one run estimated without plans
(`architectures.replay`), the exact analysis of one recorded log without plans
(`exact_replay`, through `routes.exact_route`), the regex and column-wise decoding of canonical
protobuf messages (`io.mcap.wire`, `io.mcap.columns`). The answers agree to rounding (`make
test` runs the goldens and the exactness tests once more with the switch on), so the switch is
how a suspected fast path is told from the reference.

It imports nothing: the MCAP reader and the estimation driver both ask it.
"""

from __future__ import annotations

import os

__all__ = ["REFERENCE_PATHS_ENV", "reference_paths"]

#: The environment variable that forces the plain reference paths ("1"; unset or "0": not).
REFERENCE_PATHS_ENV = "FUSIONLOG_REFERENCE_PATHS"


def reference_paths() -> bool:
    """Whether the plain reference paths are forced (read at each decision, so a test or a
    process can set it at any time)."""
    return os.environ.get(REFERENCE_PATHS_ENV, "") not in ("", "0")
