"""The registry of architectures (DESIGN.md "Architectures": names used on the CLI, in topics
and in summaries) and the one place that compiles a name into a plan.

Every backend asks `definition(name)` for an architecture (`definition.Architecture`: its
local filters and fusion rule) and refuses a name no definition has: the plans and their exact
analysis (`build_plan`), the one-run replay path (`replay`, `core.exact_replay`), the EKF/UKF
lanes (`core.nonlinear`), the consistency checks and the recording's colours. `register` adds
one (a new fusion rule: one definition, e.g. `ici.ICI`).
"""

from __future__ import annotations

import numpy as np

from ...errors import NumericalError
from ..linalg import all_finite, numerical_errors
from ..model import System
from . import rules
from .definition import Architecture
from .ei import EI
from .fbs import build_fbs
from .hkf import build_hkf
from .ici import ICI
from .plan import BuildRequest, HistoryNodes, Plan
from .single import build_ckf, build_skf
from .track_to_track import build_rule

#: Registered definitions by name, in the order of the default `[estimate] architectures`
#: list: the paper's Table I, then covariance intersection, the smoother and the plain
#: average (Gustafsson-Hendeby's "LS"); then those not run by default.
REGISTRY: dict[str, Architecture] = {}


def register(arch: Architecture, *, replace: bool = False) -> Architecture:
    """Add an architecture to the registry (every backend takes it from there); a name that is
    registered already is refused unless `replace`. Returns `arch`."""
    if arch.name in REGISTRY and not replace:
        raise ValueError(f"architecture {arch.name!r} is registered already")
    REGISTRY[arch.name] = arch
    return arch


def unregister(name: str) -> None:
    """Remove a registered architecture (a test's own rule, when it is done)."""
    REGISTRY.pop(name, None)


def definition(name: str) -> Architecture:
    """The definition of architecture `name` (a base name, or ``SKF:<sensor>``); ValueError
    naming the known ones for a name no definition has."""
    base = name.partition(":")[0]
    arch = REGISTRY.get(base)
    if arch is None:
        known = ", ".join(REGISTRY)
        raise ValueError(f"unknown architecture {name!r} (known: {known}, SKF:<sensor>)")
    return arch


for _a in (
    Architecture(
        "CKF",
        "centralised KF on all sensors, eqs. (29)-(31)",
        "centralised",
        build=build_ckf,
        default=True,
        color=(31, 119, 180),
    ),
    Architecture(
        "HKF",
        "hierarchical KF with feedback, eqs. (36)-(40)",
        "hierarchical",
        build=build_hkf,
        default=True,
        color=(255, 127, 14),
    ),
    Architecture(
        "MSC-GMF",
        "local KFs, generalised Millman formula, eqs. (6)-(7), (35)",
        "per-sensor",
        rule=rules.msc_gmf,
        joint=True,
        information=True,
        default=True,
        color=(44, 160, 44),
    ),
    Architecture(
        "MSC",
        "local KFs, Millman's formula, eqs. (32)-(34)",
        "per-sensor",
        rule=rules.msc,
        information=True,
        default=True,
        color=(214, 39, 40),
    ),
    Architecture(
        "SKF",
        "KF on one sensor",
        "single",
        build=build_skf,
        takes_sensor=True,
        default=True,
        color=(148, 103, 189),
    ),
    Architecture(
        "CI",
        "local KFs, covariance intersection",
        "per-sensor",
        rule=rules.ci,
        information=True,
        default=True,
        color=(140, 86, 75),
    ),
    Architecture(
        "FBS",
        "fixed-interval smoother, eqs. (25)-(28)",
        "smoother",
        build=build_fbs,
        default=True,
        color=(227, 119, 194),
    ),
    Architecture(
        "AVG",
        "local KFs, plain average with its true covariance",
        "per-sensor",
        rule=rules.avg,
        joint=True,
        information=True,
        default=True,
    ),
    ICI,
    EI,
):
    register(_a)

#: The architectures a scenario runs by default, in registry order.
STATE_ARCHITECTURES: tuple[str, ...] = tuple(a.name for a in REGISTRY.values() if a.default)


def parse_arch(name: str, sensor_names: list[str] | tuple[str, ...]) -> tuple[str, str | None]:
    """Split an architecture name into (base, sensor); `SKF:<sensor>` picks the SKF's sensor.

    Raises ValueError with a readable reason for an unknown name or sensor.
    """
    base, _, sensor = name.partition(":")
    arch = definition(base)
    if len(sensor_names) < arch.min_sensors:
        raise ValueError(
            f"architecture {base} fuses at least {arch.min_sensors} local filters, one per "
            f"sensor: the model has {len(sensor_names)} sensor(s)"
        )
    if not arch.takes_sensor:
        if sensor:
            takers = ", ".join(a.name for a in REGISTRY.values() if a.takes_sensor)
            raise ValueError(f"architecture {name!r}: only {takers} takes a sensor suffix")
        return base, None
    if not sensor_names:
        raise ValueError(f"{base} needs at least one sensor")
    if not sensor:
        return base, sensor_names[0]
    if sensor not in sensor_names:
        raise ValueError(
            f"architecture {name!r}: no sensor {sensor!r} (sensors: {', '.join(sensor_names)})"
        )
    return base, sensor


def build_plan(
    system: System,
    arch: str,
    steps: int,
    present: np.ndarray | None = None,
    criterion: str | None = None,
    *,
    history_nodes: bool = False,
    groups: HistoryNodes | None | str = "group",
) -> Plan:
    """Compile architecture `arch` for instants k = 0..steps.

    `present` is a boolean mask of measurement components, (K+1, m) shared by all runs or
    (M, K+1, m) per run; None means every measurement is present. A model whose numbers
    overflow or leave a matrix singular beyond what the filters can work around raises
    NumericalError naming the architecture, the step and the matrix.

    Per run, the maps are computed once per measurement history (`HistoryNodes`) and, unless
    `history_nodes`, gathered into per-run maps (a leading run axis, what the exact analysis
    cuts by runs); `run_plan` takes either (`estimate` keeps the nodes: less memory). `groups`
    is `group_by_history(present)` where the caller has it already ("group": grouped here).
    """
    base, sensor = parse_arch(arch, [s.name for s in system.sensors])
    if present is None:
        present = np.ones((steps + 1, system.m), dtype=bool)
    criterion = criterion or system.ci_criterion  # CI's cost: [estimate] ci_criterion
    request = BuildRequest(system, arch, present, sensor, criterion, step=None)
    if present.ndim == 3:
        request.nodes = group_by_history(present) if isinstance(groups, str) else groups
    with numerical_errors(lambda: _where(request)):
        check_model(system)
        arch = REGISTRY[base]
        plan = arch.build(request) if arch.build is not None else build_rule(request, arch)
    plan.system = system
    plan.complete = bool(present.all())
    return plan if history_nodes else plan.per_run_maps()


#: Per run, the maps are built per measurement history (`HistoryNodes`) when there are at most
#: this fraction as many histories as run-steps; beyond, gathering the runs' maps from the
#: nodes would cost more than computing fewer of them saves.
NODES_AT_MOST = 0.8


def group_by_history(present: np.ndarray) -> HistoryNodes | None:
    """The runs of the per-run mask `present` (M, K+1, m) grouped by history, or None when
    that would not pay (`NODES_AT_MOST`; over 16 components the grouping itself is slow).
    The architectures of one block are built on the same mask one after the other: the
    driver groups once and hands the grouping to each `build_plan` (`groups`)."""
    M, K1, m = present.shape
    if m > 16:
        return None
    nodes = HistoryNodes.of(present)
    return nodes if nodes.count <= NODES_AT_MOST * M * K1 else None


def check_model(system: System) -> None:
    """Refuse a model whose matrices are not finite (an accepted entry of 1e308 can overflow
    where the model is assembled, e.g. in G Q G')."""
    mats = {"the model's F": system.F, "the model's G Q G'": system.GQG}
    if system.prior is not None:
        mats |= {"the prior mean": system.prior.mean, "the prior covariance": system.prior.cov}
    mats |= {f"sensor {s.name}'s R": s.R for s in system.sensors}
    names = [s.name for s in system.sensors]
    mats |= {
        f"the noise cross-covariance of {names[i]} and {names[j]}": c
        for (i, j), c in system.cross_R.items()
    }
    for what, a in mats.items():
        if not all_finite(a):
            raise NumericalError(f"{what} is not finite (beyond the float range, about 1.8e308)")


def _where(request: BuildRequest) -> str:
    """ "architecture X, step k" (without the step for the model check and for fusion rules
    evaluated over all steps at once)."""
    step = "" if request.step is None else f", step {request.step}"
    return f"architecture {request.name}{step}"
