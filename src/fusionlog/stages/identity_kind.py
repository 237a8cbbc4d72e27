"""The identity kind's stage hooks: Bayesian and Dempster-Shafer identity fusion (seed 004).

MCAP (the DESIGN contract, schema ``fusionlog.Block`` for every topic, ``dim`` = columns):

=========================  ======  ========================================================
``/truth``                 1       index of the true class in ``classes``
``/sensors/<name>``        1       index of the report in the sensor's ``reports``; NaN = no
                                   report at that step (a real log may have gaps)
``/estimates/BAYES``       N       posterior probability of each class, in ``classes`` order
``/estimates/DS``          2N + 2  Bel({c}) of each class, then Pl({c}) of each class, then
                                   the conflict K of that step's combination, then the
                                   accumulated conflict 1 - prod_{t<=k} (1 - K_t)
=========================  ======  ========================================================

The sensors file's ``fusionlog.scenario`` record has ``kind = "identity"`` and the resolved
definitions (JSON, field ``identity``); the estimates file's provenance has the column layout
(field ``columns``). The math is :mod:`fusionlog.core.identity` (simulation, fusion, metrics).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from fusionlog.core.identity.fusion import columns, dims, report_indices
from fusionlog.core.identity.fusion import estimate as identity_estimate
from fusionlog.core.identity.metrics import IdentityMetrics
from fusionlog.core.identity.model import ARCHITECTURES, IdentitySystem
from fusionlog.core.identity.simulate import simulate
from fusionlog.errors import FusionlogError
from fusionlog.io.mcap import VALUES, McapFile, McapWriter
from fusionlog.io.mcap.topics import TRUTH, estimates_topic, sensor_topic
from fusionlog.scenario import Scenario, check_identity_architectures, load_model

from .common import block_runs
from .hooks import (
    Array,
    Estimator,
    Evaluator,
    Kind,
    Model,
    Prov,
    Readings,
    Sens,
    StepWriter,
    Topics,
)

#: Default bound on masses held at once by DS (runs x 2^N), as RUN_STEPS_PER_BLOCK for steps.
DS_MASSES_PER_BLOCK = 1 << 21


def _block(steps: int, runs: int, n_classes: int, requested: int | None) -> int:
    if requested is not None:
        return block_runs(steps, runs, requested)
    return max(1, min(block_runs(steps, runs), DS_MASSES_PER_BLOCK >> n_classes))


class IdentityKind(Kind):
    name = "identity"

    def system_fields(self, scenario: Scenario) -> dict[str, str]:
        return {"identity": json.dumps(_with_archs(scenario))}

    def bytes_per_run_step(self, scenario: Scenario) -> int:
        s: IdentitySystem = scenario.system
        return 8 * (1 + len(s.sensors)) * 2 + 8 * (3 * s.n + 2) * 2

    def sensor_names(self, system: IdentitySystem) -> list[str]:
        return [s.name for s in system.sensors]

    def check_architectures(
        self, names: Sequence[str], system: IdentitySystem, where: str
    ) -> list[str]:
        return check_identity_architectures(names, where)

    def simulate(
        self, scenario: Scenario, run_offset: int, runs: int
    ) -> tuple[np.ndarray, list[np.ndarray]]:
        truth, reports = simulate(scenario.system, scenario.steps, scenario.seed, run_offset, runs)
        K1 = scenario.steps + 1
        t = np.broadcast_to(truth.astype(float)[:, None, None], (runs, K1, 1))
        r = reports.astype(float)
        return t, [r[:, :, s : s + 1] for s in range(r.shape[-1])]

    def model(self, sensors: McapFile, recorded: Scenario | None, model_path: Path | None) -> Model:
        if model_path is None:
            recorded = self.recorded(sensors, recorded)
            return Model(
                recorded.system,
                "scenario",
                json.dumps(_with_archs(recorded)),
                list(recorded.architectures),
            )
        model: Scenario = load_model(model_path, "identity")
        system: IdentitySystem = model.system
        if recorded is not None:
            if system.classes != recorded.system.classes:
                raise FusionlogError(
                    f"{model_path}: identity.classes {list(system.classes)} differ from the "
                    f"recorded scenario's {list(recorded.system.classes)}"
                )
            rec = {s.name: s for s in recorded.system.sensors}
            for j, s in enumerate(system.sensors):
                if s.name in rec and s.reports != rec[s.name].reports:
                    raise FusionlogError(
                        f"{model_path}: identity_sensors[{j}].reports {list(s.reports)} differ "
                        f"from the recorded sensor's {list(rec[s.name].reports)} (the log holds "
                        "indices into them)"
                    )
        archs = list(recorded.architectures if recorded is not None else model.architectures)
        return Model(system, str(model_path), json.dumps(_with_archs(model)), archs)

    def sensor_dims(self, system: IdentitySystem) -> list[tuple[str, int]]:
        return [(s.name, 1) for s in system.sensors]  # a report index

    def estimator(
        self,
        system: IdentitySystem,
        steps: int,
        runs: int,
        archs: list[str],
        sensors: McapFile,
        kept: Any = None,
    ) -> Estimator:
        return _IdentityEstimator(system, steps, runs, archs, sensors.path)

    def write_evaluation(self, file: BinaryIO, evaluation: Any) -> None:
        from fusionlog.io.rrd import write_identity_recording  # rerun: slow to import

        write_identity_recording(file, **evaluation.recording)

    def evaluator(
        self, sc: Scenario, est: McapFile, prov: Prov, sens: Sens = None, kept: Any = None
    ) -> Evaluator:
        return _IdentityEvaluator(sc, est)


def _with_archs(sc: Scenario) -> dict[str, Any]:
    d = sc.system.to_dict()
    d["architectures"] = list(sc.architectures)
    return d


def _values_writer(vals: np.ndarray) -> StepWriter:
    def write(w: McapWriter, topic: str, k: int, t: float, off: int) -> None:
        w.write_values(topic, k, t, off, vals[:, k])

    return write


class _IdentityEstimator(Estimator):
    def __init__(
        self, system: IdentitySystem, steps: int, runs: int, archs: list[str], path: Any
    ) -> None:
        self.system, self.K, self.M, self.archs, self.path = system, steps, runs, archs, path
        self.topics = [sensor_topic(s.name) for s in system.sensors]

    def block_runs(self, requested: int | None) -> int:
        return _block(self.K, self.M, self.system.n, requested)

    def estimate(self, run_offset: int, data: dict[str, np.ndarray]) -> dict[str, StepWriter]:
        try:
            reports = np.stack(
                [
                    report_indices(data[t][..., 0], len(s.reports), t, allow_nan=True)
                    for t, s in zip(self.topics, self.system.sensors, strict=True)
                ],
                axis=-1,
            )
        except ValueError as e:
            raise FusionlogError(f"{self.path}: runs from {run_offset}: {e}") from None
        out: dict[str, StepWriter] = {}
        for a in self.archs:
            try:
                vals = identity_estimate(self.system, reports, a, run_offset)
            except ValueError as e:
                raise FusionlogError(f"{self.path}: identity fusion failed: {e}") from None
            out[a] = _values_writer(vals)
        return out

    def provenance(self) -> dict[str, str]:
        return {"columns": json.dumps(columns(self.system.classes, self.archs))}


@dataclass
class IdentityEvaluation:
    """A finished identity evaluation: the summary.json dict and what the recording draws
    (`io.rrd.write_identity_recording`'s arguments)."""

    summary: dict[str, Any]
    recording: dict[str, Any]


class _IdentityEvaluator(Evaluator):
    """Accuracy, log-loss, P(true), DS belief/plausibility/conflict; BAYES-DS disagreement."""

    def __init__(self, sc: Scenario, est: McapFile) -> None:
        self.sc, self.path = sc, est.path
        n = sc.system.n
        d = dims(n)
        self.archs = [a for a in ARCHITECTURES if estimates_topic(a) in est.topics]
        if not self.archs:
            have = ", ".join(sorted(est.topics)) or "none"
            raise FusionlogError(
                f"{est.path}: no /estimates/BAYES or /estimates/DS topics (topics: {have})"
            )
        self.topics = [estimates_topic(a) for a in self.archs]
        for a, t in zip(self.archs, self.topics, strict=True):
            if est.kind_of(t) != VALUES or est.dim_of(t) != d[a]:
                raise FusionlogError(
                    f"{est.path}: topic {t} is not an identity estimate "
                    f"(fusionlog.Block with {d[a]} values per run for {n} classes)"
                )
        self.K, self.M = est.steps() - 1, est.runs()
        self.times = est.times()
        self.metrics = IdentityMetrics(
            self.K + 1, sc.system.classes, self.archs, min(sc.sample_runs, self.M)
        )

    def block_runs(self, requested: int | None) -> int:
        return _block(self.K, self.M, self.sc.system.n, requested)

    def add(self, off: int, truth: Array, estimates: Topics, sensors: Readings = None) -> None:
        n = self.sc.system.n
        try:
            classes = report_indices(truth[:, 0, 0], n, TRUTH, allow_nan=False)
        except ValueError as e:
            raise FusionlogError(f"{self.path}: runs from {off}: {e}") from None
        if (truth[..., 0] != truth[:, :1, 0]).any():
            raise FusionlogError(f"{self.path}: runs from {off}: the true class changes")
        ests = {a: estimates[t] for a, t in zip(self.archs, self.topics, strict=True)}
        self.metrics.add(classes, ests, off)

    def evaluation(self, provenance: dict[str, Any]) -> IdentityEvaluation:
        res = self.metrics.finish()
        out: dict[str, Any] = {
            "kind": "identity",
            "scenario": self.sc.name,
            "seed": self.sc.seed,
            "runs": self.M,
            "steps": self.K,
            "state_names": list(self.sc.system.classes),
            "architectures": res.architectures,
        }
        if res.disagreement is not None:
            out["disagreement"] = res.disagreement_overall
            out["final_disagreement"] = res.disagreement_final
        definitions = {
            "columns": json.dumps(columns(self.sc.system.classes, self.archs)),
            "decision": "BAYES: largest posterior; DS: largest belief, ties by plausibility; "
            "remaining ties split evenly",
            "p_true": "BAYES: posterior; DS: normalised plausibility Pl({c}) / sum Pl",
            "per_class": "identity/<kind>/<class>/<ARCH>: mean over the runs whose truth is "
            "<class>",
        }
        return IdentityEvaluation(
            out,
            dict(
                scenario_name=self.sc.name,
                seed=self.sc.seed,
                times=self.times,
                classes=self.sc.system.classes,
                series=res.series,
                disagreement=res.disagreement,
                summary=out,
                sample_runs=res.samples,
                properties={
                    "scenario": self.sc.source,
                    "provenance": provenance,
                    "identity": definitions,
                },
            ),
        )
