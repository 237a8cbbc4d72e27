"""What the tests of one replayed run share (`test_replay_fast.py`, `test_exact_replay.py`):
replay_robot's imported log with the filter model on its instants, a cut of it, a random model
with gaps, and the state architectures with SKF on each sensor."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from cli_helpers import ok
from conftest import random_system

from fusionlog.core.architectures import STATE_ARCHITECTURES
from fusionlog.core.simulate import simulate
from fusionlog.io.mcap import McapFile
from fusionlog.stages.common import scenario_from_file
from fusionlog.stages.noise import with_message_covariances

REPLAY = Path(__file__).resolve().parents[1] / "pipeline" / "replay_robot.toml"


def robot_log(directory: Path):
    """replay_robot imported into `directory`: (sensors file, its filter model on its instants
    with its messages' R, its one run z (1, K+1, m))."""
    path = directory / "s.mcap"
    ok("import", REPLAY, "-o", path)
    mf = McapFile(path)
    system = with_message_covariances(scenario_from_file(mf).system.on_times(mf.times()), mf)
    topics = [f"/sensors/{s.name}" for s in system.sensors]
    z = np.concatenate([mf.read_all([t])[t] for t in topics], axis=-1)
    return path, system, z


def head(system, z, K1: int):
    """The log cut to its first K1 instants."""
    cut = dataclasses.replace(system, Fs=system.Fs[: K1 - 1], Qs=system.Qs[: K1 - 1])
    return dataclasses.replace(cut, Rs=system.Rs[:K1]), z[:, :K1]


def gappy():
    """A random model: three sensors of sizes 1, 2, 1, the first two with correlated noise,
    a quarter of the components missing (some instants none, some all); z (1, 151, 4)."""
    system = random_system(np.random.default_rng(3), 3, [1, 2, 1], correlated=True)
    _, z = simulate(system, 150, 4, 0, 1)
    z[np.random.default_rng(8).random(z.shape) < 0.25] = np.nan
    return system, z


def state_archs(system) -> list[str]:
    """Every state architecture, SKF once per sensor."""
    return [a for a in STATE_ARCHITECTURES if a != "SKF"] + [
        f"SKF:{s.name}" for s in system.sensors
    ]
