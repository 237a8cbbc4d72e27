"""The grid of a parameter sweep: ``--vary KEY=VALUES`` options, their product, and each grid
point as a validated scenario.

``KEY`` is a dotted path into the scenario's TOML document: tables by key (``scenario.dt``,
``model.n0``), arrays of tables by index or by the ``name`` of an element (``sensors.s1.R``,
``sensors.0.R``, ``correlations.0.cov``), arrays of values by index (``sensors.s1.R.0.0``,
one entry of a matrix). The loader's own spelling of a path (``sensors[1].R``) is accepted too.
The last key may be absent from its table (``sensors.s1.dropout`` in a file without dropouts),
and so may a whole table (``evaluate.confidence``); everything else must exist.

``VALUES`` is a comma list of TOML values (``0.5,1,2``; ``[[1.0, 0.0], [0.0, 2.0]]`` for a
matrix; a bare word is a string) or a range ``start:stop:num`` (``num`` values from start to
stop, both included) with an optional ``:log`` (log-spaced, start and stop > 0).

A grid point is applied by editing a copy of the parsed document and validating it through the
normal scenario loader (:func:`fusionlog.scenario.scenario_from_doc`): one validation path, and
a bad point is the loader's one-line error with the point named in place of the file.

Each point's Monte Carlo runs come from a seed of its own, :func:`point_seed` of the scenario's
seed and the point's index, so a point's runs are those of ``fusionlog run`` with that seed.
"""

from __future__ import annotations

import copy
import itertools
import math
import re
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fusionlog.errors import FusionlogError
from fusionlog.scenario import Scenario, scenario_from_doc, scenario_with, toml

from .common import progress

__all__ = ["GridPoint", "Vary", "grid_points", "parse_vary", "point_seed"]

#: A range: start:stop:num with an optional :log (numbers, no brackets or quotes).
_RANGE = re.compile(r"^\s*([^:\[\]\"',]+):([^:\[\]\"',]+):([^:\[\]\"',]+)(?::(log|lin))?\s*$")
#: The loader's spelling of an array index, sensors[1].R, rewritten as sensors.1.R.
_INDEX = re.compile(r"\[(\d+)\]")
#: A bare word taken as a string value (model.kind=continuous).
_WORD = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]*$")
#: Grid points at most. Each point is validated here and has an exact analysis of its own
#: (about 36 ms for the paper's example with its seven architectures on one core of the 2-core
#: development machine: 10^4 points are 6 minutes before any Monte Carlo run), and every point
#: is a row group of the outputs; beyond this a typo in num (1:2:100000) is more likely than
#: intent. A finer study is several sweeps over sub-ranges.
MAX_POINTS = 10_000


@dataclass(frozen=True)
class Vary:
    """One ``--vary KEY=VALUES``: the key as written (the parquet column's name), its path
    segments, the values and how each is shown."""

    key: str
    segments: tuple[str, ...]
    values: tuple[Any, ...]
    texts: tuple[str, ...]
    log: bool = False

    @property
    def numeric(self) -> bool:
        """Every value a number (not a boolean): a column of numbers, an axis to plot on."""
        return all(toml.is_number(v) for v in self.values)


@dataclass(frozen=True)
class GridPoint:
    """One point of the grid: its index in the product, its values by key, its scenario (with
    the point's seed and the sweep's runs)."""

    index: int
    values: dict[str, Any]
    label: str  # "scenario.dt=0.5, model.n0=0.16"
    scenario: Scenario
    file_seed: int  # the seed the point's own runs derive from (the file's, or a varied one)

    @property
    def where(self) -> str:
        """The point in a message: "<file> [point <index>: <label>]"."""
        return f"{self.scenario.path} [point {self.index}: {self.label}]"


def _bad(spec: str, reason: str) -> FusionlogError:
    return FusionlogError(f"--vary {spec}: {reason}")


def _number_text(v: float | int) -> str:
    return str(v) if isinstance(v, int) else f"{v:.6g}"


def _literal(spec: str, item: str) -> tuple[Any, str]:
    """One value of a comma list: a TOML value, or a bare word as a string."""
    text = item.strip()
    if not text:
        raise _bad(spec, "an empty value in the list")
    try:
        value = tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        if not _WORD.match(text):
            raise _bad(
                spec,
                f"{text!r} is not a TOML value (a number, a quoted string, true/false, an array)",
            ) from None
        value = text
    if isinstance(value, float) and not math.isfinite(value):
        raise _bad(spec, f"{text!r} is not a finite number")
    if isinstance(value, dict):
        raise _bad(spec, f"{text!r}: a table cannot be a value; vary its keys one by one")
    return value, text


def _split_top_level(text: str) -> list[str]:
    """Split at commas outside brackets and quotes (a matrix value holds commas)."""
    items, depth, quote, start = [], 0, "", 0
    for i, c in enumerate(text):
        if quote:
            if c == quote:
                quote = ""
        elif c in "\"'":
            quote = c
        elif c == "[":
            depth += 1
        elif c == "]":
            depth -= 1
        elif c == "," and depth == 0:
            items.append(text[start:i])
            start = i + 1
    items.append(text[start:])
    return items


def _range(spec: str, m: re.Match[str]) -> tuple[list[Any], list[str], bool]:
    """Values of start:stop:num[:log]; integers when start and stop are integers and every
    value falls on one (scenario.steps=10:50:5)."""
    a_text, b_text, n_text, scale = m.groups()
    try:
        a, b = (tomllib.loads(f"v = {t.strip()}")["v"] for t in (a_text, b_text))
        n = tomllib.loads(f"v = {n_text.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        raise _bad(spec, "a range is start:stop:num[:log] with numbers") from None
    if not (toml.is_number(a) and toml.is_number(b)) or not all(map(math.isfinite, (a, b))):
        raise _bad(spec, "a range's start and stop must be finite numbers")
    if not isinstance(n, int) or isinstance(n, bool) or n < 1:
        raise _bad(spec, f"a range's num must be an integer >= 1, got {n_text.strip()}")
    if n > MAX_POINTS:
        raise _bad(spec, f"{n} values is more than {MAX_POINTS} (the bound of a grid)")
    log = scale == "log"
    if log:
        if not (a > 0 and b > 0):
            raise _bad(spec, "a log range needs start > 0 and stop > 0")
        grid = np.geomspace(a, b, n)
    else:
        grid = np.linspace(a, b, n)
    grid[0] = a  # the ends exactly as written, not as rounded by the spacing
    if n > 1:
        grid[-1] = b
    if not log and all(isinstance(v, int) for v in (a, b)) and np.all(grid == np.round(grid)):
        values: list[Any] = [int(round(v)) for v in grid]
    else:
        # 15 digits: 0.5 rather than geomspace's 0.49999999999999994, the value meant
        values = [float(f"{v:.15g}") for v in grid]
    return values, [_number_text(v) for v in values], log


def parse_vary(spec: str) -> Vary:
    """Parse one ``KEY=VALUES`` (see the module docstring); a malformed one is a one-line
    FusionlogError naming it."""
    key, eq, text = spec.partition("=")
    key = key.strip()
    if not eq or not key:
        raise _bad(spec, "expected KEY=VALUES, e.g. scenario.dt=0.5,1,2 or scenario.dt=0.1:2:20")
    segments = tuple(_INDEX.sub(r".\1", key).split("."))
    if any(not s for s in segments):
        raise _bad(spec, f"{key!r} is not a dotted key path (an empty part)")
    m = _RANGE.match(text)
    if m is not None:
        values, texts, log = _range(spec, m)
    else:
        pairs = [_literal(spec, item) for item in _split_top_level(text)]
        values, texts, log = [v for v, _ in pairs], [t for _, t in pairs], False
    for i, v in enumerate(values):
        if any(_same(v, w) for w in values[:i]):
            raise _bad(spec, f"the value {texts[i]} is listed twice")
    return Vary(key, segments, tuple(values), tuple(texts), log)


def _same(a: Any, b: Any) -> bool:
    return type(a) is type(b) and a == b


def _resolve(doc: dict[str, Any], vary: Vary) -> list[str | int]:
    """The path of `vary` in the document: each segment a table key or an array index (an
    element of an array of tables may be named by its `name`, which may hold dots). Only the
    last key (and tables leading to it) may be missing."""
    path: list[str | int] = []
    node: Any = doc
    segs = list(vary.segments)
    i = 0
    while i < len(segs):
        where = ".".join(str(p) for p in path) or "(top level)"
        if isinstance(node, dict):
            key = segs[i]
            path.append(key)
            if key in node:
                node = node[key]
            elif i + 1 < len(segs) and segs[i + 1].isdigit():
                raise _bad(vary.key, f"the file has no {'.'.join(map(str, path))} array")
            else:
                # the last key or a missing table on the way to it: the loader judges the name
                node = {}
            i += 1
        elif isinstance(node, list):
            names = [e.get("name") for e in node if isinstance(e, dict)]
            idx = _element(node, segs, i)
            if idx is None:
                have = ", ".join(str(n) for n in names if isinstance(n, str)) or "none"
                raise _bad(
                    vary.key,
                    f"{where} has no element {segs[i]!r} (an index 0..{len(node) - 1}"
                    + (f" or a name: {have})" if names else ")"),
                )
            idx, used = idx
            path.append(idx)
            node = node[idx]
            i += used
        else:
            raise _bad(vary.key, f"{where} is {toml.tname(node)}, it has no key {segs[i]!r}")
    return path


def _element(node: list[Any], segs: list[str], i: int) -> tuple[int, int] | None:
    """(index, segments used) of the element that segs[i:] starts with: an index, or the
    longest run of segments that is an element's name (names may hold dots)."""
    if segs[i].isdigit():
        k = int(segs[i])
        return (k, 1) if k < len(node) else None
    for j in range(len(segs), i, -1):
        name = ".".join(segs[i:j])
        for k, e in enumerate(node):
            if isinstance(e, dict) and e.get("name") == name:
                return k, j - i
    return None


def _assign(doc: dict[str, Any], path: list[str | int], value: Any) -> None:
    node: Any = doc
    for p in path[:-1]:
        if isinstance(node, dict) and p not in node:
            node[p] = {}
        node = node[p]
    node[path[-1]] = copy.deepcopy(value)


def point_seed(seed: int, index: int) -> int:
    """The seed of grid point `index`: drawn from SeedSequence(seed, spawn_key=(index,)), 63
    bits (a TOML integer), so that each point has its own independent runs and the same point
    of the same sweep always has the same ones."""
    state = np.random.SeedSequence(seed, spawn_key=(index,)).generate_state(1, np.uint64)[0]
    return int(state >> np.uint64(1))


def _label(varies: Sequence[Vary], combo: Sequence[int]) -> str:
    return ", ".join(f"{v.key}={v.texts[j]}" for v, j in zip(varies, combo, strict=True))


def grid_points(
    path: str | Path, varies: Sequence[Vary], *, runs: int | None = None
) -> list[GridPoint]:
    """Every point of the product of `varies` (the last key varying fastest), each validated
    through the scenario loader before anything runs; the first bad point raises the loader's
    one-line error, the file named as ``FILE [point i: KEY=VALUE, ...]``."""
    file = str(path)
    if not varies:
        raise FusionlogError("sweep: give at least one --vary KEY=VALUES")
    keys = [v.key for v in varies]
    for i, k in enumerate(keys):
        if k in keys[:i]:
            raise FusionlogError(f"--vary {k}: the key is varied twice")
    size = math.prod(len(v.values) for v in varies)
    if size > MAX_POINTS:
        raise FusionlogError(
            f"sweep: {size} grid points is more than {MAX_POINTS} (the bound of a grid; split "
            "the study into several sweeps)"
        )
    text = toml.read_text(file)
    doc = toml.parse_toml(text, file)
    paths = [_resolve(doc, v) for v in varies]
    for v, p in zip(varies, paths, strict=True):
        for q, w in zip(paths, varies, strict=True):
            if w is not v and p[: len(q)] == q and len(p) > len(q):
                raise FusionlogError(f"--vary {v.key}: inside --vary {w.key}, which replaces it")
    points = []
    combos = enumerate(itertools.product(*(range(len(v.values)) for v in varies)))
    for index, combo in progress(combos, size, "grid", "point"):
        label = _label(varies, combo)
        edited = copy.deepcopy(doc)
        for v, p, j in zip(varies, paths, combo, strict=True):
            _assign(edited, p, v.values[j])
        where = f"{file} [point {index}: {label}]"
        sc = scenario_from_doc(edited, where, text, file)
        if sc.kind != "state":
            raise FusionlogError(
                f"{file}: a {sc.kind} scenario; sweeps evaluate state scenarios (MSE, NEES, DM)"
            )
        file_seed = sc.seed
        sc = scenario_with(sc, runs=runs, seed=point_seed(file_seed, index))
        values = {v.key: v.values[j] for v, j in zip(varies, combo, strict=True)}
        points.append(GridPoint(index, values, label, sc, file_seed))
    return points
