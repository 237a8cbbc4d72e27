"""The Python API (`import fusionlog as fl`, DESIGN.md "Python API"): the CLI's numbers for the
same scenario, runs and seed, nothing written unless asked, and the README's example."""

from __future__ import annotations

import dataclasses
import json
import os
import re
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import ok

import fusionlog as fl
from fusionlog.io.mcap import McapFile
from fusionlog.io.rrd import read_recording

ROOT = Path(__file__).resolve().parent.parent

#: (scenario, runs, steps, seed): the paper's example (shared gains), dropouts (per-run
#: patterns, conditional expected values) and several rates (a shared pattern with gaps,
#: irregular instants, sensor availability).
CASES = [
    ("tests/golden/small.toml", 300, None, 5),
    ("pipeline/ajgl2009_dropout.toml", 200, 12, 2),
    ("pipeline/multirate.toml", 150, 8, 4),
    ("pipeline/replay_robot.toml", None, None, None),  # a recorded log: per-message R, NIS
]

#: Per entry, both sides sum the same numbers in the same blocks; what can differ is the
#: summation order inside BLAS kernels over the runs (a few ulps of each partial sum), so
#: relative agreement to 1e-12 is many orders above it.
RTOL = 1e-12


def _close(a, b, what: str) -> None:
    if a is None or b is None:
        assert a is b, what
        return
    np.testing.assert_allclose(a, b, rtol=RTOL, atol=0, err_msg=what)


def _leaves(d: dict, at: str = "") -> dict[str, float]:
    """The numbers of a nested summary entry by their key path."""
    out: dict[str, float] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out |= _leaves(v, f"{at}{k}.")
        else:
            out[at + k] = v
    return out


@pytest.mark.parametrize(("path", "runs", "steps", "seed"), CASES)
def test_api_gives_the_cli_numbers_and_writes_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, path: str, runs: int, steps, seed: int
) -> None:
    out = tmp_path / "cli"
    args = [] if runs is None else ["--runs", runs, "--seed", seed]
    args += [] if steps is None else ["--steps", steps]
    ok("run", ROOT / path, "--out-dir", out, *args)
    cli_summary = json.loads((out / "summary.json").read_text())

    work = tmp_path / "api"
    work.mkdir()
    monkeypatch.chdir(work)
    sc = fl.load(ROOT / path)
    sim = fl.simulate(sc, runs=runs, seed=seed, steps=steps)
    est = fl.estimate(sc, sim)
    ev = fl.evaluate(sc, sim, est)
    assert list(work.iterdir()) == []  # nothing touched the disk

    assert (ev.summary["runs"], ev.summary["seed"]) == (cli_summary["runs"], cli_summary["seed"])
    assert list(ev.summary["architectures"]) == list(cli_summary["architectures"])
    for a, mine in ev.summary["architectures"].items():
        theirs = cli_summary["architectures"][a]
        assert mine.keys() == theirs.keys()
        for key in ("mse", "anees", "dm", "mean_trace"):
            _close(mine.get(key), theirs.get(key), f"{path} {a} {key}")
        if "expected" in theirs:
            for key in ("mse", "anees", "dm"):
                _close(mine["expected"][key], theirs["expected"][key], f"{a} expected {key}")
            assert mine["expected"].get("conditional") == theirs["expected"].get("conditional")
        if "nis" in theirs:  # truth-free consistency of a recorded log (per sensor, or one)
            assert _leaves(mine["nis"]).keys() == _leaves(theirs["nis"]).keys()
            for k, v in _leaves(theirs["nis"]).items():
                _close(_leaves(mine["nis"])[k], v, f"{a} nis {k}")

    ckf = McapFile(out / "estimates.mcap")
    for off, n, data in ckf.iter_run_blocks(["/estimates/CKF"], sim.runs):
        mean, cov = data["/estimates/CKF"]
        np.testing.assert_allclose(est["CKF"].mean[off : off + n], mean, rtol=RTOL, atol=1e-12)
        api_cov = est["CKF"].cov[off : off + n]  # (runs, K+1, n, n) whether shared or not
        assert est["CKF"].shared_cov == (cov.ndim == 3)  # the file's n x n per message
        np.testing.assert_allclose(api_cov, np.broadcast_to(cov, api_cov.shape), rtol=RTOL,
                                   atol=1e-12)  # fmt: skip


def test_shapes_and_units(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    sc = fl.load(ROOT / "pipeline/ajgl2009.toml")
    sim = fl.simulate(sc, runs=7, seed=1, steps=5)
    assert sim.times.shape == (6,) and sim.truth.shape == (7, 6, 2)
    assert {k: v.shape for k, v in sim.measurements.items()} == {
        s.name: (7, 6, 1) for s in sc.system.sensors
    }
    est = fl.estimate(sc, sim, ["CKF", "SKF:s2"])
    assert list(est) == ["CKF", "SKF:s2"]
    assert est["CKF"].mean.shape == (7, 6, 2) and est["CKF"].cov.shape == (7, 6, 2, 2)
    with pytest.raises(fl.api.FusionlogError, match="unknown architecture 'XKF'"):
        fl.estimate(sc, sim, ["XKF"])
    assert list(tmp_path.iterdir()) == []


def test_another_model_for_the_filters(tmp_path: Path) -> None:
    """`estimate` / `evaluate` with a model other than the truth's (as `fusionlog estimate
    --model`): its sensors taken by name, the expected values of the mismatched filter."""
    sc = fl.load(ROOT / "tests/golden/small.toml")
    sim = fl.simulate(sc, runs=50, seed=2)
    one = dataclasses.replace(sc, system=sc.system.subset([1]))  # the filters see s2 only
    est = fl.estimate(one, sim, ["CKF"])
    alone = fl.estimate(sc, sim, ["SKF:s2"])
    np.testing.assert_allclose(est["CKF"].mean, alone["SKF:s2"].mean, rtol=1e-13, atol=1e-13)
    ev = fl.evaluate(one, sim, est)
    assert ev.summary["architectures"]["CKF"]["expected"]["mse"] is not None


def test_save_writes_the_recording_only_when_asked(tmp_path: Path) -> None:
    sc = fl.load(ROOT / "tests/golden/small.toml")
    sim = fl.simulate(sc, runs=20, seed=1)
    ev = fl.evaluate(sc, sim, fl.estimate(sc, sim, ["CKF", "MSC"]))
    assert "CKF" in ev.table() and ev.architectures == ["CKF", "MSC"]
    target = ev.save(tmp_path / "evaluation.rrd")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["evaluation.rrd"]
    assert read_recording(target)["summary"]["architectures"].keys() == {"CKF", "MSC"}
    with pytest.raises(fl.api.FusionlogError):
        ev.save(target)  # no overwrite without force
    ev.save(target, force=True)


def test_readme_example_runs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The README's "Python API" example, as written there, in a scratch folder."""
    text = (ROOT / "README.md").read_text()
    section = text.split("## Python API", 1)[1].split("\n## ", 1)[0]
    code = re.search(r"```python\n(.*?)```", section, re.S)
    assert code is not None, "README: no python block in the Python API section"
    monkeypatch.chdir(tmp_path)
    os.symlink(ROOT / "pipeline", tmp_path / "pipeline")
    shown: list[str] = []
    exec(compile(code.group(1), "README.md", "exec"), {"print": lambda *a: shown.append(repr(a))})
    assert (tmp_path / "evaluation.rrd").exists()
    # the shapes its comment states
    assert shown[0] == repr(((200, 21, 2), (200, 21, 2, 2))), shown[0]


def test_bad_arguments_raise_the_documented_errors(tmp_path: Path) -> None:
    """Bad arguments are `fl.FusionlogError`s (`fl.ValidationError` for the scenario's
    numbers) with a clear message; mismatched simulations and estimates were numpy's
    ValueError (shapes that do not broadcast) deep inside the evaluator."""
    path = ROOT / "tests/golden/small.toml"
    sc = fl.load(path)
    for kwargs, match in (({"runs": 0}, " runs: must be >= 1"), ({"seed": -1}, " seed: ")):
        with pytest.raises(fl.ValidationError, match=match):
            fl.simulate(sc, **kwargs)
    sim = fl.simulate(sc, runs=4, seed=1, steps=3)
    est = fl.estimate(sc, sim, ["CKF"])
    for other in (fl.simulate(sc, runs=5, seed=1, steps=3), fl.simulate(sc, runs=4, steps=4)):
        with pytest.raises(fl.FusionlogError, match="not of this simulation's"):
            fl.evaluate(sc, other, est)
    with pytest.raises(fl.FusionlogError, match="estimates: empty"):
        fl.evaluate(sc, sim, fl.Estimates())
    identity = ROOT / "pipeline/aircraft_identity.toml"
    for call in (lambda: fl.simulate(identity), lambda: fl.estimate(identity, sim)):
        with pytest.raises(fl.FusionlogError, match="state scenarios"):
            call()
    replay = ROOT / "pipeline/replay_robot.toml"
    with pytest.raises(fl.FusionlogError, match="replay file is one recorded run.*runs=, seed="):
        fl.simulate(replay, runs=10, seed=3)  # it returned the one recorded run
    with pytest.raises(fl.ValidationError, match="scenario: expected a scenario"):
        fl.estimate(None, sim)  # type: ignore[arg-type]
    assert issubclass(fl.ValidationError, fl.FusionlogError)


def test_a_path_and_one_name_are_taken_as_they_read(tmp_path: Path) -> None:
    """`estimate` and `evaluate` take the scenario's path as `simulate` does, and one
    architecture as a string ("CKF" was read as the unknown architectures C, K, F)."""
    path = ROOT / "tests/golden/small.toml"
    sim = fl.simulate(path, runs=6, seed=2, steps=4)
    est = fl.estimate(str(path), sim, "CKF")
    assert list(est) == ["CKF"]
    ev = fl.evaluate(path, sim, est)
    sc = fl.load(path)
    want = fl.evaluate(sc, sim, fl.estimate(sc, sim, ["CKF"])).summary
    assert ev.summary["architectures"] == want["architectures"]


def test_filter_overrides_the_local_filter_as_on_the_cli(tmp_path: Path) -> None:
    """`fl.estimate(..., filter="EKF")` is `fusionlog run --filter EKF` (the turn scenario
    says UKF): the same summary; without it the scenario's UKF, which differs."""
    path = ROOT / "pipeline/coordinated_turn.toml"
    ok("run", path, "--out-dir", tmp_path, "--runs", "20", "--steps", "6", "--seed", "3",
       "--filter", "EKF", "--arch", "CKF", "--arch", "MSC")  # fmt: skip
    cli_summary = json.loads((tmp_path / "summary.json").read_text())
    sc = fl.load(path)
    sim = fl.simulate(sc, runs=20, seed=3, steps=6)
    ev = fl.evaluate(sc, sim, fl.estimate(sc, sim, ["CKF", "MSC"], filter="EKF"))
    ukf = fl.evaluate(sc, sim, fl.estimate(sc, sim, ["CKF", "MSC"]))
    for a in ("CKF", "MSC"):
        theirs = cli_summary["architectures"][a]
        for key in ("mse", "anees", "dm"):
            _close(ev.summary["architectures"][a][key], theirs[key], f"{a} {key}")
        assert ukf.summary["architectures"][a]["mse"] != pytest.approx(theirs["mse"], rel=1e-6)
    with pytest.raises(fl.FusionlogError, match="unknown filter 'PF'"):
        fl.estimate(sc, sim, ["CKF"], filter="PF")
