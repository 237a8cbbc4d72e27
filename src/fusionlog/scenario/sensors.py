"""The ``[[sensors]]`` tables of a scenario: each sensor kind's TOML syntax, by ``kind``.

A kind's model lives in `fusionlog.core.models` (registered there by its ``kind`` name); its
syntax here says which keys its table takes, how they become the model (validated, one-line
errors with the key path), and how the model is written back (`system_to_dict`, MCAP
metadata). Adding a sensor kind is its model, its `SensorSyntax` in `SENSOR_SYNTAX`, nothing
else: the architectures ask the model (`core.models.base`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from fusionlog.core.models import SENSOR_KINDS, LinearSensor, SensorModel

from . import toml
from .model_section import TIMING_KEYS, sensor_timing
from .nonlinear_syntax import polar_dict, polar_sensor
from .toml import Ctx

__all__ = [
    "SENSOR_SYNTAX",
    "SensorSyntax",
    "sensor_from_table",
    "sensor_matrices",
    "sensor_to_dict",
]

#: The kind of a table without ``kind``.
DEFAULT_KIND = "linear"


@dataclass(frozen=True)
class SensorSyntax:
    """A sensor kind's table: `keys` required besides ``name`` (and the optional timing keys and
    ``kind``), `optional` ones, `parse` (ctx, table, key path, name, n, state names) -> the
    model (its timing left at the default: `sensor_from_table` sets it), and `to_dict` the
    model -> the table's keys besides name, kind and timing."""

    keys: tuple[str, ...]
    optional: tuple[str, ...]
    parse: Callable[[Ctx, dict[str, Any], str, str, int, tuple[str, ...]], SensorModel]
    to_dict: Callable[[SensorModel], dict[str, Any]]


def sensor_matrices(
    ctx: Ctx, t: dict[str, Any], where: str, n: int
) -> tuple[np.ndarray, np.ndarray | None]:
    """A sensor table's H (m x n; a flat list for one row) and R (m x m, a scalar for one
    row; None when the table has no R)."""
    H = toml.matrix(ctx, t["H"], f"{where}.H", scalar=n == 1, row=True)
    if H.shape[1] != n:
        raise ctx.err(f"{where}.H", f"shape {toml.shape(H)}, expected {H.shape[0]}x{n} (m x n)")
    m = H.shape[0]
    if "R" not in t:
        return toml.readonly(H), None
    R = toml.matrix(ctx, t["R"], f"{where}.R", scalar=m == 1)
    if R.shape != (m, m):
        raise ctx.err(
            f"{where}.R",
            f"shape {toml.shape(R)}, expected {m}x{m} (H has {m} row{'s' * (m > 1)})",
        )
    return toml.readonly(H), toml.covariance_checks(ctx, R, f"{where}.R", strict=True)


def _linear(
    ctx: Ctx, t: dict[str, Any], where: str, name: str, n: int, states: tuple[str, ...]
) -> SensorModel:
    H, R = sensor_matrices(ctx, t, where, n)
    return LinearSensor(name, H, R)


def _linear_dict(s: SensorModel) -> dict[str, Any]:
    assert isinstance(s, LinearSensor)
    return {"H": toml.tolist(s.H), "R": toml.tolist(s.R)}


#: kind -> its syntax; every kind here has a model in `core.models.SENSOR_KINDS`.
SENSOR_SYNTAX: dict[str, SensorSyntax] = {
    "linear": SensorSyntax(("H", "R"), (), _linear, _linear_dict),
    **{
        kind: SensorSyntax(("position", "R"), ("position_states",), polar_sensor, polar_dict)
        for kind in ("range-bearing", "range", "bearing")
    },
}


def allowed_keys() -> tuple[str, ...]:
    """Every key a sensor table of some kind may hold (``name`` first, ``kind`` last)."""
    keys = [k for s in SENSOR_SYNTAX.values() for k in (*s.keys, *s.optional)]
    return ("name", *dict.fromkeys(keys), *TIMING_KEYS, "kind")


def sensor_from_table(
    ctx: Ctx,
    t: dict[str, Any],
    where: str,
    name: str,
    n: int,
    states: tuple[str, ...],
    dt: float,
) -> SensorModel:
    """The sensor model of a ``[[sensors]]`` table (its keys checked against its kind; the
    timing keys, common to every kind, read here against the scenario's dt)."""
    kind = t.get("kind", DEFAULT_KIND)
    if kind not in SENSOR_SYNTAX or kind not in SENSOR_KINDS:
        known = ", ".join(k for k in SENSOR_SYNTAX if k in SENSOR_KINDS)
        raise ctx.err(f"{where}.kind", f"unknown sensor kind {kind!r} (known: {known})")
    syn = SENSOR_SYNTAX[kind]
    allowed = ("name", *syn.keys, *syn.optional, *TIMING_KEYS, "kind")
    toml.check_keys(ctx, t, where, allowed, required=("name", *syn.keys))
    model = syn.parse(ctx, t, where, name, n, states)
    return dataclasses.replace(model, timing=sensor_timing(ctx, t, where, dt))


def sensor_to_dict(s: SensorModel) -> dict[str, Any]:
    """A sensor model as its table's keys (name, kind unless linear, its own keys)."""
    d: dict[str, Any] = {"name": s.name}
    if s.kind != DEFAULT_KIND:
        d["kind"] = s.kind
    return d | SENSOR_SYNTAX[s.kind].to_dict(s)
