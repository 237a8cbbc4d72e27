"""io/replay: measurements out of recorded files (ROS 2 / protobuf / JSON MCAP, CSV).

Expected values come from the plain ``mcap`` readers with the ecosystem's decoders and from the
files' text, never from the code under test. The committed example data (pipeline/data/, made
by make_replay_data.py) is read as a user's recording would be; every robustness case must give
one line that starts with the source path and names the stream.
"""

from __future__ import annotations

import functools
import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from mcap.reader import make_reader
from mcap.writer import CompressionType, IndexType, Writer
from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoderFactory
from mcap_ros2.decoder import DecoderFactory as Ros2DecoderFactory

from fusionlog.errors import DamagedFile, FusionlogError, ValidationError
from fusionlog.io.replay import Series, list_topics, read_series

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "pipeline" / "data"
ROS2 = DATA / "robot_ros2.mcap"
MOCAP = DATA / "mocap.csv"
TRUTH = DATA / "truth.csv"
XY = ["pose.pose.position.x", "pose.pose.position.y"]
BASE = 1_700_000_000_000_000_000


# -- helpers ------------------------------------------------------------------------------------


@functools.cache
def ros2_messages(topic: str) -> list[tuple[int, object]]:
    """(log_time, decoded) in log-time order, with only mcap + mcap-ros2-support."""
    with open(ROS2, "rb") as f:
        r = make_reader(f, decoder_factories=[Ros2DecoderFactory()])
        return [(m.log_time, d) for _, _, m, d in r.iter_decoded_messages(topics=[topic])]


def stamp_ns(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def csv_rows(path: Path) -> tuple[list[str], list[list[str]]]:
    lines = path.read_text().splitlines()
    return [h.strip() for h in lines[0].split(",")], [ln.split(", ") for ln in lines[1:]]


def one_line(exc: pytest.ExceptionInfo, source: Path, what: str, *needles: str) -> str:
    """The error is a FusionlogError with one line naming the source and the stream."""
    msg = str(exc.value)
    assert isinstance(exc.value, FusionlogError)
    assert "\n" not in msg and "Traceback" not in msg, msg
    assert msg.startswith(f"{source}: {what}: "), msg
    for n in needles:
        assert n in msg, (n, msg)
    return msg


def fails(source: Path, what: str = "sensors[0]", *needles: str, exc=FusionlogError, **kw) -> str:
    kw.setdefault("topic", "/odom" if source.suffix == ".mcap" else None)
    kw.setdefault("values", XY)
    with pytest.raises(exc) as ei:
        read_series(source, what=what, **kw)
    return one_line(ei, source, what, *needles)


def write_json_mcap(path: Path, topics: dict[str, list[tuple[int, object]]], **writer_kw) -> None:
    """JSON MCAP with mcap's own Writer: topic -> [(log_time, message object)]."""
    with open(path, "wb") as f:
        w = Writer(f, **writer_kw)
        w.start(profile="", library="test")
        sid = w.register_schema("test.Thing", "jsonschema", b'{"type": "object"}')
        for topic, msgs in topics.items():
            cid = w.register_channel(topic, "json", sid)
            for t, obj in msgs:
                w.add_message(cid, log_time=t, publish_time=t, data=json.dumps(obj).encode())
        w.finish()


def write_raw_mcap(path: Path, schema: tuple[str, str, bytes] | None, encoding: str, data: bytes):
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema(*schema) if schema else 0
        cid = w.register_channel("/x", encoding, sid)
        w.add_message(cid, log_time=BASE, publish_time=BASE, data=data)
        w.finish()


def load_script():
    """pipeline/data/make_replay_data.py as a module."""
    spec = importlib.util.spec_from_file_location("make_replay_data", DATA / "make_replay_data.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def sensors_file(tmp_path_factory) -> Path:
    """fusionlog's own protobuf sensors file (one run)."""
    from fusionlog.cli import main

    out = tmp_path_factory.mktemp("pb") / "s.mcap"
    res = CliRunner().invoke(
        main, ["simulate", str(ROOT / "pipeline" / "ajgl2009.toml"), "-o", str(out), "--runs", "1"]
    )
    assert res.exit_code == 0, res.output
    return out


# -- the committed ROS 2 file ---------------------------------------------------------------------


def test_ros2_file_decodes_with_plain_readers():
    with open(ROS2, "rb") as f:
        r = make_reader(f, decoder_factories=[Ros2DecoderFactory()])
        summary = r.get_summary()
        assert {s.name for s in summary.schemas.values()} == {
            "nav_msgs/msg/Odometry",
            "geometry_msgs/msg/PoseWithCovarianceStamped",
            "sensor_msgs/msg/NavSatFix",
        }
        assert all(s.encoding == "ros2msg" for s in summary.schemas.values())
        assert r.get_header().profile == "ros2"
        counts: dict[str, int] = {}
        for _, ch, _, _msg in r.iter_decoded_messages():
            assert ch.message_encoding == "cdr"
            counts[ch.topic] = counts.get(ch.topic, 0) + 1
    assert counts == {"/odom": 1350, "/pose": 44, "/fix": 45}
    assert ROS2.stat().st_size + MOCAP.stat().st_size + TRUTH.stat().st_size < 350_000


def test_ros2_odom_values_times_and_zero_covariance():
    msgs = ros2_messages("/odom")
    s = read_series(
        ROS2,
        topic="/odom",
        values=XY,
        time="header.stamp",
        covariance="pose.covariance",
        covariance_index=[0, 1],
    )
    assert isinstance(s, Series) and s.notes == ()
    assert s.times_ns.dtype == np.int64 and s.values.dtype == np.float64
    np.testing.assert_array_equal(s.times_ns, [stamp_ns(m) for _, m in msgs])
    np.testing.assert_array_equal(
        s.values, [[m.pose.pose.position.x, m.pose.pose.position.y] for _, m in msgs]
    )
    assert np.all(np.diff(s.times_ns) > 0)
    assert 29.5 < (len(s.times_ns) - 1) / ((s.times_ns[-1] - s.times_ns[0]) * 1e-9) < 30.5
    assert s.cov.shape == (1350, 2, 2) and not s.cov.any()  # the driver's all-zero covariance
    # the twist's covariance, and the default time: log_time (the arrival, after the stamp)
    v = read_series(
        ROS2,
        topic="/odom",
        values=["twist.twist.linear.x", "twist.twist.linear.y"],
        covariance="twist.covariance",
        covariance_index=[0, 1],
    )
    assert v.cov.shape == (1350, 2, 2) and not v.cov.any()
    np.testing.assert_array_equal(v.times_ns, [t for t, _ in msgs])
    assert np.all(v.times_ns > s.times_ns) and v.notes == ()
    np.testing.assert_array_equal(
        v.values, [[m.twist.twist.linear.x, m.twist.twist.linear.y] for _, m in msgs]
    )


def test_ros2_pose_stamps_sorted_with_count_and_covariance_block():
    msgs = ros2_messages("/pose")
    stamps = [stamp_ns(m) for _, m in msgs]
    late = sum(t < max(stamps[:i]) for i, t in enumerate(stamps) if i)
    assert late == 4  # the data has messages overtaken in log-time order
    s = read_series(
        ROS2,
        topic="/pose",
        values=XY,
        time="header.stamp",
        covariance="pose.covariance",
        covariance_index=[0, 1],
        what="sensors[1]",
    )
    assert s.notes == ("4 messages out of time order (sorted)",)
    order = np.argsort(stamps, kind="stable")
    np.testing.assert_array_equal(s.times_ns, np.array(stamps)[order])
    by_stamp = {stamp_ns(m): m for _, m in msgs}
    for t, val, c in zip(s.times_ns, s.values, s.cov, strict=True):
        m = by_stamp[int(t)]
        assert list(val) == [m.pose.pose.position.x, m.pose.pose.position.y]
        M = np.array(m.pose.covariance).reshape(6, 6)
        np.testing.assert_array_equal(c, M[:2, :2])
        assert c[0, 1] == c[1, 0] and np.all(np.linalg.eigvalsh(c) > 0)
    # other rows/columns: x and the yaw variance
    s2 = read_series(
        ROS2,
        topic="/pose",
        values=["pose.pose.position.x", "pose.pose.orientation.z"],
        time="header.stamp",
        covariance="pose.covariance",
        covariance_index=[0, 5],
    )
    m = by_stamp[int(s2.times_ns[0])]
    M = np.array(m.pose.covariance).reshape(6, 6)
    np.testing.assert_array_equal(s2.cov[0], M[np.ix_([0, 5], [0, 5])])


def test_ros2_measurements_match_the_truth_file():
    truth = np.loadtxt(TRUTH, delimiter=",", skiprows=1, dtype=np.float64)
    t_truth = np.array([int(r[0]) for r in csv_rows(TRUTH)[1]], dtype=np.int64)
    tr = read_series(
        TRUTH,
        topic=None,
        values=["x [m]", "y [m]", "vx [m s^-1]", "vy [m s^-1]"],
        time="#timestamp [ns]",
        time_unit="ns",
        what="truth",
    )
    np.testing.assert_array_equal(tr.times_ns, t_truth)
    np.testing.assert_array_equal(tr.values, truth[:, 1:])
    odom = read_series(
        ROS2,
        topic="/odom",
        values=[*XY, "twist.twist.linear.x", "twist.twist.linear.y"],
        time="header.stamp",
    )
    idx = np.searchsorted(tr.times_ns, odom.times_ns)
    assert np.array_equal(tr.times_ns[idx], odom.times_ns)  # every stamp is a truth instant
    err = odom.values - tr.values[idx]  # position and velocity noise, both 0.05
    assert np.all(np.abs(err.mean(axis=0)) < 0.01) and np.all(np.abs(err.std(axis=0) - 0.05) < 0.01)
    # the velocities are those of the positions: x(t) - x(0) = integral of v (trapezoid rule
    # on the fine grid of instants), to a few mm over tens of metres
    dt = np.diff(tr.times_ns) * 1e-9
    integral = np.cumsum(0.5 * (tr.values[1:, 2:] + tr.values[:-1, 2:]) * dt[:, None], axis=0)
    moved = tr.values[1:, :2] - tr.values[0, :2]
    assert np.abs(moved).max() > 20 and np.abs(moved - integral).max() < 0.02


def test_list_topics_of_the_ros2_file_and_fusionlog_file(sensors_file):
    rows = list_topics(ROS2)
    assert [r[:4] for r in rows] == [
        ("/fix", "sensor_msgs/msg/NavSatFix", "cdr", 45),
        ("/odom", "nav_msgs/msg/Odometry", "cdr", 1350),
        ("/pose", "geometry_msgs/msg/PoseWithCovarianceStamped", "cdr", 44),
    ]
    rates = {r[0]: r[4] for r in rows}
    assert rates["/fix"] == pytest.approx(1.0, rel=1e-9)
    assert rates["/odom"] == pytest.approx(30.0, rel=1e-3)
    assert rates["/pose"] == pytest.approx(1.0, rel=0.05)
    pb = {r[0]: r for r in list_topics(sensors_file)}
    assert pb["/sensors/s1"][1:4] == ("fusionlog.Block", "protobuf", 21)
    assert pb["/sensors/s1"][4] == pytest.approx(1e9 / 1e9, rel=1e-9)


def test_list_topics_without_chunk_index_and_single_message(tmp_path):
    p = tmp_path / "flat.mcap"
    write_json_mcap(
        p,
        {"/a": [(BASE + k * 250_000_000, {"v": k}) for k in range(9)], "/b": [(BASE, {"v": 0})]},
        use_chunking=False,
        index_types=IndexType.NONE,
        compression=CompressionType.NONE,
    )
    assert list_topics(p) == [
        ("/a", "test.Thing", "json", 9, 4.0),
        ("/b", "test.Thing", "json", 1, None),
    ]


# -- protobuf (fusionlog's own sensors file) and JSON ---------------------------------------------


def test_protobuf_fusionlog_sensors_file(sensors_file):
    with open(sensors_file, "rb") as f:
        r = make_reader(f, decoder_factories=[ProtobufDecoderFactory()])
        msgs = [(m.log_time, d) for _, _, m, d in r.iter_decoded_messages(topics=["/sensors/s1"])]
    s = read_series(sensors_file, topic="/sensors/s1", values=["values[0]"])
    np.testing.assert_array_equal(s.times_ns, [t for t, _ in msgs])
    np.testing.assert_array_equal(s.values[:, 0], [d.values[0] for _, d in msgs])
    st = read_series(sensors_file, topic="/sensors/s1", values=["values[0]"], time="time")
    np.testing.assert_array_equal(st.times_ns, s.times_ns)  # time (s, double) = log_time here
    msg = fails(
        sensors_file,
        "sensors[0]",
        "values[1]",
        "has 1 element",
        topic="/sensors/s1",
        values=["values[1]"],
    )
    assert "out of range" in msg


def test_json_mcap_values_times_covariance(tmp_path):
    p = tmp_path / "j.mcap"
    t0 = 1_700_000_000_123_456_789  # not a double: 1.7e18 + odd ns must stay exact
    msgs = []
    for k in range(5):
        t = t0 + k * 100_000_001
        obj = {
            "stamp": {"sec": t // 10**9, "nsec": t % 10**9},
            "t_ns": t,
            "t_ms": (t - t0) / 1e6,
            "pos": [k * 1.5, -k, 7],
            "cov": [1.0 + k, 0.1, 0.0, 0.1, 2.0, 0.0, 0.0, 0.0, 3.0],
            "name": "p",
        }
        msgs.append((BASE + k, obj))
    write_json_mcap(p, {"/j": msgs})
    want_t = [t0 + k * 100_000_001 for k in range(5)]
    for time, unit in (("stamp", "s"), ("t_ns", "ns")):
        s = read_series(
            p,
            topic="/j",
            values=["pos[0]", "pos[2]"],
            time=time,
            time_unit=unit,
            covariance="cov",
            covariance_index=[2, 0],
        )
        assert s.times_ns.tolist() == want_t  # exact int64
        np.testing.assert_array_equal(s.values, [[k * 1.5, 7.0] for k in range(5)])
        np.testing.assert_array_equal(s.cov[3], [[3.0, 0.0], [0.0, 4.0]])
    ms = read_series(p, topic="/j", values=["pos[1]"], time="t_ms", time_unit="ms")
    assert ms.times_ns.tolist() == [round(((t - t0) / 1e6) * 1e6) for t in want_t]
    # without covariance_index, a matrix of len(values)^2 numbers is taken whole
    full = read_series(p, topic="/j", values=["pos[0]", "pos[1]", "pos[2]"], covariance="cov")
    np.testing.assert_array_equal(full.cov[1], np.reshape(msgs[1][1]["cov"], (3, 3)))


def test_json_unsorted_nan_and_skips_counted(tmp_path):
    p = tmp_path / "j.mcap"
    times = [5, 1, 2, 9, 3, 4]  # ms; without 2 (NaN) and 3 (inf): 1 comes after 5, 4 after 9
    vals = [0.5, 0.1, math.nan, 0.9, math.inf, 0.4]
    write_json_mcap(
        p,
        {
            "/j": [
                (BASE + i, {"t": t, "v": v})
                for i, (t, v) in enumerate(zip(times, vals, strict=True))
            ]
        },
    )
    s = read_series(p, topic="/j", values=["v"], time="t", time_unit="ms")
    assert s.times_ns.tolist() == [1_000_000, 4_000_000, 5_000_000, 9_000_000]
    assert s.values[:, 0].tolist() == [0.1, 0.4, 0.5, 0.9]
    assert s.notes == (
        "2 messages with NaN or infinite values skipped",
        "2 messages out of time order (sorted)",
    )


def test_json_float_seconds_and_stable_sort(tmp_path):
    p = tmp_path / "j.mcap"
    write_json_mcap(p, {"/j": [(BASE, {"t": 2.5, "v": 1}), (BASE + 1, {"t": 0.1, "v": 2})]})
    s = read_series(p, topic="/j", values=["v"], time="t")
    assert s.times_ns.tolist() == [100_000_000, 2_500_000_000] and s.values[:, 0].tolist() == [2, 1]


def test_json_decimal_seconds_become_nanoseconds_from_their_digits(tmp_path):
    """As in text tables: 1305031102.160407 s is 1305031102160407000 ns, not the double's
    1305031102160407066; a covariance of such numbers reads as floats."""
    p = tmp_path / "j.mcap"
    msgs = [(BASE, {"t": 1305031102.160407, "v": 0.1, "c": [0.25]}),
            (BASE + 1, {"t": 1305031102.19433, "v": 2, "c": [1e-3]})]  # fmt: skip
    write_json_mcap(p, {"/j": msgs})
    s = read_series(p, topic="/j", values=["v"], time="t", covariance="c")
    assert s.times_ns.tolist() == [1305031102160407000, 1305031102194330000]
    assert s.values[:, 0].tolist() == [0.1, 2.0] and s.cov[:, 0, 0].tolist() == [0.25, 1e-3]
    s = read_series(p, topic="/j", values=["v"], time="t", time_unit="ms")
    assert s.times_ns.tolist() == [1305031102160407, 1305031102194330]


# -- CSV ----------------------------------------------------------------------------------------


def test_mocap_csv_spaced_headers_exact_ns():
    header, rows = csv_rows(MOCAP)
    assert header[:2] == ["#timestamp [ns]", "p_RS_R_x [m]"]
    assert MOCAP.read_text().splitlines()[0].count(", ") == 4  # comma and a space
    s = read_series(
        MOCAP,
        topic=None,
        values=["p_RS_R_x [m]", "  p_RS_R_y [m] ", "v_RS_R_x [m s^-1]", "v_RS_R_y [m s^-1]"],
        time="#timestamp [ns]",
        time_unit="ns",
        what="sensors[2]",
    )
    kept = [r for r in rows if r[1] != "nan"]
    assert len(kept) == len(rows) - 2
    assert s.times_ns.tolist() == [int(r[0]) for r in kept]  # exact, beyond float precision
    assert s.times_ns[0] == 1_700_000_000_012_500_000
    np.testing.assert_array_equal(s.values, [[float(x) for x in r[1:]] for r in kept])
    assert s.cov is None
    assert s.notes == ("2 rows with empty, NaN or infinite values skipped",)


def test_csv_default_time_column_in_seconds_decimal_exact(tmp_path):
    p = tmp_path / "m.csv"
    p.write_text("time, a\n1700000000.123456789, 1\n\n1700000000.2, 2\n1700000000.1, 3\n")
    s = read_series(p, topic=None, values=["a"])
    assert s.times_ns.tolist() == [
        1_700_000_000_100_000_000,
        1_700_000_000_123_456_789,
        1_700_000_000_200_000_000,
    ]
    assert s.values[:, 0].tolist() == [3.0, 1.0, 2.0]
    assert s.notes == ("1 row out of time order (sorted)",)
    us = read_series(p, topic=None, values=["a"], time_unit="us")
    assert us.times_ns[0] == 1_700_000_000_100  # 1700000000.1 us


# -- robustness: one line each ------------------------------------------------------------------


def test_duplicate_instants_are_errors(tmp_path):
    p = tmp_path / "j.mcap"
    write_json_mcap(
        p, {"/j": [(BASE + i, {"t": t, "v": 1.0}) for i, t in enumerate([3, 1, 3, 2, 2])]}
    )
    fails(
        p,
        "sensors[3]",
        "duplicate instant 2 ns",
        "message 4 and message 5",
        "1 more",
        topic="/j",
        values=["v"],
        time="t",
        time_unit="ns",
        exc=ValidationError,
    )
    c = tmp_path / "d.csv"
    c.write_text("time,a\n1,1\n2,2\n1,3\n")
    fails(
        c,
        "truth",
        "duplicate instant 1000000000 ns",
        "line 2 and line 4",
        values=["a"],
        exc=ValidationError,
    )


def test_missing_field_names_the_closest():
    msg = fails(
        ROS2,
        "sensors[0]",
        "no field pose.pose.positon.x",
        "pose.pose.position.x",
        values=["pose.pose.positon.x"],
        exc=ValidationError,
    )
    assert "topic /odom (nav_msgs/msg/Odometry)" in msg
    fails(ROS2, "sensors[0]", "no field header.stamps", "header.stamp", time="header.stamps")
    fails(
        ROS2,
        "sensors[0]",
        "no field twist.covariances",
        "twist.covariance",
        covariance="twist.covariances",
    )


def test_index_out_of_range_and_bad_paths():
    fails(
        ROS2, "sensors[0]", "index 36 out of range", "36 elements", values=["pose.covariance[36]"]
    )
    fails(
        ROS2, "sensors[0]", "pose.pose.position is not an array", values=["pose.pose.position[0]"]
    )
    fails(
        ROS2,
        "sensors[0]",
        "covariance_index 6 is out of range for the 6x6",
        covariance="pose.covariance",
        covariance_index=[0, 6],
    )
    fails(ROS2, "sensors[0]", "bad field path", values=["pose..x"])
    fails(ROS2, "sensors[0]", "bad field path", values=["pose.covariance[-1]"])
    fails(
        ROS2,
        "sensors[0]",
        "covariance_index has 1 entries",
        covariance="pose.covariance",
        covariance_index=[0],
    )
    fails(ROS2, "sensors[0]", "repeats", covariance="pose.covariance", covariance_index=[0, 0])
    fails(ROS2, "sensors[0]", "give covariance_index", covariance="pose.covariance")
    fails(
        ROS2,
        "sensors[0]",
        "covariance header is a message (fields stamp, frame_id), not an array of numbers",
        topic="/fix",
        values=["latitude"],
        covariance="header",
        covariance_index=[0],
    )
    fails(ROS2, "sensors[0]", "time_unit 'h'", time_unit="h")
    fails(
        ROS2, "sensors[0]", "covariance_index is given without covariance", covariance_index=[0, 1]
    )


def test_non_numeric_values_and_times():
    fails(
        ROS2,
        "sensors[0]",
        "header.frame_id is a string ('odom'), not a number",
        values=["header.frame_id"],
    )
    fails(
        ROS2,
        "sensors[0]",
        "pose.pose.position is a message (fields x, y, z), not a number",
        values=["pose.pose.position"],
    )
    fails(ROS2, "sensors[0]", "pose.covariance is an array of 36", values=["pose.covariance"])
    fails(ROS2, "sensors[0]", "header is a message", "not a time", time="header")
    fails(
        ROS2,
        "sensors[0]",
        "covariance pose.pose is a message",
        covariance="pose.pose",
        covariance_index=[0, 1],
    )


def test_json_non_numeric_and_missing_in_later_message(tmp_path):
    p = tmp_path / "j.mcap"
    write_json_mcap(p, {"/j": [(BASE, {"v": 1.0}), (BASE + 1, {"v": "2.0"}), (BASE + 2, {"w": 1})]})
    fails(
        p, "sensors[0]", "message 2: v is a string ('2.0'), not a number", topic="/j", values=["v"]
    )
    q = tmp_path / "k.mcap"
    write_json_mcap(q, {"/j": [(BASE, {"v": 1.0}), (BASE + 1, {"w": 1})]})
    fails(q, "sensors[0]", "message 2: no field v", topic="/j", values=["v"])
    r = tmp_path / "c.mcap"
    write_json_mcap(r, {"/j": [(BASE, {"v": 1.0, "c": [1, 0, 0, "x"]})]})
    fails(r, "sensors[0]", "c[3] is a string", topic="/j", values=["v", "v"], covariance="c")
    write_json_mcap(r, {"/j": [(BASE, {"v": 1.0, "c": [1, 0, 0, 1, 5]})]})
    fails(
        r,
        "sensors[0]",
        "covariance c has 5 numbers, not a square",
        topic="/j",
        values=["v"],
        covariance="c",
    )
    write_json_mcap(
        r, {"/j": [(BASE, {"v": 1.0, "c": [1]}), (BASE + 1, {"v": 1.0, "c": [1, 0, 0, 1]})]}
    )
    fails(
        r,
        "sensors[0]",
        "message 2: covariance c has 4 numbers where the first message had 1",
        topic="/j",
        values=["v"],
        covariance="c",
    )


def test_undecodable_schemas_name_topic_and_encoding(tmp_path):
    p = tmp_path / "ros1.mcap"
    write_raw_mcap(p, ("std_msgs/Float64", "ros1msg", b"float64 data"), "ros1", b"\x00" * 8)
    fails(
        p,
        "sensors[0]",
        "topic /x",
        "no decoder",
        "'ros1'",
        "'ros1msg'",
        topic="/x",
        values=["data"],
    )
    q = tmp_path / "bad.mcap"
    write_raw_mcap(
        q,
        ("pkg/msg/Bad", "ros2msg", b"float64 x\nthis is not a field ! ! !\n"),
        "cdr",
        b"\x00\x01\x00\x00" + b"\x00" * 8,
    )
    fails(
        q,
        "sensors[0]",
        "topic /x",
        "cannot decode its schema",
        "'ros2msg'",
        "'cdr'",
        topic="/x",
        values=["x"],
    )
    r = tmp_path / "pb.mcap"
    write_raw_mcap(r, ("pkg.Msg", "protobuf", b"\xff\xfe not a descriptor"), "protobuf", b"")
    fails(
        r,
        "sensors[0]",
        "topic /x",
        "cannot decode its schema",
        "'protobuf'",
        topic="/x",
        values=["x"],
    )
    s = tmp_path / "cbor.mcap"
    write_raw_mcap(s, None, "cbor", b"\xa0")
    fails(
        s, "sensors[0]", "topic /x", "no decoder", "no schema", "'cbor'", topic="/x", values=["x"]
    )


def test_message_that_does_not_match_its_schema(tmp_path):
    odometry = load_script().ODOMETRY_DEF.encode()
    p = tmp_path / "short.mcap"
    write_raw_mcap(
        p, ("nav_msgs/msg/Odometry", "ros2msg", odometry), "cdr", b"\x00\x01\x00\x00\x01"
    )
    msg = fails(
        p,
        "sensors[0]",
        "cannot read or decode message 1 of topic /x",
        "'cdr'",
        topic="/x",
        exc=DamagedFile,
    )
    assert "nav_msgs/msg/Odometry" in msg


def test_topic_missing_and_empty(tmp_path):
    fails(
        ROS2,
        "sensors[0]",
        "no topic /odometry",
        "topics: /fix, /odom, /pose",
        topic="/odometry",
        exc=ValidationError,
    )
    p = tmp_path / "empty_topic.mcap"
    write_json_mcap(p, {"/a": [(BASE, {"v": 1})], "/e": []})
    fails(p, "sensors[0]", "topic /e has no messages", topic="/e", values=["v"])
    q = tmp_path / "all_nan.mcap"
    write_json_mcap(q, {"/a": [(BASE, {"v": math.nan})]})
    fails(q, "sensors[0]", "no message with finite values", topic="/a", values=["v"])


def test_csv_errors_name_lines_and_columns(tmp_path):
    p = tmp_path / "m.csv"
    p.write_text("#timestamp [ns], p_x [m], p_y [m]\n1, 2, 3\n2, 3\n")
    fails(
        p,
        "sensors[1]",
        "line 3: 2 fields where the header has 3",
        values=["p_x [m]"],
        time="#timestamp [ns]",
        time_unit="ns",
        exc=ValidationError,
    )
    p.write_text("#timestamp [ns], p_x [m]\n1, 2\n2, 2.5.1\n")
    fails(
        p,
        "sensors[1]",
        "line 3: column 'p_x [m]': '2.5.1' is not a number",
        values=["p_x [m]"],
        time="#timestamp [ns]",
        time_unit="ns",
    )
    p.write_text("#timestamp [ns], p_x [m]\n1, 2\nnoon, 2\n")
    fails(
        p,
        "sensors[1]",
        "line 3: time column '#timestamp [ns]' 'noon' is not a number",
        values=["p_x [m]"],
        time="#timestamp [ns]",
        time_unit="ns",
    )
    p.write_text("#timestamp [ns], p_x [m]\n1, 2\n")
    fails(
        p,
        "sensors[1]",
        "no column 'p_x'",
        "closest: 'p_x [m]'",
        values=["p_x"],
        time="#timestamp [ns]",
    )
    fails(
        p, "sensors[1]", "time (default): no column 'time'", "'#timestamp [ns]'", values=["p_x [m]"]
    )
    p.write_text("")
    fails(p, "sensors[1]", "empty file (no header line)", values=["a"])
    p.write_text("time, a\n\n")
    fails(p, "sensors[1]", "no data rows", values=["a"])
    p.write_text('time, a\n1, "2\n')
    fails(p, "sensors[1]", "not valid CSV", values=["a"])
    p.write_bytes(b"time, a\n1, \xff\n")
    fails(p, "sensors[1]", "not UTF-8", values=["a"])
    p.write_text("time, a, a\n1, 2, 3\n")
    fails(p, "sensors[1]", "column 'a' appears 2 times", values=["a"])


def test_source_kinds_and_arguments(tmp_path):
    fails(tmp_path / "x.txt", "sensors[0]", "no such file", topic=None)
    fails(ROS2, "sensors[0]", "needs a topic", topic=None)
    fails(MOCAP, "sensors[0]", "given for a text table", topic="/odom")
    fails(MOCAP, "sensors[0]", "covariance fields are read from messages", covariance="c")
    fails(ROS2, "sensors[0]", "values must be a non-empty list", values=[])
    fails(tmp_path / "none.mcap", "sensors[0]", "no such file")
    fails(tmp_path / "none.csv", "sensors[0]", "no such file", values=["a"])


def test_damaged_mcap_files(tmp_path):
    data = ROS2.read_bytes()
    cases = {
        "truncated.mcap": data[: len(data) // 2],
        "not_mcap.mcap": MOCAP.read_bytes(),
        "empty.mcap": b"",
        "footer.mcap": data[:-37] + b"\x00" + data[-36:],  # the footer's opcode
    }
    flipped = bytearray(data)
    flipped[len(data) // 3] ^= 0xFF  # inside the first (zstd) chunk
    cases["flipped.mcap"] = bytes(flipped)
    for name, raw in cases.items():
        p = tmp_path / name
        p.write_bytes(raw)
        with pytest.raises(FusionlogError) as ei:
            read_series(p, topic="/odom", values=XY, what="sensors[0]")
        one_line(ei, p, "sensors[0]")
        assert isinstance(ei.value, DamagedFile), (name, str(ei.value))
        if name == "flipped.mcap":
            continue  # list_topics reads the summary and message indexes, not the chunks
        with pytest.raises(DamagedFile) as ei:
            list_topics(p)
        assert str(ei.value).startswith(f"{p}: ") and "\n" not in str(ei.value)


def test_make_replay_data_is_deterministic(tmp_path):
    load_script().main(["--out", str(tmp_path)])
    for name in ("mocap.csv", "truth.csv"):
        assert (tmp_path / name).read_bytes() == (DATA / name).read_bytes(), name

    def records(path):
        with open(path, "rb") as f:
            r = make_reader(f)
            return [
                (ch.topic, sc.name, sc.data, m.log_time, m.data) for sc, ch, m in r.iter_messages()
            ]

    assert records(tmp_path / "robot_ros2.mcap") == records(ROS2)
