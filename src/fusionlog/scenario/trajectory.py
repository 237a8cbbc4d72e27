"""The trajectory metrics' keys of ``[evaluate]`` (DESIGN.md "Trajectory metrics") and ``--align``.

::

    [evaluate]
    position_states = ["x", "y"]   # default: the states named x, y, z that exist (with truth)
    align = "rigid"                # "none" (default) | "origin" | "rigid" | "similarity"
    align_first = 100              # only the first N matched instants fit the alignment
    rpe_delta = 1                  # default 1
    rpe_unit = "frames"            # "frames" (default) | "m" | "s"

The result is a `core.trajectory.TrajectorySettings` (None: no position states, no metrics).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

from fusionlog.core.trajectory import ALIGNMENTS, MIN_FIT, RPE_UNITS, TrajectorySettings
from fusionlog.errors import ValidationError

from . import toml
from .toml import Ctx

__all__ = ["KEYS", "trajectory_section", "with_align"]

#: The keys of [evaluate] read here.
KEYS = ("position_states", "align", "align_first", "rpe_delta", "rpe_unit")
#: The default position states, in this order, where they exist.
DEFAULT_POSITIONS = ("x", "y", "z")


def trajectory_section(
    ctx: Ctx,
    doc: dict[str, Any],
    state_names: Sequence[str],
    truthed: Sequence[str] | None = None,
) -> TrajectorySettings | None:
    """The settings of ``[evaluate]``; `truthed`: the states a replay's truth gives (None: all).
    A position state named explicitly must have truth; the default keeps those that do."""
    ev = doc.get("evaluate")
    ev = ev if isinstance(ev, dict) else {}  # the section's type is checked by its parser
    names = list(state_names)
    where = "evaluate.position_states"
    if "position_states" in ev:
        v = ev["position_states"]
        positions = toml.names_list(ctx, v, where) if v != [] else ()
        if len(positions) > 3:
            raise ctx.err(where, f"{len(positions)} states: at most 3 (x, y, z of a position)")
        for i, s in enumerate(positions):
            if s not in names:
                raise ctx.err(f"{where}[{i}]", toml.unknown_msg("state", s, names))
            if truthed is not None and s not in truthed:
                raise ctx.err(f"{where}[{i}]", f"state {s!r} has no truth (truth.states)")
    else:
        have = names if truthed is None else [s for s in names if s in truthed]
        positions = tuple(s for s in DEFAULT_POSITIONS if s in have)
    mode = toml.string(ctx, ev.get("align", "none"), "evaluate.align")
    if mode not in ALIGNMENTS:
        raise ctx.err("evaluate.align", toml.unknown_msg("alignment", mode, ALIGNMENTS))
    first = None
    if "align_first" in ev:
        first = toml.integer(ctx, ev["align_first"], "evaluate.align_first", minimum=1)
        if mode in ("rigid", "similarity") and first < MIN_FIT:
            raise ctx.err(
                "evaluate.align_first",
                f"{first} instant(s) to fit a {mode} alignment, at least {MIN_FIT} needed",
            )
    unit = toml.string(ctx, ev.get("rpe_unit", "frames"), "evaluate.rpe_unit")
    if unit not in RPE_UNITS:
        raise ctx.err("evaluate.rpe_unit", toml.unknown_msg("unit", unit, RPE_UNITS))
    delta: float = 1
    if "rpe_delta" in ev:
        if unit == "frames":
            delta = toml.integer(ctx, ev["rpe_delta"], "evaluate.rpe_delta", minimum=1)
        else:
            delta = toml.number(ctx, ev["rpe_delta"], "evaluate.rpe_delta")
            if not delta > 0:
                raise ctx.err("evaluate.rpe_delta", f"must be > 0, got {toml.fmt(delta)}")
    if not positions:
        explicit = [k for k in KEYS[1:] if k in ev]
        if explicit and not (explicit == ["align"] and mode == "none"):
            raise ctx.err(
                f"evaluate.{explicit[0]}",
                "no position states (name them in evaluate.position_states; the default is the "
                "states x, y, z that exist)",
            )
        return None
    return TrajectorySettings(tuple(names.index(s) for s in positions), mode, first, delta, unit)


def with_align(scenario: Any, mode: str | None) -> Any:
    """The scenario with ``--align`` (None: as its ``[evaluate] align``)."""
    if mode is None or getattr(scenario, "kind", "state") != "state":
        return scenario
    where = scenario.path or scenario.name
    if mode not in ALIGNMENTS:
        raise ValidationError(f"--align: {toml.unknown_msg('alignment', mode, ALIGNMENTS)}")
    settings = scenario.trajectory
    if settings is None:
        if mode == "none":
            return scenario
        raise ValidationError(
            f"{where}: --align {mode}: no position states (name them in [evaluate] "
            "position_states; the default is the states x, y, z that exist)"
        )
    if settings.align_first is not None and mode in ("rigid", "similarity"):
        if settings.align_first < MIN_FIT:
            raise ValidationError(
                f"{where}: --align {mode}: evaluate.align_first = {settings.align_first}, at "
                f"least {MIN_FIT} instants are needed to fit it"
            )
    return dataclasses.replace(scenario, trajectory=dataclasses.replace(settings, align=mode))
