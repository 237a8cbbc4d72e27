"""The hooks a kind of scenario gives the generic stage drivers.

The drivers (:mod:`.simulate`, :mod:`.estimate`, :mod:`.evaluate`) own what every kind shares:
the block loop over runs, progress, provenance, the MCAP layout and atomic outputs. A kind
(``state``: :mod:`.state_kind`; ``identity``: :mod:`.identity_kind`) subclasses :class:`Kind` and
says how to simulate a block, how to estimate one (an :class:`Estimator`), how to accumulate
metrics (an :class:`Evaluator`, which returns a value) and how to write that value -- as Stone
Soup's categorical state is just another state type whose updater subclasses the same base.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, BinaryIO, NamedTuple

import numpy as np

from fusionlog.errors import FusionlogError
from fusionlog.io.mcap import VALUES, McapFile, McapWriter, sensor_topic
from fusionlog.scenario import Scenario


class Model(NamedTuple):
    """The model a filter runs with."""

    system: Any  # the kind's system
    source: str  # "scenario" or the --model file
    json: str  # the resolved system as JSON (estimates provenance)
    architectures: list[str]  # the default when --arch is not given


#: The argument types of the evaluation hooks: an array (None: no truth), the decoded
#: topics of a block, the sensor readings of a block (None: not read), the provenance record,
#: the sensors file (None: not at hand).
Array = np.ndarray | None
Topics = dict[str, Any]
Readings = dict[str, np.ndarray] | None
Prov = dict[str, str]
Sens = McapFile | None

#: Writes one step of one topic: (writer, topic, step, time, run_offset).
StepWriter = Callable[[McapWriter, str, int, float, int], None]


class Estimator(ABC):
    """Estimates blocks of runs with a kind's architectures."""

    @abstractmethod
    def block_runs(self, requested: int | None) -> int:
        """Runs per block."""

    @abstractmethod
    def estimate(self, run_offset: int, data: dict[str, np.ndarray]) -> dict[str, StepWriter]:
        """Estimates of one block, from the sensor topics' arrays (runs, K+1, dim): for each
        output topic, the function writing its message at a step."""

    @abstractmethod
    def provenance(self) -> dict[str, str]:
        """Fields the estimates' provenance record adds, known once every block is done."""

    def time_windows(self, sensors: McapFile) -> Any:
        """A one-run log too long for one block: its estimates block of time by block,
        (k0, k1, {output topic: StepWriter at steps k0..k1-1}), or None (blocks of runs)."""
        return None


class Evaluator(ABC):
    """Accumulates a kind's metrics block by block and writes its recording."""

    #: The estimates file's topics to read, and the runs per block.
    topics: list[str]
    #: The sensors file's topics `add` needs besides /truth (none unless the kind says so).
    sensor_topics: Sequence[str] = ()

    @abstractmethod
    def block_runs(self, requested: int | None) -> int:
        """Runs per block."""

    def time_windows(self) -> Any:
        """A one-run log evaluated in blocks of time: an object with ``add(k0, k1, truth,
        estimates)`` and ``evaluation()``, or None (blocks of runs)."""
        return None

    @abstractmethod
    def add(self, off: int, truth: Array, estimates: Topics, sensors: Readings = None) -> None:
        """Add one block: truth (runs, K+1, dim), each topic's decoded estimates, and the
        readings of `sensor_topics` ((runs, K+1, dim), NaN where absent; None when the caller
        does not have them)."""

    @abstractmethod
    def evaluation(self, provenance: dict[str, Any]) -> Any:
        """Everything accumulated, finished: a value whose ``summary`` is the summary.json
        dict (DESIGN.md "summary.json"), which the kind's `Kind.write_evaluation` writes."""


class Kind(ABC):
    """A kind of scenario: its system, its architectures and its three stage hooks."""

    name: str

    @abstractmethod
    def system_fields(self, scenario: Scenario) -> dict[str, str]:
        """The resolved system for the ``fusionlog.scenario`` record."""

    @abstractmethod
    def bytes_per_run_step(self, scenario: Scenario) -> int:
        """Memory a stage holds per (run, instant), for the budget check."""

    @abstractmethod
    def sensor_names(self, system: Any) -> list[str]:
        """Sensor names in the system's order (topics ``/sensors/<name>``)."""

    @abstractmethod
    def check_architectures(self, names: Sequence[str], system: Any, where: str) -> list[str]:
        """Valid architecture names (duplicates dropped), else FusionlogError naming `where`."""

    @abstractmethod
    def simulate(
        self, scenario: Scenario, run_offset: int, runs: int
    ) -> tuple[np.ndarray, list[np.ndarray]]:
        """Truth (runs, K+1, d) and each sensor's readings (runs, K+1, m), in sensor order."""

    def simulate_blocks(self, scenario: Scenario, block: int) -> Any:
        """A one-run scenario's truth and readings in blocks of time, (k0, k1, truth (1, w, d),
        [readings (1, w, m) per sensor]), or None (the whole run at once, `simulate`)."""
        return None

    def arrivals(self, scenario: Scenario, run_offset: int, runs: int) -> np.ndarray | None:
        """When each reading of the runs arrives, (runs, K+1, S) seconds; None: on time."""
        return None

    def arrival_blocks(self, scenario: Scenario, block: int) -> Any:
        """A one-run scenario's `arrivals` of run 0 in blocks of time, (w, S) s each (NaN: a
        sensor on time), in order, where delays are drawn; None otherwise."""
        return None

    def latencies(self, scenario: Scenario) -> np.ndarray | None:
        """Each sensor's fixed latency (S,) s where some sensor is late and none has a delay
        drawn per reading (a reading taken at t arrives at t + latency); None otherwise."""
        return None

    @abstractmethod
    def model(self, sensors: McapFile, recorded: Scenario | None, model_path: Path | None) -> Model:
        """The filter's model: the recorded scenario's system, or the ``--model`` file's."""

    @staticmethod
    def recorded(sensors: McapFile, recorded: Scenario | None) -> Scenario:
        """The scenario recorded in the sensors file, which must have one when there is no
        ``--model``."""
        if recorded is None:
            raise FusionlogError(
                f"{sensors.path}: no fusionlog.scenario metadata to take the model from; "
                "pass --model MODEL.toml"
            )
        return recorded

    @abstractmethod
    def sensor_dims(self, system: Any) -> list[tuple[str, int]]:
        """(sensor name, values per reading) in the system's order."""

    def check_sensor_topics(self, sensors: McapFile, system: Any) -> list[str]:
        """The sensor topics ``/sensors/<name>`` the model needs, checked against the file:
        each present, a ``fusionlog.Block`` stream with the sensor's number of values."""
        topics = []
        for name, dim in self.sensor_dims(system):
            t = sensor_topic(name)
            if t not in sensors.topics:
                have = ", ".join(sorted(sensors.topics)) or "none"
                raise FusionlogError(
                    f"{sensors.path}: no topic {t} for sensor {name!r} of the model "
                    f"(topics: {have})"
                )
            if sensors.kind_of(t) != VALUES or sensors.dim_of(t) != dim:
                raise FusionlogError(
                    f"{sensors.path}: topic {t} has {sensors.dim_of(t)} values per step "
                    f"({sensors.schema_of(t)}), the model's sensor {name!r} has {dim}"
                )
            topics.append(t)
        return topics

    @abstractmethod
    def estimator(
        self,
        system: Any,
        steps: int,
        runs: int,
        archs: list[str],
        sensors: McapFile,
        kept: Any = None,
    ) -> Estimator:
        """An estimator of every run with `archs` (`kept`: a `driver.KeptPlans` that a later
        stage of the same command shares, or None)."""

    @abstractmethod
    def write_evaluation(self, file: BinaryIO, evaluation: Any) -> None:
        """Serialise an `Evaluator.evaluation` as the kind's Rerun recording into ``file``."""

    @abstractmethod
    def evaluator(
        self, sc: Scenario, est: McapFile, prov: Prov, sens: Sens = None, kept: Any = None
    ) -> Evaluator:
        """An evaluator of the estimates against the scenario's truth (`sensors`: the sensors
        file, when the evaluation has it: its structure and per-message covariances; `kept`:
        the estimate stage's `driver.KeptPlans` of the same command, or None)."""
