"""Replaying recorded logs end to end: `fusionlog import` and `run` on pipeline/replay_robot.toml
(a ROS 2 MCAP with zero-covariance odometry and per-message-covariance poses whose header
stamps are out of log order, and a motion-capture CSV with spaced, unit-bearing headers and
nanosecond times), against an independent Kalman filter: FilterPy with the constant-velocity
model discretised exactly over each interval (the closed form of eqs. 41-42) and R per message.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import cli, ok, one_line_error
from filterpy.kalman import KalmanFilter
from mcap.reader import make_reader

from fusionlog.core.model import constant_velocity
from fusionlog.io.mcap import McapFile
from fusionlog.io.replay import read_series
from fusionlog.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]
REPLAY = ROOT / "pipeline" / "replay_robot.toml"


@pytest.fixture(scope="module")
def imported(tmp_path_factory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("replay") / "s.mcap"
    res = ok("import", REPLAY, "-o", out)
    return out, res.stdout


def _streams():
    """Each sensor's readings, read again from the sources (times ns, values, covariances)."""
    sc = load_scenario(REPLAY)
    out = []
    for sen, st in zip(sc.system.sensors, sc.replay.sensors, strict=True):
        s = read_series(st.source, **st.reader_args())
        out.append((sen, s))
    return sc, out


def test_import_writes_one_run_on_the_union_of_measurement_times(imported) -> None:
    path, stdout = imported
    sc, streams = _streams()
    instants = np.unique(np.concatenate([s.times_ns for _, s in streams]))
    f = McapFile(path)
    assert f.runs() == 1 and f.steps() == len(instants)
    np.testing.assert_allclose(f.times(), (instants - instants[0]) / 1e9, rtol=0, atol=1e-9)
    # log_time is the recorded measurement time of each message
    with open(path, "rb") as fh:
        logged = {}
        for _, ch, msg in make_reader(fh).iter_messages():
            logged.setdefault(ch.topic, []).append(msg.log_time)
    for sen, s in streams:
        np.testing.assert_array_equal(logged[f"/sensors/{sen.name}"], s.times_ns)
    # what was counted is reported
    assert "pose: 4 messages out of time order (sorted)" in stdout
    assert "odom: 1350 of 1350 messages with an all-zero" in stdout
    assert "mocap: 2 rows" in stdout
    # the pose messages carry their own covariance; odometry's all-zero ones take R (no field)
    assert f.message_covariances("/sensors/pose") is not None
    assert f.message_covariances("/sensors/odom") is None
    prov = f.metadata["fusionlog.provenance"]
    assert any(k.startswith("source_sha256:") and k.endswith("robot_ros2.mcap") for k in prov)


def _reference_ckf(sc, streams):
    """FilterPy on every instant: predict with the exact discretisation of the interval,
    update with the sensors that measure then, each with its message's R (or its own)."""
    q = sc.system.continuous[1][1, 1]  # white-acceleration density of each axis
    per = {}
    for j, (sen, s) in enumerate(streams):
        for i, t in enumerate(s.times_ns.tolist()):
            R = sen.R
            if s.cov is not None:
                c = s.cov[i]
                usable = np.abs(c).max() > 0 and np.all(np.linalg.eigvalsh(c) > 0)
                R = c if usable else R
            per.setdefault(t, []).append((j, s.values[i], R))
    times = sorted(per)
    kf = KalmanFilter(dim_x=4, dim_z=2)
    kf.x, kf.P = sc.system.prior.mean.copy(), sc.system.prior.cov.copy()
    means, covs = [], []
    for k, t in enumerate(times):
        if k:
            F1, Q1 = constant_velocity((t - times[k - 1]) / 1e9, q)
            kf.predict(F=np.kron(np.eye(2), F1), Q=np.kron(np.eye(2), Q1))
        for j, z, R in per[t]:
            kf.dim_z = 2
            kf.update(z, R=R, H=sc.system.sensors[j].H)
        means.append(kf.x.copy())
        covs.append(kf.P.copy())
    return np.array(means), np.array(covs)


def test_ckf_on_the_replay_equals_an_independent_kalman_filter(imported, tmp_path) -> None:
    path, _ = imported
    sc, streams = _streams()
    # the nominal R of a sensor given only by its messages is their mean: fill it for the test
    est = tmp_path / "e.mcap"
    ok("estimate", path, "-o", est, "--arch", "CKF")
    mean, cov = McapFile(est).read_all(["/estimates/CKF"])["/estimates/CKF"]
    m_ref, P_ref = _reference_ckf(sc, streams)
    np.testing.assert_allclose(mean[0], m_ref, rtol=1e-9, atol=1e-9)
    cov = cov if cov.ndim == 3 else cov[0]
    np.testing.assert_allclose(cov, P_ref, rtol=1e-9, atol=1e-12)


def test_run_reports_truth_metrics_and_nis(tmp_path) -> None:
    out = tmp_path / "run"
    ok("run", REPLAY, "--out-dir", out, "--arch", "CKF", "--arch", "MSC", "--arch", "SKF:mocap")
    summary = json.loads((out / "summary.json").read_text())
    assert summary["runs"] == 1
    for arch in ("CKF", "MSC", "SKF:mocap"):
        a = summary["architectures"][arch]
        assert np.isfinite(a["mse"]) and np.isfinite(a["anees"]), arch
        assert "nis" in a, arch


def test_a_recording_without_truth_is_evaluated_by_its_innovations(tmp_path) -> None:
    """No [truth]: the summary has what needs none (NIS per architecture and sensor; the trace
    of P), the recording its NIS views and bands."""
    from fusionlog.io.rrd import read_recording

    text = REPLAY.read_text().split("[truth]")[0]
    text += '\n[estimate]\narchitectures = ["CKF", "MSC", "MSC-GMF"]\n'
    text = text.replace('"data/', f'"{ROOT / "pipeline" / "data"}/')
    replay = tmp_path / "no_truth.toml"
    replay.write_text(text)
    out = tmp_path / "run"
    res = ok("run", replay, "--out-dir", out)
    assert "CKF" in res.stdout
    summary = json.loads((out / "summary.json").read_text())
    ckf, msc = summary["architectures"]["CKF"], summary["architectures"]["MSC"]
    assert "mse" not in ckf and ckf["mean_trace"] > 0
    assert set(ckf["nis"]) == set(msc["nis"]) == {"odom", "pose", "mocap"}
    for name, entry in ckf["nis"].items():
        assert set(entry) >= {"mean", "fraction_inside", "dof", "whiteness_fraction_inside"}
        # consistent data and model: each sensor's NIS is about its degrees of freedom
        assert 0.7 < entry["mean"] / entry["dof"] < 1.3, (name, entry)
    rec = read_recording(out / "evaluation.rrd")
    assert rec is not None


def test_simulate_refuses_a_replay_file_and_writes_nothing(tmp_path) -> None:
    """A replay's sensors are recordings: `simulate` once wrote a log of noise drawn from the
    replay's model (exit 0) or failed with an overflow at step 0; it names the file instead."""
    res = cli("simulate", REPLAY, "-o", tmp_path / "s.mcap")
    one_line_error(res, str(REPLAY), "replay file", "fusionlog import")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "flags", [["--runs", "5"], ["--steps", "3"], ["--seed", "1", "--runs", "2"]]
)
def test_run_refuses_monte_carlo_flags_on_a_replay(tmp_path, flags) -> None:
    """A replay is one recorded run on its measurement times (DESIGN.md "Replay files"):
    --runs/--steps/--seed were silently ignored; now they are bad usage naming the file."""
    res = cli("run", REPLAY, "--out-dir", tmp_path / "o", *flags)
    line = one_line_error(res, str(REPLAY), "replay file")
    assert all(f in line for f in flags if f.startswith("--"))
    assert not (tmp_path / "o").exists()
