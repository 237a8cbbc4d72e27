"""Architecture names used on the CLI, in MCAP topics and in summaries (DESIGN.md contract).

The names are those of the architecture registry (`core.architectures.registry`): one list,
so that a name parses exactly when there is a builder for it.
"""

from __future__ import annotations

from .architectures.registry import STATE_ARCHITECTURES, parse_arch

#: The five architectures of the paper's Table I, in its column order.
PAPER_ARCHITECTURES: tuple[str, ...] = ("CKF", "HKF", "MSC-GMF", "MSC", "SKF")

__all__ = ["PAPER_ARCHITECTURES", "STATE_ARCHITECTURES", "parse_arch"]
