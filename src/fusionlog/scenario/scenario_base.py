"""What every scenario has, whatever its kind: the Monte Carlo budget, the instants, the limits.

A scenario has a **kind**, decided once when it is loaded (:func:`fusionlog.scenario.load_scenario`)
and recorded in the sensors file's ``fusionlog.scenario`` metadata for the later stages:

* ``state`` — a linear Gaussian system (:class:`fusionlog.core.model.System`) and the fusion
  architectures of the Ajgl-Šimandl-Duník paper;
* ``identity`` — a classification problem (:class:`fusionlog.core.identity.IdentitySystem`:
  classes, prior, sensors with confusion matrices) fused by Bayes' and Dempster's rules.

Each kind is a class of its own (a subclass of :class:`Scenario`, defined beside its file's
parser): ``StateScenario`` and, for a nonlinear model, ``NonlinearScenario``
(:mod:`.state_file`), ``ReplayScenario`` (:mod:`.replay_file`: a state scenario whose sensors
are recorded), ``IdentityScenario`` (:mod:`.identity_file`). ``Scenario.system`` is the
kind's system; everything else is common, and a kind's own checks are its methods
(`check_overrides`, `check_horizon`).
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from functools import cached_property
from typing import Any, ClassVar

import numpy as np

from fusionlog.core.timing import Schedule
from fusionlog.errors import ValidationError

from . import toml
from .toml import Ctx

__all__ = [
    "KINDS",
    "Scenario",
    "Header",
    "header",
    "scenario_with",
    "check_budget",
    "memory_shortfall",
]

#: The kinds of scenario.
KINDS: tuple[str, ...] = ("state", "identity")

DEFAULT_SAMPLE_RUNS = 3
DEFAULT_CONFIDENCE = 0.95

#: MCAP fields step, runs and run_offset are uint32.
MAX_INDEX = 2**32 - 1
#: log_time is an unsigned 64-bit count of nanoseconds; keep a margin below 2^64 ns (584 years).
MAX_TIME_S = 1.8e10


@dataclass(frozen=True, eq=False)
class Scenario:
    """A validated scenario of any kind: the system, the Monte Carlo budget, the defaults."""

    #: the kind recorded in the files ("state" | "identity"), a class's own
    kind: ClassVar[str] = ""
    name: str
    description: str
    steps: int  # K: instants k = 0..K
    runs: int  # M
    seed: int
    dt: float
    state_names: tuple[str, ...]  # identity: the classes
    system: Any  # core.model.System | core.identity.IdentitySystem
    architectures: tuple[str, ...]
    confidence: float = DEFAULT_CONFIDENCE
    sample_runs: int = DEFAULT_SAMPLE_RUNS
    plane_view: bool = False  # a 2-D view of the state plane (n = 2): estimates and ellipses
    #: a long log's recorded series at every instant (default: decimated, `core.decimate`)
    full_resolution: bool = False
    source: str = ""  # the TOML text as loaded (overrides are not written back into it)
    path: str | None = None
    #: a replay's recorded data (`replay_file.Replay`, a ReplayScenario's); None: simulated
    replay: Any = None
    #: the trajectory metrics' settings (core.trajectory.TrajectorySettings); None: none
    trajectory: Any = None

    @cached_property
    def schedule(self) -> Schedule:
        """The instants of the horizon [0, steps dt], t_k = k dt (a kind whose sensors have
        their own timing says otherwise), and which sensor measures when (`core.timing`)."""
        k = np.arange(self.steps + 1)
        return Schedule(k * self.dt, np.ones((self.steps + 1, 0), dtype=bool), True)

    @property
    def times(self) -> np.ndarray:
        """t_k for k = 0..K (k dt unless the sensors' timing makes the instants irregular)."""
        return self.schedule.times

    @property
    def instants(self) -> int:
        """K + 1, the number of instants (steps + 1 on the regular grid, counted without
        building anything)."""
        return self.steps + 1

    def check_overrides(self, file: str, given: list[str]) -> None:
        """Refuse the Monte Carlo overrides `given` (``--runs`` ...) a kind does not take
        (ValidationError naming `file`); every kind so far but the replay takes them."""

    def check_horizon(self, ctx: Ctx, steps_key: str) -> None:
        """The kind's checks of a horizon other than its file's (`scenario_with`'s steps),
        ValidationError naming `steps_key`; none for a kind without sensor timing."""

    @classmethod
    def of(cls, h: Header, system: Any, **fields: Any) -> Scenario:
        """A scenario of this kind from its ``[scenario]`` header, system and other fields."""
        return cls(
            name=h.name,
            description=h.description,
            steps=h.steps,
            runs=h.runs,
            seed=h.seed,
            system=system,
            **fields,
        )


@dataclass(frozen=True)
class Header:
    """The ``[scenario]`` keys common to every kind."""

    name: str
    description: str
    steps: int
    runs: int
    seed: int
    dt: float | None


def header(ctx: Ctx, sc: dict[str, Any], *, model: bool, name_default: str = "model") -> Header:
    """Check ``[scenario]``'s common keys; in a model file (``model``) none is required."""
    for key in ("name", "steps", "runs", "seed", "dt"):
        if not model and key not in sc:
            raise ctx.err(f"scenario.{key}", "missing required key")
    name = toml.name(ctx, sc["name"], "scenario.name") if "name" in sc else name_default
    description = toml.string(ctx, sc.get("description", ""), "scenario.description")
    ints = {}
    for key, minimum, default in (("steps", 0, 0), ("runs", 1, 1), ("seed", 0, 0)):
        v = sc.get(key, default)
        ints[key] = toml.integer(ctx, v, f"scenario.{key}", minimum=minimum)
    dt = None
    if "dt" in sc:
        dt = toml.number(ctx, sc["dt"], "scenario.dt")
        if not dt > 0:
            raise ctx.err("scenario.dt", f"must be > 0, got {toml.fmt(dt)}")
    h = Header(name, description, ints["steps"], ints["runs"], ints["seed"], dt)
    _check_ranges(ctx, h.steps, h.runs, h.dt, "scenario.steps", "scenario.runs")
    return h


def _check_ranges(
    ctx: Ctx, steps: int, runs: int, dt: float | None, steps_key: str, runs_key: str
) -> None:
    """What the files can hold: indices in uint32, the last instant's time in uint64 ns."""
    if steps > MAX_INDEX - 1:
        raise ctx.err(steps_key, f"must be < {MAX_INDEX} (a uint32 step index), got {steps}")
    if runs > MAX_INDEX:
        raise ctx.err(runs_key, f"must be <= {MAX_INDEX} (a uint32 run index), got {runs}")
    if dt is not None and steps * dt > MAX_TIME_S:
        raise ctx.err(
            steps_key,
            f"steps x dt = {toml.fmt(steps * dt)} s exceeds {MAX_TIME_S:.3g} s, the longest time a "
            "log can stamp (nanoseconds in 64 bits)",
        )


def check_budget(scenario: Scenario, bytes_per_run_step: int, what: str) -> None:
    """Refuse a scenario whose smallest block (one run, every instant) cannot fit in memory.

    The stages hold one block of runs at a time (a million run-steps by default, at least one
    run): one run of K+1 instants, ``bytes_per_run_step`` each, must fit in half of the
    machine's memory, or the stage would end in a MemoryError far into the work.
    """
    why = memory_shortfall(scenario.instants, bytes_per_run_step)
    if why is not None:
        raise ValidationError(
            f"{scenario.path or scenario.name}: {what} of {scenario.instants} instants needs "
            f"{why}: use fewer steps"
        )


def memory_shortfall(instants: int, bytes_per_instant: int, runs: int = 1) -> str | None:
    """None when `runs` runs (the stages hold one at least; the Python API holds all of them)
    of `instants` instants, `bytes_per_instant` each, fit in half of this machine's memory;
    else what they need and what there is (the one memory decision, made by the loader before
    a schedule is built, by the stages with their own costs and by the API before simulating)."""
    need = runs * instants * bytes_per_instant
    have = _memory_bytes()
    if not have or need <= have // 2:
        return None
    what = "a single run" if runs == 1 else f"{runs} runs held at once"
    return f"about {need / 2**30:.3g} GiB for {what}, this machine has {have / 2**30:.1f} GiB"


def _memory_bytes() -> int:
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):  # pragma: no cover - not POSIX
        return 0


def scenario_with(
    scenario: Scenario,
    *,
    runs: int | None = None,
    steps: int | None = None,
    seed: int | None = None,
    flag: str = "--",
    recorded: bool = False,
) -> Scenario:
    """A copy with the given Monte Carlo settings replaced (None keeps the scenario's value).
    Errors name an override as `flag` + its name: "--runs" for the CLI's options, "runs" for
    the Python API's arguments (flag=""). `recorded`: the settings a sensors file records
    (`toml.Ctx`: the horizon was checked when it ran)."""
    ctx = Ctx(scenario.path if scenario.path is not None else "<scenario>", recorded)
    changes: dict[str, int] = {}
    if runs is not None:
        changes["runs"] = toml.integer(ctx, runs, f"{flag}runs", minimum=1)
    if steps is not None:
        changes["steps"] = toml.integer(ctx, steps, f"{flag}steps", minimum=0)
    if seed is not None:
        changes["seed"] = toml.integer(ctx, seed, f"{flag}seed", minimum=0)
    if not changes:
        return scenario
    new = dataclasses.replace(scenario, **changes)
    steps_key = f"{flag}steps" if steps is not None else "scenario.steps"
    _check_ranges(
        ctx,
        new.steps,
        new.runs,
        new.dt,
        steps_key,
        f"{flag}runs" if runs is not None else "scenario.runs",
    )
    if steps is not None:
        new.check_horizon(ctx, steps_key)
    return new
