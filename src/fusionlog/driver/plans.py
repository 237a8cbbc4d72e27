"""The plans of one model over one horizon, kept across the blocks of runs of a command.

Plans depend on the model and on which measurements are present, never on their values. A
`PlanCache` keeps them per (architecture, pattern shared by a block's runs), so the blocks of a
log with one pattern (usually: everything present) compile each architecture once; blocks
whose runs differ (dropouts) get per-run plans built from their own masks, which a `KeptPlans`
handed to the caches of two stages of one command lets the second take from the first. The
cache also records the blocks' patterns, which the estimates' provenance states.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import pickle
import threading
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from fusionlog.core.architectures import HistoryNodes, Plan, build_plan, shared_pattern
from fusionlog.core.architectures import registry as _registry
from fusionlog.core.architectures.registry import group_by_history
from fusionlog.core.latency import LateModel
from fusionlog.core.model import System

__all__ = ["JobPlans", "KeptPlans", "PlanCache", "pattern_record"]


@dataclass
class KeptPlans:
    """The per-run plans of the last block of runs, for a later stage of the same command on
    the same block: `fusionlog run` estimates, then the evaluation's exact analysis takes the
    same plans (the same model, horizon and masks) instead of building them again. The caller
    makes one and hands it to both stages' caches (`PlanCache.kept`). One block's plans at most
    are kept (a log of several blocks: the last one's, which the evaluation's first block does
    not match)."""

    key: bytes = b""
    plans: dict[str, Plan] = field(default_factory=dict)

    def of_block(self, key: bytes) -> dict[str, Plan]:
        """The plans kept for the block `key`, emptied first when they are another block's."""
        if key != self.key:
            self.key, self.plans = key, {}
        return self.plans


def _block_key(cache: PlanCache, present: np.ndarray) -> bytes:
    """What a block's per-run plans are made of: the model, horizon, criterion and masks."""
    at_most = _registry.NODES_AT_MOST  # the grouping's setting: a benchmark may change it
    h = hashlib.sha256(pickle.dumps((cache.system, cache.steps, cache.criterion, at_most)))
    h.update(repr(present.shape).encode())
    h.update(np.packbits(present).tobytes())
    return h.digest()


@dataclass
class PlanCache:
    """The plans of one system over one horizon, per (architecture, shared pattern).

    `system` is the filters' model on the log's instants, with its per-instant R where the
    noise varies (`of`); `steps` is K (instants k = 0..K).
    """

    system: System
    steps: int
    #: covariance intersection's cost (None: the system's, [estimate] ci_criterion)
    criterion: str | None = None
    plans: dict[tuple[str, bytes], Plan] = field(default_factory=dict, repr=False)
    #: the instants (K+1,) in seconds, where they are not k dt (a nonlinear model's filters
    #: take each interval from them; the plans have them in `system` already)
    times: np.ndarray | None = field(default=None, repr=False)
    #: each block's shared pattern (`np.packbits` of the mask; None: the block's runs differed)
    patterns: list[bytes | None] = field(default_factory=list, repr=False)
    #: the cache serves a log of one run (a replay): its block is estimated without plans
    #: where that applies (`core.architectures.replay`), the same estimates to rounding
    one_run: bool = False
    #: per-run plans shared with another stage of the same command (`KeptPlans`)
    kept: KeptPlans | None = field(default=None, repr=False)
    #: the instants (K+1,) in seconds on which late measurements arrive (None: `times`, else
    #: k dt; `core.latency`)
    clock: np.ndarray | None = field(default=None, repr=False)
    _late: LateModel | None | str = field(default="unset", repr=False)
    #: when each reading arrived, (runs, K+1, S) s, for delays that differ per run (a
    #: latency range): the log's runs from run 0 (`block_plans` cuts a block's)
    arrivals: np.ndarray | None = field(default=None, repr=False)

    @property
    def late(self) -> LateModel | None:
        """The late sensors' arrivals and stacked model (None: every sensor on time)."""
        if isinstance(self._late, str):
            clock = self.clock if self.clock is not None else self.times
            self._late = LateModel.of(self.system, self.steps, clock)
        return self._late

    def block_arrivals(self, run_offset: int, runs: int) -> np.ndarray | None:
        """When the readings of the runs [run_offset, +runs) arrived (`arrivals`), or None."""
        if self.arrivals is None:
            return None
        return self.arrivals[run_offset : run_offset + runs]

    def _build(self, arch: str, present: np.ndarray | None, **kw) -> Plan:
        """`build_plan` of `arch` for the mask `present`, through the late model if any."""
        if self.late is not None:
            return self.late.build(build_plan, arch, present, criterion=self.criterion, **kw)
        return build_plan(self.system, arch, self.steps, present, self.criterion, **kw)

    def __post_init__(self) -> None:
        if self.criterion is None:
            self.criterion = self.system.ci_criterion

    @classmethod
    def of(
        cls,
        system: System,
        times: np.ndarray | None = None,
        R: np.ndarray | None = None,
        steps: int | None = None,
    ) -> PlanCache:
        """A cache for `system` on the instants `times` (K+1,) in seconds (default k dt; see
        `System.on_times`) with the stacked noise covariance R (K+1, m, m) of each instant
        (default the system's, `System.R_at`)."""
        if times is not None:
            system = system.on_times(times)
            steps = len(times) - 1
        if R is not None:
            system = dataclasses.replace(system, Rs=np.asarray(R, dtype=float))
        if steps is None:
            raise ValueError("give the instants (times) or the number of steps")
        return cls(system, steps, times=None if times is None else np.asarray(times, float))

    def plan(self, arch: str, pattern: np.ndarray | None = None) -> Plan:
        """The plan of `arch` for a mask (K+1, m) shared by all runs (None: all present),
        compiled once."""
        K1 = self.steps + 1
        if pattern is None:
            pattern = np.ones((K1, self.system.m), dtype=bool)
        key = (arch, np.packbits(pattern).tobytes())
        plan = self.plans.get(key)
        if plan is None:
            mask = None if pattern.all() else pattern
            plan = self.plans[key] = self._build(arch, mask)
        return plan

    def block_plans(
        self,
        archs: Sequence[str],
        z: np.ndarray,
        run_offset: int = 0,
        arrivals: np.ndarray | None = None,
    ) -> tuple[dict[str, Plan], np.ndarray | None]:
        """Each architecture's plan for the block z (runs, K+1, m) of the runs from
        `run_offset` and its shared pattern (None when the runs differ: plans built per run,
        on history nodes, which the estimates and the exact analysis both take); the pattern
        is recorded for `provenance`. `arrivals` (runs, K+1, S): when the block's readings
        arrived (default: `arrivals` of the runs from `run_offset`), where delays differ."""
        late = self.late
        if late is not None and late.per_run:  # random delays: each run its own arrivals
            self.patterns.append(None)
            arr = arrivals
            if arr is None and self.arrivals is not None:
                arr = self.arrivals[run_offset : run_offset + z.shape[0]]
            present = ~np.isnan(z)
            return {
                a: self._build(a, present, arrival=arr, history_nodes=True) for a in archs
            }, None
        pattern = shared_pattern(z)
        self.patterns.append(None if pattern is None else np.packbits(pattern).tobytes())
        if pattern is not None:
            return {a: self.plan(a, pattern) for a in archs}, pattern
        present = ~np.isnan(z)
        kept = None if self.kept is None else self.kept.of_block(_block_key(self, present))
        plans: dict[str, Plan] = {}
        groups: HistoryNodes | None | str = "group"  # the runs grouped once for all archs
        for a in archs:
            plan = None if kept is None else kept.get(a)
            if plan is None:
                if isinstance(groups, str) and self.late is None:
                    groups = group_by_history(present)
                plan = self._build(a, present, history_nodes=True, groups=groups)
                if kept is not None:
                    kept[a] = plan
            plans[a] = plan
        return plans, None

    def provenance(self) -> dict[str, str]:
        """The estimates' ``measurement_pattern`` (DESIGN.md "MCAP files"): "complete", the
        mask shared by every run of every block as JSON, or "per-run" (a block's runs differed,
        two blocks differed, or there was no block)."""
        return pattern_record(self.patterns, (self.steps + 1, self.system.m))


class JobPlans:
    """The plan caches of the jobs whose blocks one process computes (a sweep's points, a
    distributed run), by job token, the least recently used dropped beyond `size`: a job's
    blocks after the first do not compile again. Whoever runs the blocks owns one and passes
    it to each (`stages.distributed`'s executors: one in this process, one on each Dask
    worker). Thread-safe: a Dask worker may run tasks in threads."""

    def __init__(self, size: int = 8) -> None:
        self.size = size
        self._caches: OrderedDict[str, PlanCache] = OrderedDict()
        self._lock = threading.Lock()

    def of(self, token: str, system: System, times: np.ndarray | None = None) -> PlanCache:
        """The plan cache of job `token` (its `system` on the instants `times`), made on first
        use."""
        with self._lock:
            c = self._caches.get(token)
            if c is not None:
                self._caches.move_to_end(token)
                return c
        c = PlanCache.of(system, times)
        with self._lock:
            c = self._caches.setdefault(token, c)
            while len(self._caches) > self.size:
                self._caches.popitem(last=False)
        return c


#: The estimates' provenance field of their measurement mask (DESIGN.md "MCAP files").
PATTERN = "measurement_pattern"


def pattern_record(patterns: Sequence[bytes | None], shape: tuple[int, int]) -> dict[str, str]:
    """``measurement_pattern`` from blocks' shared patterns (`np.packbits` of each (K+1, m)
    mask of `shape`, None where a block's runs differed): "per-run" when any block's runs
    differed, two blocks differed or there was none; else "complete" or the mask as JSON."""
    if not patterns or any(p is None for p in patterns) or len(set(patterns)) > 1:
        return {PATTERN: "per-run"}
    first = patterns[0]
    assert first is not None
    mask = np.unpackbits(np.frombuffer(first, dtype=np.uint8))[: shape[0] * shape[1]]
    mask = mask.reshape(shape).astype(bool)
    if mask.all():
        return {PATTERN: "complete"}
    return {PATTERN: _mask_json(mask)}


#: Rows of a mask's JSON checked at a time (`pattern_mask`): ~0.1 MB of temporaries.
_ROWS_AT_ONCE = 1 << 13


def _row_template(m: int) -> np.ndarray:
    """ ", [0, 0, 0]": a row of m zero digits as json.dumps writes it, after its separator."""
    return np.frombuffer((", " + json.dumps([0] * m)).encode(), dtype=np.uint8)


def _mask_json(mask: np.ndarray) -> str:
    """json.dumps of the (K+1, m) mask's rows as 0/1 ints, the same text, written into one byte
    array (each row is 3m + 2 characters: its digits at fixed places) instead of through Python
    lists: 11 bytes per instant of three sensors and its string, not ~60 (issue 34)."""
    K1, m = mask.shape
    tmpl = _row_template(m)
    flat = np.empty(K1 * len(tmpl) + 1, dtype=np.uint8)
    rows = flat[:-1].reshape(K1, len(tmpl))
    rows[:] = tmpl
    rows[:, 3::3] += mask  # ord("0") + 1 where present
    flat[1], flat[-1] = ord("["), ord("]")
    return str(memoryview(flat[1:]), "ascii")


def pattern_mask(text: str) -> np.ndarray:
    """The (K+1, m) bool mask of a ``measurement_pattern`` JSON (`pattern_record`), read from
    its digits (one byte per component and instant, no Python list per row): at their fixed
    places where the text is laid out as `pattern_record` writes it (checked a block of rows
    at a time), else wherever its 0 and 1 characters are."""
    first = text[1 : text.index("]") + 1]
    m = first.count("0") + first.count("1")
    chars = np.frombuffer(text.encode(), dtype=np.uint8)
    fixed = _fixed_layout(chars, m)
    if fixed is not None:
        return fixed
    digits = chars[(chars == ord("0")) | (chars == ord("1"))]
    return (digits == ord("1")).reshape(-1, m)


def _fixed_layout(chars: np.ndarray, m: int) -> np.ndarray | None:
    """The mask of a JSON text laid out as `_mask_json` writes it, or None (laid out otherwise)."""
    tmpl = _row_template(m)
    width = len(tmpl)
    if m < 1 or len(chars) % width or chars[0] != ord("[") or chars[-1] != ord("]"):
        return None
    K1 = len(chars) // width
    # row r as written after its separator: chars[r * width - 1 : (r + 1) * width - 1]
    padded = np.lib.stride_tricks.as_strided(
        chars[width - 1 :], shape=(K1 - 1, width), strides=(width, 1), writeable=False
    )
    other = np.ones(width, dtype=bool)
    other[3::3] = False  # the digits' places
    out = np.empty((K1, m), dtype=bool)
    head = chars[: width - 1]  # the first row: "[" then the row without its separator
    if head[0] != ord("[") or not np.array_equal(head[1:][other[2:]], tmpl[2:][other[2:]]):
        return None
    d = head[1:][~other[2:]]
    if not np.isin(d, (ord("0"), ord("1"))).all():
        return None
    out[0] = d == ord("1")
    for a in range(0, K1 - 1, _ROWS_AT_ONCE):
        part = padded[a : a + _ROWS_AT_ONCE]
        if len(part) and not (part[:, other] == tmpl[other]).all():
            return None
        d = part[:, ~other]
        if not ((d == ord("0")) | (d == ord("1"))).all():
            return None
        out[1 + a : 1 + a + len(part)] = d == ord("1")
    return out
