"""Real timing: sensors at their own rates and offsets, dropouts, irregular instants.

Independent references: the constant-velocity closed form (eqs. 41-42) for Van Loan's
discretisation, a plain FilterPy loop with each interval's F and Q and only the sensors that
measure, the exact covariance analysis against Monte Carlo (within 4 standard errors), the
plain `mcap` reader for what the files hold. Scenario errors are one line naming the key.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import cli, ok
from filterpy.kalman import KalmanFilter

from fusionlog.core.architectures import estimate
from fusionlog.core.model import constant_velocity
from fusionlog.core.simulate import simulate
from fusionlog.core.timing import SensorTiming, schedule, van_loan
from fusionlog.errors import ValidationError
from fusionlog.io.mcap import McapFile
from fusionlog.scenario import load_scenario, scenario_from_text

ROOT = Path(__file__).resolve().parents[1]
MULTIRATE = ROOT / "pipeline" / "multirate.toml"
DROPOUT = ROOT / "pipeline" / "ajgl2009_dropout.toml"
AJGL = ROOT / "pipeline" / "ajgl2009.toml"


# ------------------------------------------------------------------------------------------
# schedules and discretisation


def test_multiples_of_dt_keep_the_grid() -> None:
    sched = schedule(0.5, 8, (SensorTiming(), SensorTiming(1.0, 0.5), SensorTiming(2.0)))
    assert sched.regular
    np.testing.assert_array_equal(sched.times, np.arange(9) * 0.5)
    assert sched.measures[:, 0].all()
    np.testing.assert_array_equal(np.flatnonzero(sched.measures[:, 1]), [1, 3, 5, 7])
    np.testing.assert_array_equal(np.flatnonzero(sched.measures[:, 2]), [0, 4, 8])


def test_irregular_instants_are_the_union_of_sampling_times() -> None:
    sched = schedule(0.1, 10, (SensorTiming(0.2, 0.05), SensorTiming(0.3)))
    assert not sched.regular
    want = sorted({0.0, *np.round(0.05 + 0.2 * np.arange(5), 9), *np.round(0.3 * np.arange(4), 9)})
    np.testing.assert_allclose(sched.times, want, atol=1e-12)
    assert (sched.measures.sum(axis=0) == [5, 4]).all()
    assert not sched.measures[0, 0] and sched.measures[0, 1]  # t = 0: only the second


@pytest.mark.parametrize("delta", [0.01, 0.37, 1.0, 12.5])
def test_van_loan_gives_the_constant_velocity_closed_form(delta: float) -> None:
    q = 0.7
    F, Q = van_loan(np.array([[0.0, 1.0], [0.0, 0.0]]), np.diag([0.0, q]), delta)
    F_ref, Q_ref = constant_velocity(delta, q)
    np.testing.assert_allclose(F, F_ref, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(Q, Q_ref, rtol=1e-10, atol=1e-15)


def test_the_system_on_regular_instants_is_itself_bit_for_bit() -> None:
    sc = load_scenario(AJGL)
    assert sc.system.on_times(sc.times) is sc.system


# ------------------------------------------------------------------------------------------
# scenario validation

BASE = """
[scenario]
name = "t"
steps = 10
runs = 5
seed = 1
dt = 0.1

[model]
kind = "constant-velocity"
n0 = 1.0

[prior]
mean = [0.0, 0.0]
cov = [[1.0, 0.0], [0.0, 1.0]]

[[sensors]]
name = "a"
H = [[1.0, 0.0]]
R = 1.0
TIMING
"""


@pytest.mark.parametrize(
    "timing, key, reason",
    [
        ("period = 0.0", "sensors[0].period", "must be > 0"),
        ("period = -1.0", "sensors[0].period", "must be > 0"),
        ("offset = -0.1", "sensors[0].offset", "must be >= 0"),
        ("period = 0.2\noffset = 0.2", "sensors[0].offset", "must be < period"),
        ("dropout = 1.0", "sensors[0].dropout", "must be in [0, 1)"),
        ("dropout = -0.1", "sensors[0].dropout", "must be in [0, 1)"),
        ("period = 5.0\noffset = 2.0", "sensors[0].offset", "never measures within [0, 1] s"),
        ("period = '1'", "sensors[0].period", "number"),
    ],
)
def test_bad_timing_is_one_line(timing: str, key: str, reason: str) -> None:
    with pytest.raises(ValidationError) as e:
        scenario_from_text(BASE.replace("TIMING", timing), "bad.toml")
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"bad.toml: {key}: "), msg
    assert reason in msg, msg


def test_irregular_instants_need_a_continuous_model() -> None:
    text = BASE.replace("TIMING", "period = 0.25").replace(
        'kind = "constant-velocity"\nn0 = 1.0',
        "F = [[1.0, 0.1], [0.0, 1.0]]\nQ = [[0.01, 0.0], [0.0, 0.01]]",
    )
    with pytest.raises(ValidationError, match=r"^bad.toml: model.F: explicit F, Q hold for dt"):
        scenario_from_text(text, "bad.toml")
    # with multiples of dt the explicit model is fine
    scenario_from_text(text.replace("period = 0.25", "period = 0.2"), "ok.toml")


def test_a_filter_model_for_irregular_instants_needs_a_continuous_model(tmp_path: Path) -> None:
    """`estimate --model` (and the API's estimate with another model) on a log whose instants
    are irregular: an explicit F, Q (for dt only) is refused as the scenario itself would be;
    it used to be applied between every two instants, 50 ms or 100 ms apart alike."""
    import fusionlog as fl
    from fusionlog.errors import FusionlogError

    text = MULTIRATE.read_text()
    cv = 'kind = "constant-velocity"\naxes = 2'
    assert cv in text
    F = np.kron(np.eye(2), [[1.0, 0.1], [0.0, 1.0]]).tolist()
    Q = np.kron(np.eye(2), [[0.001, 0.01], [0.01, 0.2]]).tolist()
    explicit = text.replace(cv, f"F = {F}\nQ = {Q}\n#").replace("n0 = 2.0", "# n0")
    for timing in ("period = 1.0\n", "period = 0.2\noffset = 0.05\n", "period = 0.1\n"):
        explicit = explicit.replace(timing, "", 1)  # the model file alone loads
    model = tmp_path / "model.toml"
    model.write_text(explicit)
    log = tmp_path / "s.mcap"
    ok("simulate", MULTIRATE, "-o", log, "--runs", "5", "--steps", "10")
    res = cli("estimate", log, "-o", tmp_path / "e.mcap", "--model", model)
    assert res.exit_code == 2 and len(res.stderr.splitlines()) == 1, res.output
    assert f"{model}: model.F: explicit F, Q hold for dt only" in res.stderr
    assert f"{log} are irregular" in res.stderr and not (tmp_path / "e.mcap").exists()
    sim = fl.simulate(fl.load(MULTIRATE), runs=5, steps=10)
    with pytest.raises(FusionlogError, match="model.F: explicit F, Q hold for dt only"):
        fl.estimate(fl.load(model), sim, ["CKF"])
    # a constant-velocity model (another n0) is discretised on each interval: fine
    other = tmp_path / "cv.toml"
    other.write_text(text.replace("n0 = 2.0", "n0 = 0.5"))
    ok("estimate", log, "-o", tmp_path / "e.mcap", "--model", other, "--arch", "CKF")
    assert fl.estimate(fl.load(other), sim, ["CKF"])["CKF"].mean.shape == (5, 16, 4)
    # on the grid of dt (the paper's scenario), an explicit model stays a model mismatch
    ajgl = tmp_path / "a.mcap"
    ok("simulate", AJGL, "-o", ajgl, "--runs", "5", "--steps", "4")
    fq = AJGL.read_text().replace('kind = "constant-velocity"', "F = [[1.0, 1.0], [0.0, 1.0]]")
    (tmp_path / "fq.toml").write_text(fq.replace("n0 = 0.16", "Q = [[0.1, 0.0], [0.0, 0.1]]"))
    ok("estimate", ajgl, "-o", tmp_path / "f.mcap", "--model", tmp_path / "fq.toml")


def test_steps_override_rechecks_the_timing(tmp_path: Path) -> None:
    path = tmp_path / "s.toml"
    path.write_text(BASE.replace("TIMING", "period = 0.5\noffset = 0.4"))
    res = cli("simulate", path, "-o", tmp_path / "s.mcap", "--steps", "2")
    assert res.exit_code == 2 and "never measures" in res.stderr, res.output
    assert len(res.stderr.splitlines()) == 1


def test_continuous_model_and_axes() -> None:
    text = BASE.replace("TIMING", "").replace(
        'kind = "constant-velocity"\nn0 = 1.0',
        'kind = "continuous"\nA = [[0.0, 1.0], [0.0, 0.0]]\nQc = [[0.0, 0.0], [0.0, 0.1]]',
    )
    sc = scenario_from_text(text)
    F, Q = constant_velocity(0.1, 0.1)
    np.testing.assert_allclose(sc.system.F, F, atol=1e-15)
    np.testing.assert_allclose(sc.system.Q, Q, rtol=1e-10)
    sc = load_scenario(MULTIRATE)
    assert sc.system.n == 4 and sc.state_names == ("x", "vx", "y", "vy")


# ------------------------------------------------------------------------------------------
# simulation: schedule and dropouts


def test_dropouts_are_deterministic_whatever_the_block() -> None:
    sc = load_scenario(DROPOUT)
    system = sc.system
    _, z = simulate(system, 20, 7, 0, 3000)
    _, part = simulate(system, 20, 7, 1000, 777)
    np.testing.assert_array_equal(z[1000:1777], part)
    lost = np.isnan(z).mean()
    assert abs(lost - 0.1) < 4 * np.sqrt(0.1 * 0.9 / z.size)
    # a scenario without dropout keys draws nothing more: the same numbers as the paper's
    _, z0 = simulate(load_scenario(AJGL).system, 20, 7, 0, 50)
    assert not np.isnan(z0).any()
    np.testing.assert_array_equal(np.where(np.isnan(z[:50]), z0, z[:50]), z0)


# ------------------------------------------------------------------------------------------
# the shared path on irregular instants against FilterPy


def _filterpy_multirate(system, measures, z):
    """CKF by FilterPy: at instant k, predict with that interval's F and Q, then update with the
    stacked rows of the sensors that measure (their block of R, cross-covariances included)."""
    n = system.n
    out_x, out_P = [], []
    for run in z:
        kf = KalmanFilter(dim_x=n, dim_z=system.m)
        kf.x, kf.P = system.prior.mean.copy(), system.prior.cov.copy()
        xs, Ps = [], []
        for k in range(len(measures)):
            if k > 0:
                kf.predict(F=system.F_at(k), Q=system.GQG_at(k))
            rows = np.concatenate(
                [
                    np.arange(system.m)[sl]
                    for j, sl in enumerate(system.sensor_slices)
                    if measures[k, j]
                ]  # fmt: skip
            ).astype(int)
            if len(rows):
                kf.dim_z = len(rows)  # the sensors that measure now
                kf.update(run[k, rows], R=system.R[np.ix_(rows, rows)], H=system.H[rows])
            xs.append(kf.x.copy())
            Ps.append(kf.P.copy())
        out_x.append(xs)
        out_P.append(Ps)
    return np.array(out_x), np.array(out_P)


def test_multirate_ckf_matches_filterpy_on_irregular_instants() -> None:
    sc = load_scenario(MULTIRATE, steps=30)
    sched = sc.schedule
    system = sc.system.on_times(sched.times)
    assert not system.time_invariant and len(np.unique(np.diff(sched.times).round(9))) > 1
    _, z = simulate(system, sched.steps, 3, 0, 4, sched.measures)
    est = estimate(system, z, "CKF")
    x_ref, P_ref = _filterpy_multirate(system, sched.measures, z)
    np.testing.assert_allclose(est.mean, x_ref, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(est.cov, P_ref[0], rtol=1e-9, atol=1e-12)


# ------------------------------------------------------------------------------------------
# end to end: files, inspect, exact vs Monte Carlo


@pytest.fixture(scope="module")
def multirate_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("mr") / "out"
    archs = sum([["--arch", a] for a in ("CKF", "HKF", "MSC-GMF", "MSC", "FBS")], [])
    ok("run", MULTIRATE, "--out-dir", out, "--runs", "1500", "--steps", "40", *archs)
    return out


def test_sensor_topics_have_messages_at_their_instants_only(multirate_run: Path) -> None:
    from mcap.reader import make_reader

    sc = load_scenario(MULTIRATE, steps=40)
    counts: dict[str, int] = {}
    times: dict[str, list[int]] = {}
    with open(multirate_run / "sensors.mcap", "rb") as f:
        for _, channel, message in make_reader(f).iter_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            times.setdefault(channel.topic, []).append(message.log_time)
    sched = sc.schedule
    assert counts["/truth"] == len(sched.times)
    for j, s in enumerate(sc.system.sensors):
        at = sched.measures[:, j]
        assert counts[f"/sensors/{s.name}"] == at.sum()
        np.testing.assert_array_equal(
            times[f"/sensors/{s.name}"], np.rint(sched.times[at] * 1e9).astype(np.int64)
        )
    f = McapFile(multirate_run / "sensors.mcap")
    data = f.read_all(["/sensors/radar"])["/sensors/radar"]
    at = sched.measures[:, 0]
    assert np.isnan(data[:, ~at]).all() and np.isfinite(data[:, at]).all()


def test_inspect_shows_rates_and_lost_share(multirate_run: Path, tmp_path: Path) -> None:
    res = ok("inspect", multirate_run / "sensors.mcap")
    lines = res.stdout.splitlines()
    rate = {ln.split()[0]: lines[i + 1] for i, ln in enumerate(lines) if "/sensors/" in ln}
    assert "(1 Hz), 0.0 % lost" in rate["/sensors/radar"]
    assert "(5 Hz), 0.0 % lost" in rate["/sensors/gnss"]
    assert "(10 Hz), 0.0 % lost" in rate["/sensors/odometer"]
    ok("simulate", DROPOUT, "-o", tmp_path / "d.mcap", "--runs", "2000")
    res = ok("inspect", tmp_path / "d.mcap")
    shares = [float(ln.split(", ")[-1].split(" %")[0]) for ln in res.stdout.splitlines()
              if "% lost" in ln]  # fmt: skip
    assert len(shares) == 3 and all(abs(s - 10.0) < 1.0 for s in shares), shares


def test_multirate_exact_agrees_with_monte_carlo(multirate_run: Path) -> None:
    """A deterministic multi-rate pattern: the unconditional exact values, within 4 SE."""
    summary = json.loads((multirate_run / "summary.json").read_text())
    for arch, a in summary["architectures"].items():
        ex, se = a["expected"], a["stderr"]
        assert ex["mse"] is not None, arch
        assert abs(a["mse"] - ex["mse"]) < 4 * se["mse"], (arch, a["mse"], ex["mse"], se["mse"])
        assert abs(a["anees"] - ex["anees"]) < 4 * se["anees"], arch
    # the consistent filters: expected ANEES = n = 4
    for arch in ("CKF", "MSC-GMF", "FBS"):
        assert summary["architectures"][arch]["expected"]["anees"] == pytest.approx(4.0, 1e-9)


def test_estimates_are_at_every_instant_on_the_real_times(multirate_run: Path) -> None:
    est = McapFile(multirate_run / "estimates.mcap")
    sens = McapFile(multirate_run / "sensors.mcap")
    np.testing.assert_array_equal(est.times(), sens.times())
    assert all(c == len(sens.times()) for c in est.topics.values())


def test_scenario_without_timing_keys_writes_what_it_always_wrote(tmp_path: Path) -> None:
    ok("simulate", AJGL, "-o", tmp_path / "s.mcap", "--runs", "10")
    f = McapFile(tmp_path / "s.mcap")
    assert set(f.topics.values()) == {21}
    assert "sparse" not in f.metadata["fusionlog.layout"]


def test_dropout_scenario_is_the_papers_example_with_dropouts() -> None:
    sc, paper = load_scenario(DROPOUT), load_scenario(AJGL)
    assert [s.timing.dropout for s in sc.system.sensors] == [0.1, 0.1, 0.1]
    np.testing.assert_array_equal(sc.system.F, paper.system.F)
