"""Issue 28, part 2: valid inputs accepted, bad ones named.

A covariance in mixed units (a radar's m^2 beside rad^2) is positive definite whatever its
scale, judged here by exact rational arithmetic; the posterior Cramer-Rao bound from a known (or
partly known) initial state against a Kalman filter started from P = 0 (FilterPy) and against
the recursion restricted to the initial covariance's range; and each bad input the walk-through
met (a turn rate of 1e300, a FIFO or a device given to `summary`, a damaged compressed ROS 1
bag, a metadata.yaml with wrong types, max_diff out of range, a failing sweep point, UKF
parameters out of range, a replay whose states nothing determines) one line naming the file and
the problem, exit 2, nothing written.
"""

from __future__ import annotations

import os
import stat
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import cli, ok, one_line_error
from filterpy.kalman import KalmanFilter
from references import PIPELINE

import fusionlog as fl
from fusionlog.errors import ValidationError
from fusionlog.scenario import scenario_from_text

RADAR = (PIPELINE / "radar_tracking.toml").read_text()
TURN = (PIPELINE / "coordinated_turn.toml").read_text()
RADAR_R = "R = [[100.0, 0.0], [0.0, 3.0e-4]]"


def _edit(text: str, old: str, new: str, count: int = 1) -> str:
    assert old in text, old
    return text.replace(old, new, count)


def _files(root: Path) -> list[str]:
    return sorted(p.relative_to(root).as_posix() for p in root.rglob("*"))


# ------------------------------------------------------------------------------------------
# 1. positive definiteness does not depend on the units
# ------------------------------------------------------------------------------------------


def test_a_radars_R_in_metres_and_radians_is_accepted(tmp_path: Path) -> None:
    """R = diag(9e6 m^2, 1e-6 rad^2) (3 km range, 1 mrad bearing) was refused as "not positive
    definite (smallest eigenvalue 1e-06)"; it loads as written and the scenario runs."""
    text = _edit(RADAR, RADAR_R, "R = [[9.0e6, 0.0], [0.0, 1.0e-6]]")
    sc = scenario_from_text(text, "radar.toml")
    np.testing.assert_array_equal(sc.system.sensors[0].R, [[9.0e6, 0.0], [0.0, 1.0e-6]])
    f = tmp_path / "radar.toml"
    f.write_text(text)
    ok("run", f, "--out-dir", tmp_path / "out", "--runs", "20", "--steps", "5", "--arch", "CKF")


def _exact_2x2(a: float, b: float, d: float) -> tuple[bool, Fraction]:
    """Whether [[a, b], [b, d]] is positive definite, in exact rational arithmetic (a > 0 and
    ad - b^2 > 0), and how far it is from singular relative to its diagonal: 1 - b^2 / (ad)."""
    fa, fb, fd = Fraction(a), Fraction(b), Fraction(d)
    if fa <= 0 or fd <= 0:
        return False, Fraction(-1)
    rho2 = fb * fb / (fa * fd)
    return 1 - rho2 > 0, 1 - rho2


@pytest.mark.parametrize("scale", [1.0, 1e-6, 1e6, 1e-150, 1e150])
@pytest.mark.parametrize("key", ["sensors[1].R", "prior.cov", "model.Q", "truth.initial_cov"])
def test_definiteness_is_that_of_exact_arithmetic_in_any_units(scale: float, key: str) -> None:
    """2 x 2 covariances with variances a radar's 9e6 apart, and the first state (or
    measurement) rescaled by `scale` (a change of units): accepted exactly when they are
    positive (semi)definite in exact arithmetic, whatever the scale; correlations within 1e-9
    of +-1 (a question of rounding, not of units) are left out."""
    rng = np.random.default_rng(7)
    strict = key in ("sensors[1].R", "prior.cov")
    seen = {True: 0, False: 0}
    for _ in range(40):
        sd = np.array([3e3 * scale, 1e-3]) * rng.uniform(0.5, 2.0, 2)
        rho = rng.choice(
            [rng.uniform(-0.999, 0.999), rng.choice([-1.0, 1.0]) * rng.uniform(1.0, 3)]
        )
        a, d = float(sd[0] ** 2), float(sd[1] ** 2)
        b = float(rho * sd[0] * sd[1])
        want, margin = _exact_2x2(a, b, d)
        if abs(margin) < 1e-9:
            continue
        M = f"[[{a!r}, {b!r}], [{b!r}, {d!r}]]"
        text = _with_matrix(key, M)
        try:
            scenario_from_text(text, "u.toml")
            got = True
        except ValidationError as e:
            kind = "positive definite" if strict else "positive semidefinite"
            assert f"u.toml: {key}: not {kind}" in str(e), str(e)
            got = False
        assert got == want, (key, a, b, d, str(margin))
        seen[want] += 1
    assert seen[True] and seen[False]


#: a linear scenario with a 2-D state and a 2-D sensor, every covariance given.
_LINEAR = """\
[scenario]
name = "u"
steps = 3
runs = 5
seed = 1
dt = 1.0
[model]
F = [[1.0, 0.0], [0.0, 1.0]]
Q = {Q}
[prior]
mean = [0.0, 0.0]
cov = {P}
[truth]
initial_mean = [0.0, 0.0]
initial_cov = {T}
[[sensors]]
name = "a"
H = [[1.0, 0.0]]
R = 1.0
[[sensors]]
name = "b"
H = [[1.0, 0.0], [0.0, 1.0]]
R = {R}
"""


def _with_matrix(key: str, M: str) -> str:
    fill = {
        "Q": "[[1.0, 0.0], [0.0, 1.0]]",
        "P": "[[1.0, 0.0], [0.0, 1.0]]",
        "T": "[[1.0, 0.0], [0.0, 1.0]]",
        "R": "[[1.0, 0.0], [0.0, 1.0]]",
    }
    fill[{"sensors[1].R": "R", "prior.cov": "P", "model.Q": "Q", "truth.initial_cov": "T"}[key]] = M
    return _LINEAR.format(**fill)


def test_a_correlation_in_mixed_units_is_judged_on_the_joint_covariance() -> None:
    """A cross-covariance between a sensor in metres (R = 9e6) and one in radians (R = 1e-6):
    correlation 0.5 accepted, 1.0 (singular joint covariance) refused naming the key."""
    base = _with_matrix("sensors[1].R", "[[9.0e6, 0.0], [0.0, 1.0e-6]]")
    base = _edit(
        base, 'name = "a"\nH = [[1.0, 0.0]]\nR = 1.0', 'name = "a"\nH = [[0.0, 1.0]]\nR = 1.0e-6'
    )
    ok_text = base + '[[correlations]]\nsensors = ["a", "b"]\ncov = [[1.5, 0.0]]\n'  # rho 0.5
    scenario_from_text(ok_text, "c.toml")
    bad = base + '[[correlations]]\nsensors = ["a", "b"]\ncov = [[3.0, 0.0]]\n'  # rho = 1
    with pytest.raises(ValidationError, match=r"^c\.toml: correlations\[0\]\.cov: makes the joint"):
        scenario_from_text(bad, "c.toml")


# ------------------------------------------------------------------------------------------
# 2. the PCRB from a known or partly known initial state
# ------------------------------------------------------------------------------------------


def _polar_rows(sensor, x: np.ndarray) -> np.ndarray:
    """d[range, bearing]/dx (or the bearing's row), written out: range = |d|, bearing =
    atan2(dy, dx), d = target - sensor (states x, y at indices 0 and 2)."""
    dx, dy = x[0] - sensor.position[0], x[2] - sensor.position[1]
    r2 = dx * dx + dy * dy
    rng_row, brg_row = np.zeros(len(x)), np.zeros(len(x))
    rng_row[[0, 2]] = dx / np.sqrt(r2), dy / np.sqrt(r2)
    brg_row[[0, 2]] = -dy / r2, dx / r2
    return np.array([rng_row, brg_row] if sensor.kind == "range-bearing" else [brg_row])


def _Dz(system, truth: np.ndarray, measurements: dict, k: int) -> np.ndarray:
    """E[sum_j H_j^T R_j^-1 H_j] at instant k over the runs, over the sensors that measured."""
    M, _, n = truth.shape
    D = np.zeros((n, n))
    for s in system.sensors:
        for r in range(M):
            if not np.isnan(measurements[s.name][r, k]).any():
                H = _polar_rows(s, truth[r, k])
                D += H.T @ np.linalg.solve(s.R, H)
    return D / M


def _bound_summary(bound: np.ndarray) -> tuple[float, np.ndarray]:
    per_state = np.diagonal(bound, axis1=1, axis2=2)
    return float(per_state.sum(axis=1).mean() / bound.shape[-1]), per_state.mean(axis=0)


def test_pcrb_from_a_known_initial_state_is_a_kalman_filter_from_zero(tmp_path: Path) -> None:
    """Two radars, constant-velocity target, [truth] initial_cov = 0 (a known initial state;
    it was "the initial covariance is singular to working precision"). With linear motion the
    bound is J_k^-1 of J_k = (Q + F J_{k-1}^-1 F^T)^-1 + D_z(k) from J_0^-1 = 0: FilterPy's
    Kalman filter started from P = 0, updated at each instant by a measurement with H = U,
    R = I, U^T U = D_z(k) (the runs' average information, computed here from the simulated
    truth). Tolerance: the two forms differ by rounding amplified by the bound's condition."""
    text = _edit(
        RADAR,
        "[[sensors]]",
        "[truth]\ninitial_mean = [2000.0, 10.0, 3000.0, -5.0]\n"
        "initial_cov = [[0.0, 0, 0, 0], [0, 0.0, 0, 0], [0, 0, 0.0, 0], [0, 0, 0, 0.0]]\n"
        "\n[[sensors]]",
    )
    f = tmp_path / "known.toml"
    f.write_text(text)
    sc = fl.load(f)
    sim = fl.simulate(sc, runs=30, seed=4, steps=12)
    summary = fl.evaluate(sc, sim, fl.estimate(sc, sim, ["CKF"])).summary
    n = sc.system.n
    kf = KalmanFilter(dim_x=n, dim_z=n)
    kf.x, kf.P = np.zeros(n), np.zeros((n, n))
    kf.F, kf.Q = sc.system.F, sc.system.Q
    bound, cond = [], 1.0
    for k in range(len(sim.times)):
        if k:
            kf.predict()
        w, V = np.linalg.eigh(_Dz(sc.system, sim.truth, sim.measurements, k))
        kf.update(np.zeros(n), R=np.eye(n), H=(V * np.sqrt(np.clip(w, 0, None))).T)
        bound.append(kf.P.copy())
        if k:
            cond = max(cond, np.linalg.cond(kf.P))
    bound = np.array(bound)
    np.testing.assert_array_equal(bound[0], 0.0)  # known: no error at k = 0
    rtol = 100 * cond * np.finfo(float).eps
    assert rtol < 1e-6
    mse, per_state = _bound_summary(bound)
    assert summary["pcrb"]["mse"] == pytest.approx(mse, rel=rtol)
    np.testing.assert_allclose(summary["pcrb"]["mse_per_state"], per_state, rtol=rtol)


def test_pcrb_of_a_turn_with_known_positions_restricted_to_the_known_range(tmp_path: Path) -> None:
    """coordinated_turn.toml with the initial positions known ([truth] initial_cov zero on
    x and y) and the radar losing a fifth of its readings. With P_0 = V diag(l) V^T on its
    range V, J_0^-1 = V Y_0^-1 V^T, Y_0 = diag(l)^-1 + V^T D_z(0) V, and (J_0 + D11)^-1 =
    V (Y_0 + V^T D11 V)^-1 V^T; from J_1 on, Tichavsky's recursion (D11, D12, D22 from the
    turn's Jacobians at the simulated truth) in information form."""
    text = _edit(
        TURN,
        "[[sensors]]",
        "[truth]\ninitial_mean = [0.0, 15.0, 500.0, 0.0, 0.05]\n"
        "initial_cov = [[0.0, 0, 0, 0, 0], [0, 16.0, 0, 0, 0], [0, 0, 0.0, 0, 0], "
        "[0, 0, 0, 16.0, 0], [0, 0, 0, 0, 4.0e-4]]\n\n[[sensors]]",
    )
    text = _edit(
        text, "R = [[25.0, 0.0], [0.0, 1.0e-3]]", "dropout = 0.2\nR = [[25.0, 0.0], [0.0, 1.0e-3]]"
    )
    f = tmp_path / "turn.toml"
    f.write_text(text)
    sc = fl.load(f)
    sim = fl.simulate(sc, runs=25, seed=5, steps=10)
    summary = fl.evaluate(sc, sim, fl.estimate(sc, sim, ["CKF"])).summary
    system, motion = sc.system, sc.system.motion_model
    truth, times = sim.truth, sim.times
    M, K1, n = truth.shape
    P0 = np.diag([0.0, 16.0, 0.0, 16.0, 4e-4])
    V = np.eye(n)[:, [1, 3, 4]]  # P0's range
    Y0 = np.diag(1 / np.diag(V.T @ P0 @ V)) + V.T @ _Dz(system, truth, sim.measurements, 0) @ V
    bound = [V @ np.linalg.inv(Y0) @ V.T]
    J, cond = None, 1.0
    for k in range(1, K1):
        dt = times[k] - times[k - 1]
        Qi = np.linalg.inv(motion.Q(dt))
        Fs = [motion.jacobian(truth[r, k - 1], dt) for r in range(M)]
        D11 = sum(F.T @ Qi @ F for F in Fs) / M
        D12 = -(sum(Fs) / M).T @ Qi
        G = V @ np.linalg.inv(Y0 + V.T @ D11 @ V) @ V.T if J is None else np.linalg.inv(J + D11)
        J = Qi - D12.T @ G @ D12 + _Dz(system, truth, sim.measurements, k)
        bound.append(np.linalg.inv(J))
        cond = max(cond, np.linalg.cond(J))
    rtol = 100 * cond * np.finfo(float).eps
    assert rtol < 1e-6
    mse, per_state = _bound_summary(np.array(bound))
    assert summary["pcrb"]["mse"] == pytest.approx(mse, rel=rtol)
    np.testing.assert_allclose(summary["pcrb"]["mse_per_state"], per_state, rtol=rtol)


# ------------------------------------------------------------------------------------------
# 3. bad inputs: one line naming the file and the problem, exit 2, nothing written
# ------------------------------------------------------------------------------------------


def test_a_turn_rate_of_1e300_is_one_line(tmp_path: Path) -> None:
    """Prior omega = 1e300: five numpy RuntimeWarnings and exit 0 with MSE inf. The truth's
    turn (the simulation) and the filters' (a truth of its own, only the prior at 1e300) are
    refused as an overflow, naming the scenario, resp. the sensors file, architecture, step."""
    text = _edit(
        TURN, "mean = [0.0, 15.0, 500.0, 0.0, 0.05]", "mean = [0.0, 15.0, 500.0, 0.0, 1e300]"
    )
    f = tmp_path / "turn.toml"
    f.write_text(text)
    res = cli("run", f, "--out-dir", tmp_path / "out", "--runs", "10", "--steps", "4")
    one_line_error(
        res,
        f"{f}: simulation: the true state at step 1: the coordinated turn overflows",
        "omega = 1e+300 rad/s",
    )
    g = tmp_path / "prior_only.toml"
    g.write_text(
        _edit(
            text,
            "[[sensors]]",
            "[truth]\ninitial_mean = [0.0, 15.0, 500.0, 0.0, 0.05]\n\n[[sensors]]",
        )
    )
    ok("simulate", g, "-o", tmp_path / "s.mcap", "--runs", "10", "--steps", "4")
    res = cli("estimate", tmp_path / "s.mcap", "-o", tmp_path / "e.mcap", "--arch", "CKF")
    one_line_error(res, "s.mcap: architecture CKF, step ", "the coordinated turn overflows")
    assert _files(tmp_path) == ["prior_only.toml", "s.mcap", "turn.toml"]


@pytest.mark.parametrize("kind", ["fifo", "device"])
def test_summary_of_a_fifo_or_a_device_says_what_it_is(tmp_path: Path, kind: str) -> None:
    """It said "no such file"; now what `inspect` says (special files made here, never system
    paths)."""
    p = tmp_path / "rec.rrd"
    if kind == "fifo":
        os.mkfifo(p)
        what = "is a FIFO (named pipe), not a regular file"
    else:
        try:
            os.mknod(p, stat.S_IFCHR | 0o600, os.makedev(1, 3))
        except PermissionError as e:
            pytest.skip(f"cannot make a device node here: {e}")
        what = "is a character device, not a regular file"
    for args in ([], ["--json"]):
        one_line_error(cli("summary", p, *args), f"{p}: {what}")
    one_line_error(cli("inspect", p), f"{p}: {what}")


def _compressed_bag(path: Path) -> None:
    """A ROS 1 bag of 400 PointStamped on /pos in bz2-compressed chunks."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types
    Pt, Header, Time = (
        T["geometry_msgs/msg/PointStamped"],
        T["std_msgs/msg/Header"],
        T["builtin_interfaces/msg/Time"],
    )
    w = Writer(path)
    w.set_compression(Writer.CompressionFormat.BZ2)
    with w:
        c = w.add_connection("/pos", Pt.__msgtype__, typestore=ts)
        for i in range(400):
            t = 1_600_000_000_000_000_000 + i * 100_000_000
            stamp = Time(sec=t // 10**9, nanosec=t % 10**9)
            msg = Pt(
                header=Header(seq=i, stamp=stamp, frame_id="map"),
                point=T["geometry_msgs/msg/Point"](x=0.1 * i, y=0.0, z=0.0),
            )
            w.write(c, t, ts.serialize_ros1(msg, Pt.__msgtype__))


_BAG_REPLAY = """\
[scenario]
name = "bag"
[model]
kind = "constant-velocity"
n0 = 1.0
[prior]
mean = [0.0, 0.0]
cov = [[100.0, 0.0], [0.0, 1.0]]
[[sensors]]
name = "pos"
source = "{source}"
topic = "/pos"
values = ["point.x"]
H = [[1.0, 0.0]]
R = 0.01
"""


def test_a_damaged_compressed_ros1_bag_names_the_file_and_the_topic(tmp_path: Path) -> None:
    """64 zero bytes in the middle of a bz2 chunk: "Invalid data stream" named neither the
    file nor the topic; `import` and `inspect` now name both."""
    good = tmp_path / "good.bag"
    _compressed_bag(good)
    data = bytearray(good.read_bytes())
    mid = len(data) // 2
    data[mid : mid + 64] = bytes(64)
    bad = tmp_path / "bad.bag"
    bad.write_bytes(bytes(data))
    f = tmp_path / "replay.toml"
    f.write_text(_BAG_REPLAY.format(source="bad.bag"))
    line = one_line_error(
        cli("import", f, "-o", tmp_path / "s.mcap"),
        f"{bad}: sensors[0] (pos): topic /pos: damaged ROS bag",
    )
    assert "--recover" not in line
    one_line_error(cli("inspect", bad), f"{bad}: topic /pos: damaged ROS bag")
    f.write_text(_BAG_REPLAY.format(source="good.bag"))
    ok("import", f, "-o", tmp_path / "s.mcap")  # the same bag undamaged reads


def _ros2_bag(path: Path) -> None:
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    Pt = ts.types["geometry_msgs/msg/PointStamped"]
    with Writer(path, version=8) as w:
        c = w.add_connection("/pos", Pt.__msgtype__, typestore=ts)
        for i in range(10):
            t = 1_600_000_000_000_000_000 + i * 100_000_000
            msg = Pt(
                header=ts.types["std_msgs/msg/Header"](
                    stamp=ts.types["builtin_interfaces/msg/Time"](
                        sec=t // 10**9, nanosec=t % 10**9
                    ),
                    frame_id="map",
                ),
                point=ts.types["geometry_msgs/msg/Point"](x=0.1 * i, y=0.0, z=0.0),
            )
            w.write(c, t, ts.serialize_cdr(msg, Pt.__msgtype__))


@pytest.mark.parametrize(
    ("old", "new", "fragment"),
    [
        (
            "type: geometry_msgs/msg/PointStamped",
            "type: std_msgs/msg/String",
            "metadata.yaml lists 10 messages of type std_msgs/msg/String, and the bag's storage "
            "has none",
        ),
        (
            "type: geometry_msgs/msg/PointStamped",
            "type: 42",
            "metadata.yaml: topic entry 0: type 42 is not a string",
        ),
        ("name: /pos", "name: 7", "metadata.yaml: topic entry 0: name 7 is not a string"),
        (
            "message_count: 10\n    topic_metadata",
            "message_count: ten\n    topic_metadata",
            "metadata.yaml: topic entry 0: message_count 'ten' is not an integer",
        ),
    ],
)
def test_a_metadata_yaml_with_a_wrong_type_says_what_is_wrong(
    tmp_path: Path, old: str, new: str, fragment: str
) -> None:
    """A hand-edited metadata.yaml: a type the storage does not hold said the topic "has no
    messages"; a name or count of the wrong YAML type was an internal error (exit 3)."""
    bag = tmp_path / "ros2"
    _ros2_bag(bag)
    meta = bag / "metadata.yaml"
    meta.write_text(_edit(meta.read_text(), old, new))
    f = tmp_path / "replay.toml"
    f.write_text(_BAG_REPLAY.format(source="ros2"))
    one_line_error(
        cli("import", f, "-o", tmp_path / "s.mcap"), f"{bag}: sensors[0] (pos): ", fragment
    )
    assert not (tmp_path / "s.mcap").exists()
    res = cli("inspect", bag)
    if res.exit_code == 2:
        one_line_error(res, str(bag), fragment)
    else:  # the topic listed, with why its messages are not there
        assert res.exit_code == 0 and fragment in res.stdout, res.output


_TRUTH_REPLAY = """\
[scenario]
name = "t"
state_names = ["x", "v"]
[model]
kind = "constant-velocity"
n0 = 0.1
[prior]
mean = [0.0, 0.0]
cov = [[1.0, 0.0], [0.0, 1.0]]
[[sensors]]
name = "s"
source = "x.txt"
values = ["x"]
H = [[1.0, 0.0]]
R = 1.0
[truth]
source = "x.txt"
values = ["x"]
states = ["x"]
max_diff = {max_diff}
"""


@pytest.mark.parametrize("value", ["1e10", "1e-10", "0.0"])
def test_max_diff_names_its_range(tmp_path: Path, value: str) -> None:
    """`max_diff = 1e9` said "must be > 0"; the range is that of a sensor's period: one
    nanosecond (the resolution of a log's time) to 1e9 s, both ends accepted."""
    (tmp_path / "x.txt").write_text("time x\n0 1\n1 2\n2 3\n")
    f = tmp_path / "r.toml"
    f.write_text(_TRUTH_REPLAY.format(max_diff=value))
    one_line_error(
        cli("import", f, "-o", tmp_path / "s.mcap"),
        f"{f}: truth.max_diff: must be > 0 seconds, from 1e-09",
        "to 1e+09",
        f"got {float(value):.6g}",
    )
    for edge in ("1e9", "1e-9"):
        f.write_text(_TRUTH_REPLAY.format(max_diff=edge))
        ok("run", f, "--out-dir", tmp_path / f"o{edge}", "--arch", "CKF")


def test_a_failing_sweep_point_is_named(tmp_path: Path) -> None:
    """The numbers overflow at one grid point only: the line names that point (its index and
    values), not just the file."""
    text = _LINEAR.format(
        Q="[[1.0, 0.0], [0.0, 1.0]]",
        P="[[1.0, 0.0], [0.0, 1.0]]",
        T="[[1.0, 0.0], [0.0, 1.0]]",
        R="[[1.0, 0.0], [0.0, 1.0]]",
    )
    f = tmp_path / "s.toml"
    f.write_text(_edit(text, "steps = 3", "steps = 4"))
    res = cli(
        "sweep",
        f,
        "--vary",
        "model.F=[[1.0, 0.0], [0.0, 1.0]],[[1e120, 0.0], [0.0, 1.0]]",
        "--workers",
        "0",
        "--runs",
        "10",
        "--out-dir",
        tmp_path / "w",
    )
    # whichever task fails first (the point's simulation or its filters) names the point
    one_line_error(res, f"{f} [point 1: model.F=[[1e120, 0.0], [0.0, 1.0]]]: ", "overflows")
    assert _files(tmp_path) == ["s.toml"]


@pytest.mark.parametrize(
    ("ukf", "fragments"),
    [
        (
            "kappa = 1e300",
            [
                "estimate.ukf.kappa: must be in (-4, 75.5023] with alpha = 1 (n = 4), got 1e+300",
                "1e+150 standard deviations",
            ],
        ),
        (
            "alpha = 0.5, kappa = 330.0",
            ["estimate.ukf.kappa: must be in (-4, 314.009] with alpha = 0.5"],
        ),
        ("alpha = 2.0", ["estimate.ukf.alpha: must be in (0, 1], got 2"]),
        ("alpha = 0.0", ["estimate.ukf.alpha: must be > 0, got 0"]),
        ("beta = -0.5", ["estimate.ukf.beta: must be >= 0", "got -0.5"]),
        ("kappa = -4.0", ["estimate.ukf.kappa", "<= 0"]),
    ],
)
def test_ukf_parameters_outside_their_ranges_are_one_line(
    tmp_path: Path, ukf: str, fragments: list[str]
) -> None:
    """kappa = 1e300 ran (CKF MSE 2207 against a PCRB of 23). The upper end of n + lambda is
    the chi-square(n = 4) quantile of 1 - 2^-52, 79.5023 (scipy's chi2 here, not the code's)."""
    from scipy.stats import chi2

    assert chi2.isf(np.finfo(float).eps, 4) == pytest.approx(79.5023, abs=1e-4)
    f = tmp_path / "ukf.toml"
    f.write_text(_edit(RADAR, 'filter = "EKF"', f'filter = "UKF"\nukf = {{{ukf}}}'))
    one_line_error(cli("simulate", f, "-o", tmp_path / "s.mcap"), f"{f}: ", *fragments)
    assert _files(tmp_path) == ["ukf.toml"]


@pytest.mark.parametrize(
    "ukf", ["kappa = 75.5", "alpha = 0.5, kappa = 314.0", "alpha = 0.1, beta = 0.0"]
)
def test_ukf_parameters_inside_their_ranges_run(tmp_path: Path, ukf: str) -> None:
    f = tmp_path / "ukf.toml"
    f.write_text(_edit(RADAR, 'filter = "EKF"', f'filter = "UKF"\nukf = {{{ukf}}}'))
    ok("run", f, "--out-dir", tmp_path / "o", "--runs", "5", "--steps", "3", "--arch", "CKF")


_NO_PRIOR = """\
[scenario]
name = "np"
state_names = ["x", "vx", "y", "vy"]
[model]
kind = "constant-velocity"
axes = 2
n0 = 1.0
[[sensors]]
name = "s"
source = "d.csv"
values = {values}
H = {H}
R = {R}
"""


def test_a_replay_without_prior_whose_states_nothing_determines_is_one_line(tmp_path: Path) -> None:
    """No prior and a sensor of x alone: y and vy are never determined, no filter ever had a
    covariance and every metric was NaN, exit 0, no note. Refused naming the states; with a
    sensor of x and y the same replay runs."""
    (tmp_path / "d.csv").write_text(
        "time,px,py\n" + "".join(f"{0.1 * i:.1f},{i},{2 * i}\n" for i in range(20))
    )
    f = tmp_path / "np.toml"
    f.write_text(_NO_PRIOR.format(values='["px"]', H="[[1.0, 0.0, 0.0, 0.0]]", R="0.01"))
    one_line_error(
        cli("run", f, "--out-dir", tmp_path / "o"),
        f"{f}: prior: missing, and no sensor ever determines y, vy through the model",
    )
    assert not (tmp_path / "o").exists()
    f.write_text(
        _NO_PRIOR.format(
            values='["px", "py"]',
            H="[[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]",
            R="[[0.01, 0.0], [0.0, 0.01]]",
        )
    )
    ok("run", f, "--out-dir", tmp_path / "o", "--arch", "CKF")
