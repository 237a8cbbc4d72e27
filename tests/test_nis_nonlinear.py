"""NIS and innovation whiteness of nonlinear models (range-bearing radars, the coordinated turn):
the only consistency checks of a recorded log without truth.

The reference is the EKF's innovation written here from its formulas (Bar-Shalom, Li and
Kirubarajan 2001, ch. 10), one run and one instant at a time: x- = f(x_{k-1}),
P- = F_J P_{k-1} F_J' + Q with F_J the motion's Jacobian at x_{k-1}, nu = z - h(x-) with the
bearing wrapped to (-pi, pi], S = H P- H' + R with H the sensor's Jacobian at x-; the range,
bearing, turn and their derivatives written out here, not asked of the models.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from cli_helpers import ok
from scipy.stats import chi2

from fusionlog.core.model import Prior, System
from fusionlog.core.models import CoordinatedTurn, RangeBearingSensor
from fusionlog.core.nis import innovations
from fusionlog.core.nonlinear import estimate
from fusionlog.core.simulate import simulate
from fusionlog.stages.consistency import NisAccumulator

EPS = np.finfo(float).eps


def cv(T: float, q: float) -> tuple[np.ndarray, np.ndarray]:
    """Constant velocity on [x, vx, y, vy] over T, white acceleration of density q per axis."""
    F1 = np.array([[1.0, T], [0.0, 1.0]])
    Q1 = q * np.array([[T**3 / 3, T**2 / 2], [T**2 / 2, T]])
    return np.kron(np.eye(2), F1), np.kron(np.eye(2), Q1)


def turn(x: np.ndarray, T: float) -> tuple[np.ndarray, np.ndarray]:
    """The coordinated turn (Bar-Shalom et al., sec. 11.7) on [x, vx, y, vy, w]: f(x) and its
    Jacobian, differentiated by hand."""
    px, vx, py, vy, w = x
    s, c = np.sin(w * T), np.cos(w * T)
    A, B = s / w, (1 - c) / w
    dA, dB = (T * c * w - s) / w**2, (T * s * w - (1 - c)) / w**2
    f = np.array([px + A * vx - B * vy, c * vx - s * vy, py + B * vx + A * vy, s * vx + c * vy, w])
    J = np.array(
        [
            [1, A, 0, -B, vx * dA - vy * dB],
            [0, c, 0, -s, -T * s * vx - T * c * vy],
            [0, B, 1, A, vx * dB + vy * dA],
            [0, s, 0, c, T * c * vx - T * s * vy],
            [0, 0, 0, 0, 1],
        ]
    )
    return f, J


def turn_Q(T: float, q: float, q_turn: float) -> np.ndarray:
    Q = np.zeros((5, 5))
    Q[:4, :4] = cv(T, q)[1]
    Q[4, 4] = q_turn * T
    return Q


def wrap(a):
    """To (-pi, pi]."""
    return np.pi - np.mod(np.pi - a, 2 * np.pi)


def radar(x: np.ndarray, at) -> tuple[np.ndarray, np.ndarray]:
    """Range and bearing of state x from a radar at `at`, and their Jacobian."""
    dx, dy = x[0] - at[0], x[2] - at[1]
    r2 = dx * dx + dy * dy
    r = np.sqrt(r2)
    H = np.zeros((2, len(x)))
    H[0, 0], H[0, 2], H[1, 0], H[1, 2] = dx / r, dy / r, -dy / r2, dx / r2
    return np.array([r, np.arctan2(dy, dx)]), H


def reference(mean, cov, z, times, prior, radars, Rs, motion):
    """Per run and instant, per sensor: (NIS, S^-1/2 nu (lower Cholesky), S) of the EKF's
    innovation of the filtered estimates (mean, cov), NaN where the sensor did not measure;
    `motion(x, T)` -> (f(x), F_J, Q)."""
    M, K1, _ = mean.shape
    out = {j: (np.full((M, K1), np.nan), np.full((M, K1, 2), np.nan), np.zeros((M, K1, 2, 2)))
           for j in range(len(radars))}  # fmt: skip
    for m in range(M):
        for k in range(K1):
            if k == 0:
                xp, Pp = prior.mean, prior.cov
            else:
                f, F, Q = motion(mean[m, k - 1], times[k] - times[k - 1])
                xp, Pp = f, F @ cov[m, k - 1] @ F.T + Q
            for j, (at, R) in enumerate(zip(radars, Rs, strict=True)):
                zj = z[m, k, 2 * j : 2 * j + 2]
                if np.isnan(zj).any():
                    continue
                zhat, H = radar(xp, at)
                nu = zj - zhat
                nu[1] = wrap(nu[1])
                S = H @ Pp @ H.T + R
                u = np.linalg.solve(np.linalg.cholesky(S), nu)
                out[j][0][m, k] = nu @ np.linalg.solve(S, nu)
                out[j][1][m, k] = u
                out[j][2][m, k] = S
    return out


RADARS = ((0.0, 0.0), (900.0, 380.0))  # from b the target is near bearing pi, crossing it
R_RADAR = np.diag([25.0, 1e-3])


def radar_system(turning: bool, filt: str, times: np.ndarray):
    """Two radars on a target from (300, 400) at (12, -4) m/s, turning at 0.04 rad/s or not."""
    sensors = [
        RangeBearingSensor(name, np.array(at), (0, 2), 5 if turning else 4, R_RADAR)
        for name, at in zip("ab", RADARS, strict=True)
    ]
    mean = np.array([300.0, 12.0, 400.0, -4.0, 0.04])
    cov = np.diag([100.0, 9.0, 100.0, 9.0, 1e-4])
    if turning:
        ct = CoordinatedTurn((0.1, 0.1), 1e-5)
        F0, Q0 = ct.jacobian(np.zeros(5), 1.0).copy(), ct.Q(1.0)
        system = System(F0, Q0, tuple(sensors), Prior(mean, cov), motion_model=ct, filter=filt)

        def motion(x, T):
            return (*turn(x, T), turn_Q(T, 0.1, 1e-5))
    else:
        F, Q = cv(1.0, 0.5)
        system = System(F, Q, tuple(sensors), Prior(mean[:4], cov[:4, :4]), filter=filt,
                        continuous=(np.kron(np.eye(2), [[0.0, 1.0], [0.0, 0.0]]),
                                    np.kron(np.eye(2), [[0.0, 0.0], [0.0, 0.5]])))  # fmt: skip

        def motion(x, T):
            F, Q = cv(T, 0.5)
            return F @ x, F, Q

    return system.on_times(times), motion


@pytest.mark.parametrize(
    ("turning", "filt", "arch"),
    [(False, "EKF", "CKF"), (True, "EKF", "CKF"), (True, "UKF", "CKF"), (True, "EKF", "MSC")],
)
def test_nis_is_the_ekf_innovation_of_each_run_and_instant(turning, filt, arch):
    """`innovations` of the estimates of a radar scenario (irregular instants, a quarter of the
    readings lost, bearings across +-pi) equals the EKF innovation computed here, per run,
    instant and sensor: the NIS, the degrees of freedom and S^-1/2 nu; for a UKF's estimates
    the EKF-form innovation too (what `core.nis` documents); for MSC against its fused
    prediction."""
    times = np.cumsum(np.r_[0.0, np.tile([1.0, 0.5, 1.5], 8)])
    system, motion = radar_system(turning, filt, times)
    _, z = simulate(system, len(times) - 1, 11, 0, 6)
    lost = np.random.default_rng(3).random(z.shape[:2] + (2,)) < 0.25
    z[np.repeat(lost, 2, axis=-1)] = np.nan
    bearing_b = z[..., 3][np.isfinite(z[..., 3])]
    assert (np.abs(bearing_b) > 2.5).all() and (bearing_b > 0).any() and (bearing_b < 0).any()
    track = estimate(system, arch, z, None)
    want = reference(track.mean, track.cov, z, times, system.prior, RADARS, [R_RADAR] * 2, motion)
    for j in range(2):
        got = innovations(system, track.mean, track.cov, z, np.arange(2 * j, 2 * j + 2))
        nis, u, S = want[j]
        np.testing.assert_array_equal(np.isnan(got.nis), np.isnan(nis))
        np.testing.assert_array_equal(got.dof, np.where(np.isnan(nis), 0, 2))
        have = ~np.isnan(nis)
        # rounding moves S by eps |S| (entries of 100 m^2 beside 1e-3 rad^2), the NIS by that
        # relative amount times the condition number of S
        cond = np.linalg.cond(S[have])
        tol = 8 * EPS * cond * (1 + nis[have])
        assert (np.abs(got.nis[have] - nis[have]) <= tol).all(), np.abs(got.nis[have] - nis[have])
        err = np.abs(got.normalised[have] - u[have]).max(axis=-1)
        assert (err <= 8 * EPS * cond * (1 + np.abs(u[have]).max(axis=-1))).all(), err.max()


@pytest.mark.parametrize("filt", ["EKF", "UKF"])
def test_a_consistent_filter_s_mean_nis_is_in_its_chi_square_band(filt):
    """Small noise and weak nonlinearity (metre ranges, milliradian bearings, kilometres away):
    the EKF/UKF is consistent, so each radar's NIS summed over runs and instants is
    chi-square with the summed degrees of freedom (independent innovations): inside its
    99.9 % band, and its normalised innovations white (as `test_nis` asks of the KF)."""
    K, M = 30, 400
    times = np.arange(K + 1.0)
    sensors = tuple(
        RangeBearingSensor(name, np.array(at), (0, 2), 4, np.diag([1.0, 1e-6]))
        for name, at in (("a", (0.0, 0.0)), ("b", (5000.0, 0.0)))
    )
    F, Q = cv(1.0, 0.05)
    prior = Prior(np.array([2000.0, 10.0, 3000.0, -5.0]), np.diag([100.0, 4.0, 100.0, 4.0]))
    system = System(F, Q, sensors, prior, filter=filt).on_times(times)
    _, z = simulate(system, K, 5, 0, M)
    track = estimate(system, "CKF", z, None)
    acc = NisAccumulator(system, ["CKF"], K + 1)
    acc.add(z, {"CKF": (track.mean, track.cov)})
    summary = acc.summary(0.95)["CKF"]
    for name in "ab":
        entry = summary[name]
        assert entry["dof"] == 2.0
        D = 2 * M * (K + 1)  # every reading present, the prior's prediction at k = 0 too
        lo, hi = chi2.ppf([0.0005, 0.9995], D) / (M * (K + 1))
        assert lo < entry["mean"] < hi, (name, entry["mean"], lo, hi)
        assert entry["whiteness_fraction_inside"] > 0.85, entry
    # an over-confident filter (R believed 10 x smaller) leaves the band
    small = System(F, Q, tuple(
        RangeBearingSensor(s.name, s.position, (0, 2), 4, s.R / 10) for s in sensors
    ), prior, filter=filt).on_times(times)  # fmt: skip
    track = estimate(small, "CKF", z, None)
    acc = NisAccumulator(small, ["CKF"], K + 1)
    acc.add(z, {"CKF": (track.mean, track.cov)})
    assert acc.summary(0.95)["CKF"]["a"]["mean"] > hi


#: The radar log: 'a' at the origin, 'b' at (900, 380), each every 0.1 s (b 0.05 s after a).
N_READ = 40


def write_log(path) -> None:
    """A JSON MCAP of two radars' range and bearing of a target at (12, -4) m/s from (300,
    400), stamped in the header."""
    from mcap.writer import Writer

    rng, ns, t0 = np.random.default_rng(8), 10**9, 1_700_000_000 * 10**9
    msgs = []
    for i in range(N_READ):
        for topic, at, off in (("/a", RADARS[0], 0), ("/b", RADARS[1], 50)):
            s = t0 + (i * 100 + off) * ns // 1000
            t = (s - t0) / ns
            dx, dy = 300 + 12 * t - at[0], 400 - 4 * t - at[1]
            r = float(np.hypot(dx, dy) + 5 * rng.normal())
            b = float(wrap(np.arctan2(dy, dx) + 0.03 * rng.normal()))
            msgs.append((s, topic, r, b))
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("Reading", "jsonschema", b'{"type": "object"}')
        ch = {t: w.register_channel(t, "json", sid) for t in ("/a", "/b")}
        for s, topic, r, b in msgs:
            body = {"header": {"stamp": {"sec": s // ns, "nanosec": s % ns}}, "r": r, "b": b}
            w.add_message(ch[topic], log_time=s, data=json.dumps(body).encode(), publish_time=s)
        w.finish()


HEAD = """
[scenario]
name = "radar_log"

[model]
kind = "constant-velocity"
axes = 2
n0 = 0.5

[prior]
mean = [300.0, 12.0, 400.0, -4.0]
cov = [[100.0, 0, 0, 0], [0, 9.0, 0, 0], [0, 0, 100.0, 0], [0, 0, 0, 9.0]]
"""

#: Read with placeholder linear sensors (a replay's sensors are H z): the model comes with
#: `estimate --model`.
REPLAY = HEAD + "".join(
    f"""
[[sensors]]
name = "{s}"
H = [[1.0, 0, 0, 0], [0, 0, 1.0, 0]]
R = [[25.0, 0.0], [0.0, 1e-3]]
source = "log.mcap"
topic = "/{s}"
values = ["r", "b"]
time = "header.stamp"
"""
    for s in "ab"
)

MODEL = (
    HEAD
    + "".join(
        f"""
[[sensors]]
name = "{s}"
kind = "range-bearing"
position = [{at[0]}, {at[1]}]
R = [[25.0, 0.0], [0.0, 1e-3]]
"""
        for s, at in zip("ab", RADARS, strict=True)
    )
    + '\n[estimate]\nfilter = "EKF"\n'
)


def radar_log(tmp_path):
    """`import` of the radar log (no truth) and `estimate --model` (range-bearing, EKF)."""
    write_log(tmp_path / "log.mcap")
    (tmp_path / "replay.toml").write_text(REPLAY)
    (tmp_path / "model.toml").write_text(MODEL)
    ok("import", tmp_path / "replay.toml", "-o", tmp_path / "s.mcap")
    ok("estimate", tmp_path / "s.mcap", "--model", tmp_path / "model.toml", "--arch", "CKF",
       "--arch", "MSC", "-o", tmp_path / "e.mcap")  # fmt: skip
    return tmp_path


def evaluated(folder, name: str) -> dict:
    """`evaluate` of the log's readings and estimates: summary.json as written."""
    ok("evaluate", folder / "s.mcap", folder / "e.mcap", "-o", folder / f"{name}.rrd",
       "--summary", folder / name, "--force")  # fmt: skip
    return json.loads((folder / name).read_text())


def test_a_truth_free_radar_log_evaluates_with_its_nis(tmp_path):
    """`import` of a recorded radar log without truth, `estimate --model` with range-bearing
    sensors (EKF), `evaluate`: exit 0, and summary.json's NIS of each architecture and radar
    is the mean of the EKF innovations computed here on the estimates and readings read back
    (per-sensor architectures against their fused prediction), with its degrees of freedom
    and whiteness."""
    from fusionlog.io.mcap import McapFile

    summary = evaluated(radar_log(tmp_path), "summary.json")
    sens, est = McapFile(tmp_path / "s.mcap"), McapFile(tmp_path / "e.mcap")
    times = sens.times()
    ((_, _, data),) = sens.iter_run_blocks(["/sensors/a", "/sensors/b"], 1)
    z = np.concatenate([data["/sensors/a"], data["/sensors/b"]], -1)
    prior = Prior(np.array([300.0, 12.0, 400.0, -4.0]), np.diag([100.0, 9.0, 100.0, 9.0]))

    def motion(x, T):  # n0 = 0.5 per the replay's nominal 1 s step
        F, Q = cv(T, 0.5)
        return F @ x, F, Q

    for arch in ("CKF", "MSC"):
        ((_, _, (mean, cov)),) = (
            (o, r, d[f"/estimates/{arch}"])
            for o, r, d in est.iter_run_blocks([f"/estimates/{arch}"], 1)
        )
        cov = np.broadcast_to(cov, (1,) + cov.shape[-3:])
        want = reference(mean, cov, z, times, prior, RADARS, [R_RADAR] * 2, motion)
        entry = summary["architectures"][arch]["nis"]
        for j, name in enumerate("ab"):
            nis = want[j][0]
            assert np.isfinite(nis).sum() == N_READ
            got = entry[name]
            assert got["dof"] == 2.0
            np.testing.assert_allclose(got["mean"], np.nanmean(nis), rtol=1e-9)
            assert np.isfinite(got["whiteness_max_abs_autocorr"])
            assert got["whiteness_bound"] == pytest.approx(1.96 / np.sqrt(N_READ), rel=1e-12)


def test_in_blocks_of_time_the_nis_is_that_of_the_whole_log(tmp_path, monkeypatch):
    """The same log evaluated in blocks of 8 instants (4 readings of each radar a block, fewer
    than the whiteness's 10 lags): every NIS entry, whiteness too, that of the whole log (the
    blocks change only the order of roundings; the whiteness's lagged sums expand the
    autocorrelation about the mean, O(1) values: 1e-12)."""
    folder = radar_log(tmp_path)
    whole = evaluated(folder, "whole.json")
    monkeypatch.setenv("FUSIONLOG_TIME_BLOCK", "8")
    blocks = evaluated(folder, "blocks.json")
    for arch in ("CKF", "MSC"):
        a, b = whole["architectures"][arch]["nis"], blocks["architectures"][arch]["nis"]
        assert a.keys() == b.keys() == {"a", "b"}
        for name in a:
            assert a[name].keys() == b[name].keys()
            for key, value in a[name].items():
                assert np.isfinite(value), (arch, name, key)
                assert b[name][key] == pytest.approx(value, rel=1e-12, abs=1e-12), (arch, key)
