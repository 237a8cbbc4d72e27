"""Replays of logs that others recorded (``../shared/data/logs``, see its README.md) and of the
pipeline's own examples in the new formats, against an independent Kalman filter.

Each case is a replay file written here; the logs are read again in the test with the
ecosystem's libraries (rosbags, mcap-ros2-support, the text parsed here, geodetic fixes through
pymap3d about the first fix), and a Kalman filter written here (the constant-velocity model
discretised exactly over each interval, the sensors that measure at an instant stacked, each
message's covariance where it is usable, else R) must give the CKF's estimates to 1e-9.
The real logs are read from their shared folder, never copied; without it those cases skip.
"""

from __future__ import annotations

from decimal import Decimal
from pathlib import Path

import numpy as np
import pymap3d
import pytest
from cli_helpers import ok

from fusionlog.io.mcap import McapFile

ROOT = Path(__file__).resolve().parents[1]
LOGS = ROOT / ".." / "shared" / "data" / "logs"
PIPELINE = ROOT / "pipeline"

CV = {2: ["x", "vx", "y", "vy"], 3: ["x", "vx", "y", "vy", "z", "vz"]}


# -- the logs read again, independently ------------------------------------------------------


def _ns(text: str, unit: int = 10**9) -> int:
    return int((Decimal(text.strip()) * unit).to_integral_value())


def _table(path: Path, time: int, cols: list[int], sep: str | None, unit: int = 10**9):
    rows = []
    for line in path.read_text().splitlines()[1:] if sep == "," else path.read_text().splitlines():
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        f = line.split(sep)
        vals = [float(f[c]) for c in cols]
        if all(np.isfinite(vals)):
            rows.append((_ns(f[time], unit), vals))
    rows.sort(key=lambda r: r[0])
    return np.array([r[0] for r in rows]), np.array([r[1] for r in rows]), None


def _get(msg, path: str):
    for part in path.split("."):
        msg = getattr(msg, part)
    return msg


def _messages(path: Path, topic: str):
    """(record/log time, decoded message) of a topic, from a bag (rosbags) or an MCAP."""
    if path.suffix == ".mcap":
        from mcap.reader import make_reader
        from mcap_ros2.decoder import DecoderFactory

        with open(path, "rb") as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            return [(m.log_time, d) for _, _, m, d in reader.iter_decoded_messages(topics=[topic])]
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as r:
        conns = [c for c in r.connections if c.topic == topic]
        return [(t, r.deserialize(raw, c.msgtype)) for c, t, raw in r.messages(connections=conns)]


def _msg_stream(path: Path, topic: str, values: list[str], stamp: bool, cov: str | None = None,
                idx=(0, 1)):  # fmt: skip
    rows = []
    for t, m in _messages(path, topic):
        if stamp:
            s = m.header.stamp
            t = s.sec * 10**9 + s.nanosec
        z = [float(_get(m, v)) for v in values]
        c = None
        if cov is not None:
            full = np.asarray(_get(m, cov), dtype=float)
            k = int(round(np.sqrt(full.size)))
            c = full.reshape(k, k)[np.ix_(idx, idx)]
        rows.append((t, z, c))
    rows = [r for r in rows if np.all(np.isfinite(r[1]))]
    rows.sort(key=lambda r: r[0])
    t = np.array([r[0] for r in rows])
    z = np.array([r[1] for r in rows])
    c = np.array([r[2] for r in rows]) if cov is not None else None
    return t, z, c


def _enu(stream, origin=None):
    t, lla, c = stream
    o = origin if origin is not None else (lla[0, 0], lla[0, 1], lla[0, 2] if lla.shape[1] > 2
                                          else 0.0)  # fmt: skip
    alt = lla[:, 2] if lla.shape[1] > 2 else np.full(len(t), o[2])
    e, n, u = pymap3d.geodetic2enu(lla[:, 0], lla[:, 1], alt, *o)
    return t, np.stack([e, n, u], axis=1)[:, : lla.shape[1]], c


# -- the independent filter ------------------------------------------------------------------


def _usable(c: np.ndarray) -> bool:
    """Finite, not all zero, symmetric to rounding (1e-9 relative), positive definite."""
    return bool(
        np.isfinite(c).all() and np.abs(c).max() > 0 and np.allclose(c, c.T, rtol=1e-9, atol=0)
        and np.linalg.eigvalsh(c).min() > 0
    )  # fmt: skip


def _kf(axes: int, q: float, prior, sensors):
    """sensors: (H, R, (times ns, values, covariances or None)). Returns means, covariances."""
    at: dict[int, list] = {}
    for H, R, (t, z, c) in sensors:
        for i in range(len(t)):
            Ri = 0.5 * (c[i] + c[i].T) if c is not None and _usable(c[i]) else R
            at.setdefault(int(t[i]), []).append((H, z[i], Ri))
    times = sorted(at)
    x, P = np.array(prior[0], float), np.array(prior[1], float)
    means, covs = [], []
    eye = np.eye(axes)
    for k, t in enumerate(times):
        if k:
            dt = (t - times[k - 1]) / 1e9
            F = np.kron(eye, np.array([[1.0, dt], [0.0, 1.0]]))
            Q = np.kron(eye, q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]]))
            x, P = F @ x, F @ P @ F.T + Q
        H = np.vstack([h for h, _, _ in at[t]])
        z = np.concatenate([zz for _, zz, _ in at[t]])
        R = np.zeros((len(z), len(z)))
        r0 = 0
        for _, zz, Rr in at[t]:
            R[r0 : r0 + len(zz), r0 : r0 + len(zz)] = Rr
            r0 += len(zz)
        S = H @ P @ H.T + R
        K = np.linalg.solve(S, H @ P).T
        x = x + K @ (z - H @ x)
        A = np.eye(len(x)) - K @ H
        P = A @ P @ A.T + K @ R @ K.T
        means.append(x)
        covs.append(P)
    return np.array(means), np.array(covs)


def _ckf(tmp: Path, text: str):
    f = tmp / "replay.toml"
    f.write_text(text)
    ok("import", f, "-o", tmp / "s.mcap")
    ok("estimate", tmp / "s.mcap", "-o", tmp / "e.mcap", "--arch", "CKF")
    mean, cov = McapFile(tmp / "e.mcap").read_all(["/estimates/CKF"])["/estimates/CKF"]
    return mean[0], cov if cov.ndim == 3 else cov[0]


# -- the cases -------------------------------------------------------------------------------


def _H(axes: int, rows: list[int]) -> np.ndarray:
    H = np.zeros((len(rows), 2 * axes))
    H[np.arange(len(rows)), rows] = 1.0
    return H


def _toml(axes: int, n0: float, prior_sd: float, sensors: list[tuple[str, np.ndarray, float]],
          truth: str = "") -> str:  # fmt: skip
    n = 2 * axes
    cov = (np.eye(n) * prior_sd**2).tolist()
    parts = [
        f'[scenario]\nname = "t"\nstate_names = {CV[axes]}\n',
        f'[model]\nkind = "constant-velocity"\naxes = {axes}\nn0 = {n0}\n',
        f"[prior]\nmean = {[0.0] * n}\ncov = {cov}\n",
    ]
    for body, H, r in sensors:
        R = (np.eye(H.shape[0]) * r).tolist()
        parts.append(f"[[sensors]]\n{body}\nH = {H.tolist()}\nR = {R}\n")
    return "\n".join(parts) + truth


def _case(name: str):
    """(replay file text, axes, n0, prior sd, [(H, R, independent stream)])."""
    L = LOGS.resolve()
    pos2, vel2, pos3 = _H(2, [0, 2]), _H(2, [1, 3]), _H(3, [0, 2, 4])
    if name == "kitti_gps_txt":
        body = (
            f'name = "gps"\nsource = "{L}/KittiGps_converted.txt"\n'
            'values = ["X", "Y"]\ntime = "Time"'
        )
        s = [(body, pos2, 4.0)]
        return (
            s,
            2,
            0.5,
            100.0,
            [(pos2, 4 * np.eye(2), _table(L / "KittiGps_converted.txt", 0, [1, 2], ","))],
        )
    if name == "tum_freiburg":
        body = (
            f'name = "slam"\nsource = "{L}/freiburg1_xyz-rgbdslam.txt"\nformat = "tum"\n'
            'values = ["tx", "ty", "tz"]'
        )
        s = [(body, pos3, 1e-4)]
        return (
            s,
            3,
            0.1,
            10.0,
            [
                (
                    pos3,
                    1e-4 * np.eye(3),
                    _table(L / "freiburg1_xyz-rgbdslam.txt", 0, [1, 2, 3], None),
                )
            ],
        )
    if name == "euroc_csv":
        body = (
            f'name = "vicon"\nsource = "{L}/V102_groundtruth.csv"\n'
            'values = ["p_RS_R_x [m]", "p_RS_R_y [m]"]\ntime = "#timestamp"\ntime_unit = "ns"'
        )
        s = [(body, pos2, 1e-6)]
        return (
            s,
            2,
            1.0,
            10.0,
            [(pos2, 1e-6 * np.eye(2), _table(L / "V102_groundtruth.csv", 0, [1, 2], ",", 1))],
        )
    if name == "husky_ros1_bag":
        bag = L / "test1.bag"
        fix = (
            f'name = "fix"\nsource = "{bag}"\ntopic = "/fix"\nvalues = ["latitude", "longitude"]\n'
            'time = "header.stamp"\ngeodetic = true\ncovariance = "position_covariance"\n'
            "covariance_index = [0, 1]"
        )
        odom = (
            f'name = "odom"\nsource = "{bag}"\ntopic = "/husky_velocity_controller/odom"\n'
            'values = ["twist.twist.linear.x", "twist.twist.linear.y"]\ntime = "header.stamp"'
        )
        s = [(fix, pos2, 4.0), (odom, vel2, 0.01)]
        ind = [
            (
                pos2,
                4 * np.eye(2),
                _enu(
                    _msg_stream(bag, "/fix", ["latitude", "longitude"], True, "position_covariance")
                ),
            ),
            (
                vel2,
                0.01 * np.eye(2),
                _msg_stream(
                    bag,
                    "/husky_velocity_controller/odom",
                    ["twist.twist.linear.x", "twist.twist.linear.y"],
                    True,
                ),
            ),
        ]
        return s, 2, 0.1, 10.0, ind
    if name == "ros2_db3_folder":
        bag = L / "bag"
        gps = (
            f'name = "gps"\nsource = "{bag}"\ntopic = "/gps"\nvalues = ["latitude", "longitude"]\n'
            'geodetic = true\ncovariance = "position_covariance"\ncovariance_index = [0, 1]'
        )
        odom = (
            f'name = "odom"\nsource = "{bag}/bag_0.db3"\ntopic = "/odometry"\n'
            'values = ["twist.twist.linear.x", "twist.twist.linear.y"]'
        )
        s = [(gps, pos2, 9.0), (odom, vel2, 0.04)]
        ind = [
            (
                pos2,
                9 * np.eye(2),
                _enu(
                    _msg_stream(
                        bag, "/gps", ["latitude", "longitude"], False, "position_covariance"
                    )
                ),
            ),
            (
                vel2,
                0.04 * np.eye(2),
                _msg_stream(
                    bag, "/odometry", ["twist.twist.linear.x", "twist.twist.linear.y"], False
                ),
            ),
        ]
        return s, 2, 0.5, 10.0, ind
    if name == "circles_mcap_custom_gps":
        m = L / "going_in_circles1_0.mcap"
        gps = (
            f'name = "gps"\nsource = "{m}"\ntopic = "/gps"\n'
            'values = ["latitude", "longitude", "altitude"]\n'
            'time = "header.stamp"\ngeodetic = true'
        )
        pos = _H(3, [0, 2, 4])
        s = [(gps, pos, 9.0)]
        ind = [
            (
                pos,
                9 * np.eye(3),
                _enu(_msg_stream(m, "/gps", ["latitude", "longitude", "altitude"], True)),
            )
        ]
        return s, 3, 0.5, 10.0, ind
    if name == "nav2_mcap":
        m = L / "nav2_turtlebot.mcap"
        amcl = (
            f'name = "amcl"\nsource = "{m}"\ntopic = "/amcl_pose"\n'
            'values = ["pose.pose.position.x", "pose.pose.position.y"]\n'
            'covariance = "pose.covariance"\ncovariance_index = [0, 1]\n'
            'time = "header.stamp"'
        )
        odom = (
            f'name = "odom"\nsource = "{m}"\ntopic = "/odom"\n'
            'values = ["twist.twist.linear.x", "twist.twist.linear.y"]\ntime = "header.stamp"'
        )
        s = [(amcl, pos2, 0.25), (odom, vel2, 0.01)]
        ind = [
            (
                pos2,
                0.25 * np.eye(2),
                _msg_stream(
                    m,
                    "/amcl_pose",
                    ["pose.pose.position.x", "pose.pose.position.y"],
                    True,
                    "pose.covariance",
                ),
            ),
            (
                vel2,
                0.01 * np.eye(2),
                _msg_stream(m, "/odom", ["twist.twist.linear.x", "twist.twist.linear.y"], True),
            ),
        ]
        return s, 2, 0.1, 10.0, ind
    raise KeyError(name)  # fmt: skip


REAL = ["kitti_gps_txt", "tum_freiburg", "euroc_csv", "husky_ros1_bag", "ros2_db3_folder",
        "circles_mcap_custom_gps", "nav2_mcap"]  # fmt: skip


@pytest.mark.skipif(not LOGS.is_dir(), reason="the shared real logs are not here")
@pytest.mark.parametrize("name", REAL)
def test_ckf_on_a_real_log_equals_an_independent_kalman_filter(tmp_path: Path, name: str) -> None:
    sensors, axes, n0, sd, ind = _case(name)
    mean, cov = _ckf(tmp_path, _toml(axes, n0, sd, sensors))
    m_ref, P_ref = _kf(axes, n0, (np.zeros(2 * axes), sd**2 * np.eye(2 * axes)), ind)
    assert mean.shape == m_ref.shape
    scale = np.abs(m_ref).max()
    np.testing.assert_allclose(mean, m_ref, rtol=1e-9, atol=1e-9 * scale)
    np.testing.assert_allclose(cov, P_ref, rtol=1e-9, atol=1e-9 * np.abs(P_ref).max())


def test_ckf_on_the_ros1_gps_example_equals_an_independent_kalman_filter(tmp_path: Path) -> None:
    """pipeline/replay_gps_ros1.toml: NavSatFix in degrees about a given origin, a covariance
    per message (three all zero: R), velocities from TwistStamped."""
    bag = PIPELINE / "data" / "gps_ros1.bag"
    pos2, vel2 = _H(2, [0, 2]), _H(2, [1, 3])
    fix = _enu(_msg_stream(bag, "/fix", ["latitude", "longitude"], True, "position_covariance"),
               origin=(46.5197, 6.5657, 372.0))  # fmt: skip
    vel = _msg_stream(bag, "/vel", ["twist.linear.x", "twist.linear.y"], True)
    prior = (np.array([0.0, 4.0, 0.0, 1.5]), np.diag([25.0, 4.0, 25.0, 4.0]))
    m_ref, P_ref = _kf(
        2, 0.05, prior, [(pos2, 4 * np.eye(2), fix), (vel2, 0.0025 * np.eye(2), vel)]
    )
    f = tmp_path / "s.mcap"
    ok("import", PIPELINE / "replay_gps_ros1.toml", "-o", f)
    ok("estimate", f, "-o", tmp_path / "e.mcap", "--arch", "CKF")
    mean, cov = McapFile(tmp_path / "e.mcap").read_all(["/estimates/CKF"])["/estimates/CKF"]
    np.testing.assert_allclose(mean[0], m_ref, rtol=1e-9, atol=1e-9 * np.abs(m_ref).max())
    np.testing.assert_allclose(cov, P_ref, rtol=1e-9, atol=1e-12)


def test_ckf_on_the_tum_example_equals_an_independent_kalman_filter(tmp_path: Path) -> None:
    """pipeline/replay_tum.toml: a TUM trajectory (whitespace, # comments, decimal seconds)."""
    slam = _table(PIPELINE / "data" / "tum_slam.txt", 0, [1, 2, 3], None)
    pos3 = _H(3, [0, 2, 4])
    prior = (np.array([1.3, 0.0, 0.6, 0.0, 1.6, 0.0]), np.eye(6))
    m_ref, P_ref = _kf(3, 0.05, prior, [(pos3, 4e-4 * np.eye(3), slam)])
    f = tmp_path / "s.mcap"
    ok("import", PIPELINE / "replay_tum.toml", "-o", f)
    ok("estimate", f, "-o", tmp_path / "e.mcap", "--arch", "CKF")
    mean, cov = McapFile(tmp_path / "e.mcap").read_all(["/estimates/CKF"])["/estimates/CKF"]
    np.testing.assert_allclose(mean[0], m_ref, rtol=1e-9, atol=1e-9 * np.abs(m_ref).max())
    np.testing.assert_allclose(cov if cov.ndim == 3 else cov[0], P_ref, rtol=1e-9, atol=1e-15)


@pytest.mark.skipif(not LOGS.is_dir(), reason="the shared real logs are not here")
@pytest.mark.parametrize(
    ("log", "topic", "field"),
    [
        ("test1.bag", "/fix", "position_covariance"),
        ("bag", "/gps", "latitude"),
        ("bag/bag_0.db3", "/odometry", "twist.twist.linear.x"),
        ("nav2_turtlebot.mcap", "/amcl_pose", "pose.covariance"),
        ("going_in_circles1_0.mcap", "/imu", "imu.linear_acceleration.z"),
    ],
)
def test_inspect_lists_the_fields_of_real_logs(log: str, topic: str, field: str) -> None:
    out = ok("inspect", LOGS / log).stdout
    lines = out.splitlines()
    at = next(i for i, ln in enumerate(lines) if ln.split() and ln.split()[0] == topic)
    fields = []
    for ln in lines[at + 1 :]:
        if not ln.startswith("      "):
            break
        fields.append(ln.split()[0])
    assert field in fields, (field, fields[:20])
