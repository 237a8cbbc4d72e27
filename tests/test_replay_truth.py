"""A replay's truth and what the evaluation says (DESIGN.md, "Recorded logs, more formats";
summary.json): truth sampled at other times (nearest, interpolated), partial truth (metrics over
the truthed states, NEES on their marginal), `truth: {states, matched, unmatched}`,
`mean_trace` as the mean of the traces in estimates.mcap, and the truth-free output (NIS per
architecture and sensor, no warning, no seed line).

The hand computations read the instants from the sensors file's log times, the truth from its
text with decimal arithmetic, and the estimates from estimates.mcap.
"""

from __future__ import annotations

import json
import warnings
from decimal import Decimal
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import ok
from mcap.reader import make_reader

from fusionlog.io.mcap import McapFile

ROOT = Path(__file__).resolve().parents[1]
PIPELINE = ROOT / "pipeline"


def _instants(sensors: Path) -> np.ndarray:
    """The measurement times (ns) of every sensor message: the replay's instants."""
    with open(sensors, "rb") as f:
        t = [m.log_time for _, ch, m in make_reader(f).iter_messages() if ch.topic != "/truth"]
    return np.unique(np.array(t, dtype=np.int64))


def _rows(path: Path, sep: str | None, skip_header: bool) -> tuple[np.ndarray, np.ndarray]:
    lines = [ln for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    lines = lines[1:] if skip_header else lines
    t = np.array([int(Decimal(ln.split(sep)[0]) * 10**9) for ln in lines], dtype=np.int64)
    v = np.array([[float(x) for x in ln.split(sep)[1:]] for ln in lines])
    return t, v


def _run(tmp: Path, toml: Path, *archs: str) -> tuple[Path, dict]:
    out = tmp / "run"
    args = [a for arch in archs for a in ("--arch", arch)]
    ok("run", toml, "--out-dir", out, *args)
    return out, json.loads((out / "summary.json").read_text())


def _metrics(err: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, float]:
    """mse per state (eq. 44-45 with one run: mean over the instants) and the ANEES."""
    nees = np.einsum("ki,kij,kj->k", err, np.linalg.inv(P), err)
    return (err**2).mean(axis=0), float(nees.mean())


@pytest.fixture(scope="module")
def gps_run(tmp_path_factory) -> tuple[Path, dict]:
    return _run(tmp_path_factory.mktemp("gps"), PIPELINE / "replay_gps_ros1.toml", "CKF", "MSC")


def test_truth_mse_nearest_equals_a_hand_computation(gps_run) -> None:
    out, summary = gps_run
    instants = _instants(out / "sensors.mcap")
    t, v = _rows(PIPELINE / "data" / "gps_truth.tsv", "\t", skip_header=True)
    # nearest within 10 ms, a tie to the earlier sample: by hand, instant by instant
    truth = np.full((len(instants), 4), np.nan)
    for k, tk in enumerate(instants.tolist()):
        d = np.abs(t - tk)
        j = int(np.argmin(d))  # argmin: the first (earlier) of equal distances
        if d[j] <= 10_000_000:
            truth[k] = v[j]  # columns east, north, v_east, v_north -> states e, ve, n, vn
    truth = truth[:, [0, 2, 1, 3]]
    have = np.isfinite(truth).all(axis=1)
    states = ["east", "v_east", "north", "v_north"]
    assert summary["truth"] == {"states": states, "matched": int(have.sum()),
                                "unmatched": int((~have).sum())}  # fmt: skip
    for arch in ("CKF", "MSC"):
        mean, cov = McapFile(out / "estimates.mcap").read_all([f"/estimates/{arch}"])[
            f"/estimates/{arch}"
        ]
        cov = cov if cov.ndim == 3 else cov[0]
        mse, anees = _metrics((truth - mean[0])[have], cov[have])
        a = summary["architectures"][arch]
        np.testing.assert_allclose(a["mse_per_state"], mse, rtol=1e-9)
        np.testing.assert_allclose(a["mse"], mse.mean(), rtol=1e-9)
        np.testing.assert_allclose(a["anees"], anees, rtol=1e-9)
        # mean_trace: the mean over the instants of the traces in estimates.mcap
        np.testing.assert_allclose(a["mean_trace"], np.trace(cov, axis1=1, axis2=2).mean(),
                                   rtol=1e-12)  # fmt: skip


def test_partial_interpolated_truth_equals_a_hand_computation(tmp_path: Path) -> None:
    """replay_tum.toml: motion-capture positions only (x, y, z of six states), interpolated."""
    out, summary = _run(tmp_path, PIPELINE / "replay_tum.toml", "CKF")
    instants = _instants(out / "sensors.mcap")
    t, v = _rows(PIPELINE / "data" / "tum_mocap.txt", None, skip_header=False)
    pos = v[:, :3]
    truth = np.full((len(instants), 3), np.nan)
    for k, tk in enumerate(instants.tolist()):
        hi = int(np.searchsorted(t, tk))
        if hi < len(t) and t[hi] == tk:
            truth[k] = pos[hi]
        elif 0 < hi < len(t) and tk - t[hi - 1] <= 20_000_000 and t[hi] - tk <= 20_000_000:
            w = (tk - t[hi - 1]) / (t[hi] - t[hi - 1])
            truth[k] = pos[hi - 1] * (1 - w) + pos[hi] * w
    have = np.isfinite(truth).all(axis=1)
    assert summary["truth"] == {"states": ["x", "y", "z"], "matched": int(have.sum()),
                                "unmatched": int((~have).sum())}  # fmt: skip
    mean, cov = McapFile(out / "estimates.mcap").read_all(["/estimates/CKF"])["/estimates/CKF"]
    cov = cov if cov.ndim == 3 else cov[0]
    idx = [0, 2, 4]
    mse, anees = _metrics((truth - mean[0][:, idx])[have], cov[have][:, idx][:, :, idx])
    a = summary["architectures"]["CKF"]
    assert a["mse_per_state"][1] is None and a["mse_per_state"][3] is None  # not truthed
    np.testing.assert_allclose([a["mse_per_state"][i] for i in idx], mse, rtol=1e-9)
    np.testing.assert_allclose(a["mse"], mse.mean(), rtol=1e-9)
    np.testing.assert_allclose(a["anees"], anees, rtol=1e-9)  # on the 3-state marginal
    assert 2.0 < a["anees"] < 4.0  # about its 3 degrees of freedom, not 6
    np.testing.assert_allclose(a["mean_trace"], np.trace(cov, axis1=1, axis2=2).mean(), rtol=1e-12)


def test_a_truth_free_replay_has_nis_per_sensor_no_warning_no_seed(tmp_path: Path) -> None:
    text = (PIPELINE / "replay_robot.toml").read_text().split("[truth]")[0]
    text = text.replace('"data/', f'"{PIPELINE / "data"}/')
    text += '\n[estimate]\narchitectures = ["CKF", "HKF", "MSC", "SKF:mocap", "FBS"]\n'
    replay = tmp_path / "no_truth.toml"
    replay.write_text(text)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # "Mean of empty slice" and the like fail the test
        res = ok("run", replay, "--out-dir", tmp_path / "run")
    assert "seed" not in res.stdout and "one recorded log" in res.stdout
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert "truth" not in summary
    out = res.stdout.splitlines()
    head = next(i for i, ln in enumerate(out) if ln.startswith("architecture"))
    assert out[head].split()[:3] == ["architecture", "sensor", "NIS"]
    for arch in ("CKF", "HKF", "MSC", "FBS"):
        nis = summary["architectures"][arch]["nis"]
        assert set(nis) == {"odom", "pose", "mocap"}, arch
        row = next(ln for ln in out if ln.startswith(arch + " "))
        assert f"{nis['odom']['mean']:.4f}" in row and "%" in row
    # estimates.mcap's traces, averaged over the instants
    est = McapFile(tmp_path / "run" / "estimates.mcap")
    _, cov = est.read_all(["/estimates/CKF"])["/estimates/CKF"]
    cov = cov if cov.ndim == 3 else cov[0]
    np.testing.assert_allclose(summary["architectures"]["CKF"]["mean_trace"],
                               np.trace(cov, axis1=1, axis2=2).mean(), rtol=1e-12)  # fmt: skip


def test_the_api_gives_the_partial_truth_metrics_of_the_cli(tmp_path: Path) -> None:
    import fusionlog as fl

    _, summary = _run(tmp_path, PIPELINE / "replay_tum.toml", "CKF")
    sc = fl.load(PIPELINE / "replay_tum.toml")
    sim = fl.simulate(sc)
    ev = fl.evaluate(sc, sim, fl.estimate(sc, sim, ["CKF"]))
    assert ev.summary["truth"] == summary["truth"]
    for key in ("mse", "anees", "mean_trace"):
        np.testing.assert_allclose(ev.summary["architectures"]["CKF"][key],
                                   summary["architectures"]["CKF"][key], rtol=1e-12)  # fmt: skip
