"""The Python API: the pipeline on numpy arrays, nothing written to disk unless asked.

    import fusionlog as fl
    sc = fl.load("pipeline/ajgl2009.toml")       # a validated scenario
    sim = fl.simulate(sc, runs=1000, seed=3)      # .times (K+1,), .truth (M, K+1, n),
                                                  # .measurements {sensor: (M, K+1, m)}, NaN = none
    est = fl.estimate(sc, sim, ["CKF", "MSC"])    # {arch: .mean (M, K+1, n),
                                                  #        .cov (M, K+1, n, n)}
    ev = fl.evaluate(sc, sim, est)                # .summary, .table(), .save("evaluation.rrd")

The API is an adapter over the stages, as the CLI is: `simulate` and `estimate` are
`stages.simulation` (the simulate stage's hook: the random streams belong to chunks of runs, so
the runs are those `fusionlog simulate` writes; `driver.estimate_block` in the estimate stage's
blocks of runs with one plan cache), and `evaluate` is the state evaluator fed the same blocks:
the same scenario, runs and seed give the CLI's numbers.

Bad arguments fail as the CLI does: one `FusionlogError` (a `ValidationError` for the shapes
and values of arrays) naming the argument (`runs`, `filter`, `architectures`,
`sim.measurements['s1']`, `estimates['CKF'].cov`) and the problem (`fusionlog.arguments`),
never numpy's error from deep inside; `simulate`
refuses runs that cannot all be held in memory before allocating them
(`scenario.scenario_base.memory_shortfall`, the CLI's memory decision).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from . import _API
from .arguments import (
    check_architecture_names,
    check_estimate_shapes,
    check_estimate_values,
)
from .core import evaluation
from .core.architectures import Estimate as BlockEstimate
from .core.model import System
from .core.names import check_architectures
from .driver.plans import PATTERN
from .errors import FusionlogError, ValidationError  # noqa: F401 (fl.api.FusionlogError)
from .io.mcap import estimates_topic, sensor_topic
from .scenario import Scenario, load_scenario
from .stages.evaluator import SensorLog, StateEvaluator
from .stages.simulation import (
    Simulation,
    blocks_of,
    estimate_blocks,
    simulation_of,
    state_scenario,
    with_arrivals,
)
from .stages.state_kind import check_discretisable

__all__ = list(_API)  # the names `fusionlog` itself offers


class Estimate:
    """One architecture's estimates of M runs at instants k = 0..K: `mean` (M, K+1, n) and
    `cov` (M, K+1, n, n), for linear and nonlinear scenarios alike.

    Where every run has the same covariance (a linear model without per-run dropouts: the
    gains are computed once for all runs: docs/internals.md) `cov` is a
    read-only view of one (K+1, n, n) array broadcast over the runs, so it costs no memory
    per run: `shared_cov` is then True and `cov[0]` is that array. Otherwise `cov` holds each
    run's own. NaN in both mean and cov marks an instant without an estimate (no prior yet).
    `Estimate(mean, cov)` takes `cov` (M, K+1, n, n), or (K+1, n, n) shared by every run.
    """

    __slots__ = ("_cov", "_shared", "mean")

    def __init__(self, mean: np.ndarray, cov: np.ndarray) -> None:
        self.mean = mean
        shared = (
            isinstance(mean, np.ndarray)
            and isinstance(cov, np.ndarray)
            and mean.ndim == 3
            and cov.ndim == 3
        )
        self._shared = cov if shared else None
        self._cov = np.broadcast_to(cov, mean.shape[:1] + cov.shape) if shared else cov

    @property
    def cov(self) -> np.ndarray:
        """(M, K+1, n, n): each run's covariance at each instant (see the class)."""
        return self._cov

    @property
    def shared_cov(self) -> bool:
        """Whether every run has the same covariance (`cov` a broadcast view of `cov[0]`)."""
        return self._shared is not None

    def __repr__(self) -> str:
        shared = ", shared by the runs" if self.shared_cov else ""
        shapes = f"mean {np.shape(self.mean)}, cov {np.shape(self.cov)}"
        return f"Estimate({shapes}{shared})"


class Estimates(dict[str, Estimate]):
    """{architecture: Estimate} (`Estimate`: `.mean` (M, K+1, n), `.cov` (M, K+1, n, n)).
    `provenance` is what the estimates file records of the measurement pattern (which exact
    analysis applies)."""

    provenance: dict[str, str]


class Evaluation(evaluation.Evaluation):
    """An evaluation (`core.evaluation.Evaluation`: `.summary` the summary.json dict, per-step
    `.series` per architecture, `.samples`, ...) with the adapters a notebook wants."""

    def table(self) -> str:
        """The results table `fusionlog summary` prints (`report.format_table`)."""
        from .report import format_table

        return format_table(self.summary, self.sensors)

    def save(self, path: str | os.PathLike[str], *, force: bool = False) -> Path:
        """Write the Rerun recording to `path` (atomically, `io.atomic.Outputs`; an existing
        file only with `force`): `io.rrd.write_evaluation`. Returns the path."""
        from .io.atomic import Outputs
        from .io.rrd import write_evaluation  # rerun: slow to import, needed only here

        target = Path(path)
        with Outputs([target], force=force) as outs:
            write_evaluation(outs.open(target), self)
            outs.commit()
        return target


def load(path: str | os.PathLike[str]) -> Scenario:
    """The validated scenario of a TOML file (docs/reference/scenario.md); FusionlogError with
    the file, key and reason when it is not valid."""
    return load_scenario(path)


def simulate(
    scenario: Scenario | str | os.PathLike[str],
    runs: int | None = None,
    seed: int | None = None,
    steps: int | None = None,
) -> Simulation:
    """Simulate `runs` runs (default the scenario's) of K = `steps` steps with `seed`: the
    runs `fusionlog simulate --runs --steps --seed` writes to its sensors file. `scenario` is
    a loaded scenario or the path of its file (`load`); a replay file gives its recorded
    readings as one run (and takes no runs, seed or steps)."""
    return simulation_of(state_scenario(scenario), runs, seed, steps)


def estimate(
    scenario: Scenario | str | os.PathLike[str],
    sim: Simulation,
    architectures: Sequence[str] | str | None = None,
    *,
    filter: str | None = None,
    late: str | None = None,
) -> Estimates:
    """Each architecture's estimates of the runs (default: the scenario's `[estimate]
    architectures`; one name may be given as a string; an empty list is refused), as
    `fusionlog estimate` computes them: {name: `Estimate`} with `.mean` (M, K+1, n) and `.cov`
    (M, K+1, n, n). `scenario` is the filters' model: the one simulated, or another
    (`fusionlog estimate --model`), whose sensors are taken from `sim` by name; `filter`
    ("EKF" or "UKF") overrides its local filter as `--filter` does, `late` its policy for late
    measurements as `--late` does."""
    scenario = state_scenario(scenario)
    _check_sim(sim)
    system = with_arrivals(scenario.system, sim)  # a replay's delays are in its data
    if filter is not None:
        from .stages.state_kind import with_filter

        system = with_filter(system, filter, "filter")
    if late is not None:
        from .stages.state_kind import with_late

        system = with_late(system, late, "late")
    names = check_architecture_names(architectures)
    archs = check_architectures(names or list(scenario.architectures), system, "architectures")
    check_discretisable(
        system,
        sim.scenario,
        scenario.path or scenario.name,
        f"the simulation of {sim.scenario.name}",
    )
    parts, provenance = estimate_blocks(system, sim, archs)
    out = Estimates({a: _joined(es) for a, es in parts.items()})
    out.provenance = provenance | {"late": system.late}  # the policy, for `evaluate`
    return out


def _check_sim(sim: Simulation) -> None:
    if not isinstance(sim, Simulation):
        raise ValidationError(
            f"sim: expected a Simulation (fusionlog.simulate), got {type(sim).__name__}"
        )
    sim.check()


def _joined(es: list[BlockEstimate]) -> Estimate:
    """One estimate of the blocks' runs (a covariance shared by every block stays shared)."""
    if len(es) == 1:
        return Estimate(es[0].mean, es[0].cov)
    mean = np.concatenate([e.mean for e in es])
    if all(e.shared_cov and e.cov is es[0].cov for e in es):
        return Estimate(mean, es[0].cov)
    covs = [e.cov if not e.shared_cov else np.broadcast_to(e.cov, e.mean.shape[:1] + e.cov.shape)
            for e in es]  # fmt: skip
    return Estimate(mean, np.concatenate(covs))


def evaluate(
    scenario: Scenario | str | os.PathLike[str], sim: Simulation, estimates: Estimates
) -> Evaluation:
    """MSE (eq. 45), ANEES, DM (eq. 47) with their exact expected values, NIS where it says
    something, and sample runs: what `fusionlog evaluate` puts in summary.json and the
    recording (written only by `Evaluation.save`). `scenario` is the model the estimates
    were made with (`estimate`); the truth is `sim`'s. `estimates` is {name: `Estimate`} of
    `sim`'s runs and instants, each (run, instant) an estimate (finite, its covariance
    positive semidefinite) or none (NaN in mean and cov): anything else is a
    ValidationError naming the architecture."""
    scenario = state_scenario(scenario)
    _check_sim(sim)
    sc = sim.scenario  # the truth's: the runs, steps and seed simulated
    system = scenario.system
    late = getattr(estimates, "provenance", {}).get("late")
    if late is not None and isinstance(system, System):  # `estimate(late=)`: its policy
        system = dataclasses.replace(system, late=late)
    filter_sys, truth_sys = sim.on_instants(system), sim.on_instants(sc.system)
    _check_estimates(sim, estimates, filter_sys)
    # the estimates' record of their measurement pattern (plain dicts: none known, per run)
    prov = (
        estimates.provenance
        if isinstance(estimates, Estimates) and hasattr(estimates, "provenance")
        else {PATTERN: "per-run"}
    )
    # the sensors' availability, where it says something (their own timing, a recording)
    timed = sc.replay is not None or any(not s.timing.default for s in sc.system.sensors)
    log = SensorLog(
        sim.truth is not None,
        sim.scheduled if timed else None,
        sim.truth_info,
        sim.arrivals(scenario.system),
    )
    ev = StateEvaluator(
        sc, list(estimates), filter_sys, truth_sys, sim.runs, sim.times, prov, log, sc.name
    )
    topics = {sensor_topic(name): z for name, z in sim.measurements.items()}
    for off, n in blocks_of(sim):
        ests = {}
        for a, e in estimates.items():
            mean, cov = ests[estimates_topic(a)] = _runs(e, off, n)
            check_estimate_values(a, mean, cov, off)  # a shared cov: its (K+1, n, n)
        readings = {t: z[off : off + n] for t, z in topics.items()}
        truth = None if sim.truth is None else sim.truth[off : off + n]
        ev.add(off, truth, ests, readings)
    return Evaluation(**vars(ev.evaluation({"command": "fusionlog.evaluate"})))


def _check_estimates(sim: Simulation, estimates: Estimates, system: System) -> None:
    """The estimates are `Estimate`s of known architectures, of `sim`'s runs and instants and
    of the filter's states: one clear error, not numpy's deep inside."""
    if not isinstance(estimates, Mapping):
        raise ValidationError(
            f"estimates: expected {{architecture: Estimate}} (what fusionlog.estimate returns), "
            f"got {type(estimates).__name__}"
        )
    if not estimates:
        raise ValidationError("estimates: empty (fusionlog.estimate gives them)")
    names = check_architecture_names(list(estimates))
    check_architectures(names, system, "estimates")
    for a, e in estimates.items():
        if not isinstance(e, Estimate):
            raise ValidationError(
                f"estimates[{a!r}]: expected an Estimate (fusionlog.estimate returns them; "
                f"fusionlog.Estimate(mean, cov) makes one), got {type(e).__name__}"
            )
        check_estimate_shapes(a, e, sim.runs, len(sim.times), system.n)


def _runs(e: Estimate, off: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(mean, cov) of runs [off, off + n) of an estimate, a shared covariance (K+1, n, n)
    once for the block (the evaluator's one inverse per instant for all runs)."""
    return e.mean[off : off + n], e._shared if e._shared is not None else e.cov[off : off + n]
