"""Recorded logs in more formats (DESIGN.md, "Recorded logs, more formats"): text tables of any
shape, ROS 1 and ROS 2 bags, geodetic fixes, truth at other times, and the one-line errors of
each new key. Small logs are written here (rosbags writes the bags); the real logs in
``../shared/data/logs`` are read in tests/test_replay_real_logs.py.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pymap3d
import pytest
from cli_helpers import cli, ok, one_line_error

from fusionlog.core.associate import associate
from fusionlog.errors import FusionlogError
from fusionlog.io.replay import read_series, source_kind, to_enu

LAT0, LON0, ALT0 = 47.3977, 8.5456, 488.0


# -- text tables ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("sep", "name"),
    [(",", "a.csv"), ("\t", "a.tsv"), (";", "a.dat"), ("   ", "a.txt"), (" \t ", "a")],
)
def test_text_table_delimiter_found_from_content(tmp_path: Path, sep: str, name: str) -> None:
    p = tmp_path / name
    rows = ["time", "x", "y"], ["0.5", "1.25", "-2"], ["1.5", "3", "4e-1"]
    p.write_text("\n".join(sep.join(r) for r in rows) + "\n")
    assert source_kind(p) == "text"
    s = read_series(p, topic=None, values=["x", "y"])
    np.testing.assert_array_equal(s.times_ns, [500_000_000, 1_500_000_000])
    np.testing.assert_array_equal(s.values, [[1.25, -2.0], [3.0, 0.4]])


@pytest.mark.parametrize("sep", ["\t", ";"])
def test_text_table_delimiter_found_from_every_sample_line(tmp_path: Path, sep: str) -> None:
    """A header whose names hold commas ("x, m") splits on commas too: only the data lines
    tell that the table is tab- or semicolon-separated (a comma splits none of them)."""
    p = tmp_path / "t.txt"
    rows = ["time", "x, m", "y, m"], ["0.5", "1.25", "-2"], ["1.5", "3", "0.4"]
    p.write_text("\n".join(sep.join(r) for r in rows) + "\n")
    s = read_series(p, topic=None, values=["y, m", "x, m"])
    np.testing.assert_array_equal(s.times_ns, [500_000_000, 1_500_000_000])
    np.testing.assert_array_equal(s.values, [[-2.0, 1.25], [0.4, 3.0]])


def test_text_table_delimiter_given_and_columns_with_comments(tmp_path: Path) -> None:
    p = tmp_path / "log.txt"
    p.write_text("# exported by a logger\n\n10|1.0|2.0\n# a comment mid-file\n20|3.0|4.0\n")
    s = read_series(
        p, topic=None, values=["b"], time="t", time_unit="ms", delimiter="|",
        columns=["t", "a", "b"],
    )  # fmt: skip
    np.testing.assert_array_equal(s.times_ns, [10_000_000, 20_000_000])
    np.testing.assert_array_equal(s.values[:, 0], [2.0, 4.0])


def test_tum_format(tmp_path: Path) -> None:
    p = tmp_path / "traj.txt"
    p.write_text(
        "# ground truth trajectory\n# timestamp tx ty tz qx qy qz qw\n"
        "1305031098.6659 1.3563 0.6305 1.6380 0.6132 0.5962 -0.3311 -0.3986\n"
        "1305031098.6758 1.3543 0.6306 1.6360 0.6129 0.5966 -0.3316 -0.3980\n"
    )
    s = read_series(p, topic=None, values=["tx", "tz", "qw"], format="tum")
    np.testing.assert_array_equal(s.times_ns, [1305031098665900000, 1305031098675800000])
    np.testing.assert_array_equal(s.values[1], [1.3543, 1.6360, -0.3980])


@pytest.mark.parametrize(
    ("text", "unit", "ns"),
    [
        ("1700000000.123456789", "s", 1700000000123456789),
        ("1403715524907143168", "ns", 1403715524907143168),
        ("46534.478375790000428", "s", 46534478375790),  # more digits than a double holds
        ("0.0000000015", "s", 2),  # half to even
        ("0.0000000025", "s", 2),
        ("0.0000000035", "s", 4),  # half to even: up
        ("1.5e-3", "s", 1_500_000),
        ("2.5e-9", "s", 2),  # an exponent: the same half to even as its plain digits
        ("25E-10", "s", 2),
        ("3.5e-9", "s", 4),
        ("0.5e-6", "ms", 0),
        ("1.5e-6", "ms", 2),
        (".25", "us", 250),
    ],
)
def test_decimal_times_become_whole_nanoseconds_from_their_digits(
    tmp_path: Path, text: str, unit: str, ns: int
) -> None:
    p = tmp_path / "t.csv"
    p.write_text(f"time,v\n{text},1\n")
    s = read_series(p, topic=None, values=["v"], time_unit=unit)
    assert int(s.times_ns[0]) == ns


def _fails(match: str, **kw) -> str:
    with pytest.raises(FusionlogError) as ei:
        read_series(**kw)
    msg = str(ei.value)
    assert "\n" not in msg and match in msg, msg
    return msg


def test_text_table_bad_shapes_are_one_line(tmp_path: Path) -> None:
    p = tmp_path / "t.txt"
    p.write_text("time x y\n1 2 3\n")
    _fails("delimiter ';' does not split line 1", source=p, topic=None, values=["x"],
           delimiter=";")  # fmt: skip
    _fails("line 1: 3 fields where columns has 2", source=p, topic=None, values=["x"],
           columns=["time", "x"])  # fmt: skip
    p.write_text("timexy\n1\n")
    _fails("no delimiter (comma, tab, semicolon, whitespace) splits it", source=p, topic=None,
           values=["x"])  # fmt: skip
    p.write_text("time,x\n1,2\n3\n")
    _fails("line 3: 1 fields where the header has 2", source=p, topic=None, values=["x"])


@pytest.mark.parametrize(
    ("row", "says"),
    [("1,1_000", "column 'x': '1_000' is not a number"),
     ("1,\uff11", "column 'x': '\uff11' is not a number"),
     ("1_0,1", "time column 'time' '1_0' is not a number"),
     ("\u0661,1", "time column 'time' '\u0661' is not a number")],
)  # fmt: skip
def test_cells_python_reads_but_a_table_does_not_hold_are_not_numbers(
    tmp_path: Path, row: str, says: str
) -> None:
    """float() and Decimal() read "1_000" and other scripts' digits: a table does not."""
    p = tmp_path / "t.csv"
    p.write_text(f"time,x\n{row}\n", encoding="utf-8")
    _fails(f"line 2: {says}", source=p, topic=None, values=["x"])


# -- bags ----------------------------------------------------------------------------------

N_FIX = 12


def _fixes() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Times (ns, not in order), lat/lon/alt, and per-message ENU covariances (3x3)."""
    rng = np.random.default_rng(5)
    t = 1_600_000_000_000_000_000 + np.arange(N_FIX) * 200_000_000
    t[[3, 4]] = t[[4, 3]]  # two messages out of time order in the file
    enu = np.cumsum(rng.normal(0, 1.0, (N_FIX, 3)), axis=0)
    lla = np.stack(pymap3d.enu2geodetic(*enu.T, LAT0, LON0, ALT0), axis=1)
    sd = rng.uniform(0.5, 3.0, (N_FIX, 1)) * np.array([1.0, 1.0, 2.0])
    cov = np.stack([np.diag(s**2) for s in sd])
    return t, lla, cov


def _write_bag(path: Path, ros: int, definitions: bool = True) -> None:
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if ros == 1 else Stores.ROS2_HUMBLE)
    T = ts.types
    Fix, Status = T["sensor_msgs/msg/NavSatFix"], T["sensor_msgs/msg/NavSatStatus"]
    Header, Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
    t, lla, cov = _fixes()
    msgs = []
    for i in range(N_FIX):
        stamp = Time(sec=int(t[i]) // 10**9, nanosec=int(t[i]) % 10**9)
        header = Header(seq=i, stamp=stamp, frame_id="gps") if ros == 1 else Header(
            stamp=stamp, frame_id="gps"
        )  # fmt: skip
        fix = Fix(header=header, status=Status(status=0, service=1), latitude=lla[i, 0],
                  longitude=lla[i, 1], altitude=lla[i, 2], position_covariance=cov[i].ravel(),
                  position_covariance_type=2)  # fmt: skip
        msgs.append(fix)
    record = 1_600_000_000_000_000_000 + np.arange(N_FIX) * 200_000_000 + 50_000_000
    if ros == 1:
        from rosbags.rosbag1 import Writer

        with Writer(path) as w:
            c = w.add_connection("/fix", Fix.__msgtype__, typestore=ts)
            for r, m in zip(record, msgs, strict=True):
                w.write(c, int(r), ts.serialize_ros1(m, Fix.__msgtype__))
        return
    from rosbags.rosbag2 import Writer

    with Writer(path, version=8) as w:
        c = w.add_connection("/fix", Fix.__msgtype__, typestore=ts)
        for r, m in zip(record, msgs, strict=True):
            w.write(c, int(r), ts.serialize_cdr(m, Fix.__msgtype__))
    if not definitions:  # as rosbag2 before Iron recorded: no definitions, no type hashes
        import re
        import sqlite3

        db = sqlite3.connect(next(path.glob("*.db3")))
        with db:
            db.execute("DELETE FROM message_definitions")
            db.execute("UPDATE topics SET type_description_hash = ''")
            db.execute("DELETE FROM metadata")
        db.close()
        meta = path / "metadata.yaml"
        text = re.sub(r"type_description_hash:\s*\n?\s*RIHS01_\w+", "type_description_hash: ''",
                      meta.read_text())  # fmt: skip
        meta.write_text(text)


@pytest.mark.parametrize("ros", [1, 2])
def test_bag_topic_reads_fields_times_and_covariances(tmp_path: Path, ros: int) -> None:
    path = tmp_path / ("log.bag" if ros == 1 else "log_ros2")
    _write_bag(path, ros)
    t, lla, cov = _fixes()
    order = np.argsort(t, kind="stable")
    sources = [path] if ros == 1 else [path, next(path.glob("*.db3"))]
    for src in sources:
        assert source_kind(src) == "bag"
        s = read_series(src, topic="/fix", values=["latitude", "longitude", "altitude"],
                        time="header.stamp", covariance="position_covariance")  # fmt: skip
        np.testing.assert_array_equal(s.times_ns, t[order])
        np.testing.assert_array_equal(s.values, lla[order])
        np.testing.assert_array_equal(s.cov, cov[order])
        assert s.notes == ("1 message out of time order (sorted)",)
        # without `time`: the record time; covariance_index picks the east-north block
        s = read_series(src, topic="/fix", values=["latitude", "longitude"],
                        covariance="position_covariance", covariance_index=[0, 1])  # fmt: skip
        np.testing.assert_array_equal(np.diff(s.times_ns), 200_000_000)
        np.testing.assert_array_equal(s.cov, cov[:, :2, :2])


def test_ros2_bag_without_definitions_decodes_standard_types(tmp_path: Path) -> None:
    path = tmp_path / "nodefs"
    _write_bag(path, 2, definitions=False)
    s = read_series(path, topic="/fix", values=["latitude"], time="header.stamp")
    t, lla, _ = _fixes()
    np.testing.assert_array_equal(s.values[:, 0], lla[np.argsort(t, kind="stable"), 0])


def test_bag_errors_are_one_line(tmp_path: Path) -> None:
    path = tmp_path / "log.bag"
    _write_bag(path, 1)
    _fails("no topic /gps in the bag (topics: /fix)", source=path, topic="/gps", values=["x"])
    _fails("topic /fix (sensor_msgs/msg/NavSatFix): no field lat", source=path, topic="/fix",
           values=["lat"])  # fmt: skip
    _fails("needs a topic", source=path, topic=None, values=["latitude"])
    bad = tmp_path / "bad.bag"
    bad.write_bytes(b"#ROSBAG V2.0\nnot a bag")
    _fails("damaged or not a ROS bag", source=bad, topic="/fix", values=["latitude"])


def test_a_damaged_bag_is_not_sent_to_inspect_recover(tmp_path: Path) -> None:
    """`inspect --recover` reads MCAP only: a damaged bag's error does not point there, and
    `inspect --recover` on a bag says it is a bag (not "damaged: not a valid MCAP", exit 0)."""
    bad = tmp_path / "bad.bag"
    bad.write_bytes(b"#ROSBAG V2.0\nnot a bag")
    line = one_line_error(cli("inspect", bad), str(bad), "damaged or not a ROS bag")
    assert "--recover" not in line
    f = tmp_path / "replay.toml"
    f.write_text(_BASE + 'source = "bad.bag"\ntopic = "/fix"\nvalues = ["latitude", "longitude"]\n'
                 "geodetic = true\n")  # fmt: skip
    line = one_line_error(cli("import", f, "-o", tmp_path / "s.mcap"), "damaged or not a ROS bag")
    assert "--recover" not in line and not (tmp_path / "s.mcap").exists()
    _write_bag(tmp_path / "ros2", 2)
    for target in (bad, tmp_path / "ros2"):
        one_line_error(cli("inspect", "--recover", target), str(target), "is a ROS bag",
                       "--recover reads damaged MCAP files only")  # fmt: skip


@pytest.mark.parametrize("named", ["folder", "db3"])
def test_import_never_writes_onto_a_file_of_a_bag_folder(tmp_path: Path, named: str) -> None:
    """A ROS 2 bag is its folder's files: neither its .db3 nor its metadata.yaml is ever an
    output, whichever of them the replay names (even with --force)."""
    bag = tmp_path / "ros2"
    _write_bag(bag, 2)
    db3 = next(bag.glob("*.db3"))
    source = "ros2" if named == "folder" else f"ros2/{db3.name}"
    f = tmp_path / "replay.toml"
    f.write_text(_BASE + f'source = "{source}"\ntopic = "/fix"\n'
                 'values = ["latitude", "longitude"]\ngeodetic = true\n')  # fmt: skip
    before = {p.name: p.read_bytes() for p in bag.iterdir()}
    for target in (db3, bag / "metadata.yaml"):
        res = cli("import", f, "-o", target, "--force")
        one_line_error(res, str(target), "is an input of this command, not an output")
    assert {p.name: p.read_bytes() for p in bag.iterdir()} == before


# -- geodetic ------------------------------------------------------------------------------


def test_geodetic_fixes_to_enu_about_the_first_fix_in_time_order(tmp_path: Path) -> None:
    path = tmp_path / "log.bag"
    _write_bag(path, 1)
    t, lla, _ = _fixes()
    s = read_series(path, topic="/fix", values=["latitude", "longitude", "altitude"],
                    time="header.stamp")  # fmt: skip
    enu, origin = to_enu(path, "sensors[0]", s, None)
    first = lla[np.argmin(t)]
    assert origin == tuple(first)
    # independent: the fixes were made from ENU about (LAT0, LON0, ALT0); about the first fix
    # they are those ENU minus the first one's, rotated by the small difference of the planes
    want = np.stack(pymap3d.geodetic2enu(*lla.T, *first), axis=1)[np.argsort(t, kind="stable")]
    np.testing.assert_allclose(enu.values, want, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(enu.values[0], [0.0, 0.0, 0.0])
    two, _ = to_enu(path, "sensors[0]", s.__class__(s.times_ns, s.values[:, :2], None, ()), None)
    np.testing.assert_allclose(two.values, want[:, :2], rtol=0, atol=1e-3)


@pytest.mark.parametrize(
    ("col", "value", "match"),
    [(0, 91.0, "latitude 91 "), (0, -4.6e6, "outside ±90"), (1, 500.0, "longitude 500 ")],
)
def test_geodetic_values_that_are_not_degrees(tmp_path: Path, col, value, match) -> None:
    p = tmp_path / "fix.csv"
    rows = [[0, LAT0, LON0, ALT0], [1, LAT0, LON0, ALT0]]
    rows[1][col + 1] = value
    p.write_text("time,lat,lon,alt\n" + "\n".join(",".join(map(str, r)) for r in rows) + "\n")
    s = read_series(p, topic=None, values=["lat", "lon", "alt"])
    with pytest.raises(FusionlogError) as ei:
        to_enu(p, "sensors[0]", s, None)
    msg = str(ei.value)
    assert match in msg and "values must be degrees" in msg and "\n" not in msg, msg


# -- truth association ---------------------------------------------------------------------


def test_associate_nearest_interpolate_exact_by_hand() -> None:
    times = np.array([100, 200, 300, 400])
    vals = np.array([[1.0], [2.0], [4.0], [8.0]])
    instants = np.array([90, 150, 249, 300, 351, 390, 500])
    nearest = associate(instants, times, vals, "nearest", 50)
    # 90 -> 100; 150 -> a tie between 100 and 200: the earlier; 249 -> 200 (49 away);
    # 300 -> 300; 351 -> 51 from 300 and 49 from 400: 400; 390 -> 400; 500 -> none within 50
    np.testing.assert_array_equal(nearest[:, 0], [1, 1, 2, 4, 8, 8, np.nan])
    inter = associate(instants, times, vals, "interpolate", 60)
    # 90: nothing before; 150: 1.5; 249: 2 + 0.49 * 2; 300: the sample; 351: 4 + 0.51 * 4,
    # both within 60; 390: 300 is 90 away; 500: nothing after
    np.testing.assert_allclose(inter[:, 0], [np.nan, 1.5, 2.98, 4.0, 6.04, np.nan, np.nan])
    exact = associate(instants, times, vals, "exact", 0)
    np.testing.assert_array_equal(exact[:, 0], [np.nan] * 3 + [4.0] + [np.nan] * 3)


def test_associate_takes_samples_exactly_max_diff_away() -> None:
    """ "Within max_diff" includes max_diff itself, in whole nanoseconds: samples at 0, 200,
    300 and 1000 ns, max_diff 100 ns. Interpolated: 100 is 100 from both 0 and 200
    (the mean, 2.5); 250 between 200 and 300, 50 from each (6); 101 is 101 from 0 (none).
    Nearest: 400 is 100 from 300; 900 is 100 from 1000; 401 is 101 from both (none)."""
    times = np.array([0, 200, 300, 1000], dtype=np.int64)
    vals = np.array([[1.0], [4.0], [8.0], [16.0]])
    inter = associate(np.array([100, 250, 101]), times, vals, "interpolate", 100)
    np.testing.assert_array_equal(inter[:, 0], [2.5, 6.0, np.nan])
    nearest = associate(np.array([400, 900, 401, 100]), times, vals, "nearest", 100)
    np.testing.assert_array_equal(nearest[:, 0], [8.0, 16.0, np.nan, 1.0])


# -- replay files: the one-line error of each new key --------------------------------------

_BASE = """
[scenario]
name = "t"
state_names = ["x", "vx", "y", "vy"]
[model]
kind = "constant-velocity"
axes = 2
n0 = 0.1
[prior]
mean = [0.0, 0.0, 0.0, 0.0]
cov = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
[[sensors]]
name = "s"
H = [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]
R = [[1.0, 0.0], [0.0, 1.0]]
"""


@pytest.fixture
def logs(tmp_path: Path) -> Path:
    (tmp_path / "xy.txt").write_text("time x y\n0 1 2\n1 2 3\n2 3 4\n")
    (tmp_path / "late.txt").write_text("time x\n0.5 1\n1.5 2\n")
    (tmp_path / "fix.csv").write_text(f"time,lat,lon\n0,{LAT0},{LON0}\n1,95.0,{LON0}\n")
    _write_bag(tmp_path / "log.bag", 1)
    return tmp_path


@pytest.mark.parametrize(
    ("sensor", "truth", "fragments"),
    [
        ('source = "xy.txt"\nvalues = ["x", "y"]\ndelimiter = ";"', "",
         ["xy.txt", "delimiter ';' does not split line 1"]),
        ('source = "xy.txt"\nvalues = ["x", "y"]\ncolumns = ["time", "x", "y", "z"]', "",
         ["xy.txt", "line 1: 3 fields where columns has 4"]),
        ('source = "xy.txt"\nvalues = ["x", "y"]\ncolumns = ["time", "x", "y"]\n'
         'format = "tum"', "", ["sensors[0].columns", "not used with format = 'tum'"]),
        ('source = "xy.txt"\nvalues = ["x", "y"]\nformat = "kitti"', "",
         ["sensors[0].format", "unknown format 'kitti'"]),
        ('source = "xy.txt"\nvalues = ["x", "y"]\ndelimiter = ",,"', "",
         ["sensors[0].delimiter", "expected one character"]),
        ('source = "log.bag"\ntopic = "/gps"\nvalues = ["latitude", "longitude"]\n'
         "geodetic = true", "", ["log.bag", "no topic /gps in the bag (topics: /fix)"]),
        ('source = "log.bag"\nvalues = ["latitude", "longitude"]\ngeodetic = true', "",
         ["sensors[0].topic", "missing required key"]),
        ('source = "."\ntopic = "/fix"\nvalues = ["x", "y"]', "",
         ["sensors[0].source", "is a folder but not a ROS 2 bag (no metadata.yaml"]),
        ('source = "."\nvalues = ["x", "y"]', "",
         ["sensors[0].source", "is a folder but not a ROS 2 bag (no metadata.yaml"]),
        ('source = "log.bag"\ntopic = "/fix"\nvalues = ["latitude", "longitude"]', "",
         ["sensors[0].values", "'latitude' is in degrees: give geodetic = true"]),
        ('source = "fix.csv"\nvalues = ["lat", "lon"]\ngeodetic = true', "",
         ["fix.csv", "latitude 95 ", "outside ±90"]),
        ('source = "fix.csv"\nvalues = ["lat", "lon"]\ngeodetic = true\norigin = [1.0, 2.0]',
         "", ["sensors[0].origin", "expected [latitude, longitude, altitude]"]),
        ('source = "fix.csv"\nvalues = ["lat", "lon"]\ngeodetic = true\n'
         "origin = [91.0, 2.0, 0.0]", "", ["sensors[0].origin", "latitude 91 is outside ±90"]),
        ('source = "fix.csv"\nvalues = ["lat", "lon"]\ngeodetic = "yes"', "",
         ["sensors[0].geodetic", "expected true or false"]),
        ('source = "xy.txt"\nvalues = ["x", "y"]',
         '[truth]\nsource = "xy.txt"\nvalues = ["x"]\nstates = ["x"]\nmax_diff = 0.0',
         ["truth.max_diff", "must be > 0 seconds"]),
        ('source = "xy.txt"\nvalues = ["x", "y"]',
         '[truth]\nsource = "xy.txt"\nvalues = ["x"]\nstates = ["x"]\nmax_diff = -1',
         ["truth.max_diff", "must be > 0 seconds"]),
        ('source = "xy.txt"\nvalues = ["x", "y"]',
         '[truth]\nsource = "xy.txt"\nvalues = ["x"]\nstates = ["x"]\nmatch = "closest"',
         ["truth.match", "unknown match 'closest'"]),
        ('source = "xy.txt"\nvalues = ["x", "y"]',
         '[truth]\nsource = "late.txt"\nvalues = ["x"]\nstates = ["x"]\nmatch = "exact"',
         ["late.txt", "truth: none of its 2 samples is at an instant"]),
        ('source = "xy.txt"\nvalues = ["x", "y"]',
         '[truth]\nsource = "late.txt"\nvalues = ["x"]\nstates = ["x"]\nmax_diff = 0.4',
         ["late.txt", "truth: none of its 2 samples is within max_diff = 0.4 s"]),
    ],
)  # fmt: skip
def test_bad_input_of_each_new_key_is_one_line(logs: Path, sensor, truth, fragments) -> None:
    f = logs / "replay.toml"
    f.write_text(_BASE + sensor + "\n" + truth + "\n")
    one_line_error(cli("import", f, "-o", logs / "s.mcap"), *fragments)
    assert not (logs / "s.mcap").exists()


def test_sensors_that_do_not_overlap_in_time_are_noted(logs: Path) -> None:
    """One sensor on header stamps, one on the record time days later: the instants are still
    their union, and the gap is said (not predicted across in silence)."""
    (logs / "later.txt").write_text("time x y\n172800 1 2\n172801 2 3\n")
    f = logs / "replay.toml"
    f.write_text(
        _BASE + 'source = "xy.txt"\nvalues = ["x", "y"]\n[[sensors]]\nname = "u"\n'
        'source = "later.txt"\nvalues = ["x", "y"]\ntime = "time"\n'
        "H = [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]\nR = [[1.0, 0.0], [0.0, 1.0]]\n"
    )
    res = ok("import", f, "-o", logs / "s.mcap")
    assert (
        "note: u and s do not overlap in time: u's first reading is 172798 s (2 days) after "
        "s's last (u: time = 'time', s: the default time)"
    ) in res.stdout, res.stdout
    (logs / "later.txt").write_text("time x y\n1.5 1 2\n2.5 2 3\n")
    assert "overlap" not in ok("import", f, "-o", logs / "s.mcap", "--force").stdout


def test_truth_without_prior_runs_with_truth_metrics(logs: Path) -> None:
    """[truth] without [prior]: the filters start with no information; the truth metrics are
    there, the exact expected values (which need an initial distribution) are not."""
    f = logs / "replay.toml"
    base = _BASE.replace("[prior]\nmean = [0.0, 0.0, 0.0, 0.0]\n", "").replace(
        "cov = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], "
        "[0.0, 0.0, 0.0, 1.0]]\n", ""
    )  # fmt: skip
    f.write_text(base + 'source = "xy.txt"\nvalues = ["x", "y"]\n[truth]\nsource = "xy.txt"\n'
                 'values = ["x", "y"]\nstates = ["x", "y"]\n')  # fmt: skip
    res = cli("run", f, "--out-dir", logs / "out", "--arch", "CKF")
    assert res.exit_code == 0, (res.output, res.exception)


# -- inspect -------------------------------------------------------------------------------


def test_inspect_bags_lists_field_paths_types_and_first_values(tmp_path: Path) -> None:
    _write_bag(tmp_path / "log.bag", 1)
    _write_bag(tmp_path / "ros2", 2)
    t, lla, _ = _fixes()
    for target in (
        tmp_path / "log.bag",
        tmp_path / "ros2",
        next((tmp_path / "ros2").glob("*.db3")),
    ):
        out = ok("inspect", target).stdout
        assert "/fix" in out and f"{N_FIX} messages" in out and "sensor_msgs/msg/NavSatFix" in out
        lines = {ln.split()[0]: ln.split()[1:] for ln in out.splitlines()[2:] if ln.strip()}
        assert lines["latitude"][0] == "float"
        assert float(lines["latitude"][1]) == pytest.approx(lla[0, 0], rel=1e-9)
        assert lines["header.stamp.sec"] == ["int", str(int(t[0]) // 10**9)]
        assert lines["position_covariance"][0] == "float[9]"


def test_inspect_lists_the_fields_of_foreign_mcap_topics() -> None:
    root = Path(__file__).resolve().parents[1]
    out = ok("inspect", root / "pipeline/data/robot_ros2.mcap").stdout
    for fragment in ("twist.twist.linear.x", "pose.covariance", "float[36]", "header.stamp.sec"):
        assert fragment in out, fragment


def test_inspect_on_a_folder_that_is_not_a_bag(tmp_path: Path) -> None:
    one_line_error(cli("inspect", tmp_path), str(tmp_path), "not a ROS 2 bag")


def test_run_workers_on_a_replay_is_a_one_line_error(logs: Path) -> None:
    f = logs / "replay.toml"
    f.write_text(_BASE + 'source = "xy.txt"\nvalues = ["x", "y"]\n')
    res = cli("run", f, "--out-dir", logs / "out", "--workers", "1")
    one_line_error(res, "a replay is one recorded run", "without --workers")
    assert not (logs / "out").exists()


@pytest.mark.parametrize("flag", ["--runs", "--steps", "--seed"])
def test_monte_carlo_flags_on_a_replay_are_refused_not_ignored(logs: Path, flag: str) -> None:
    """A replay is one recorded run on its measurement times: `run --runs 5` said nothing and
    ran one, as the file's own scenario.runs/steps/seed are refused."""
    f = logs / "replay.toml"
    f.write_text(_BASE + 'source = "xy.txt"\nvalues = ["x", "y"]\n')
    res = cli("run", f, "--out-dir", logs / "out", flag, "5")
    one_line_error(res, str(f), f"{flag}: not used with a replay file")
    assert not (logs / "out").exists()


def test_simulate_on_a_replay_is_a_one_line_error(logs: Path) -> None:
    """`simulate` of a replay wrote one simulated instant from its model and prior (the
    recorded readings ignored): it points to `import` instead."""
    f = logs / "replay.toml"
    f.write_text(_BASE + 'source = "xy.txt"\nvalues = ["x", "y"]\n')
    res = cli("simulate", f, "-o", logs / "s.mcap")
    one_line_error(res, str(f), "a replay file: its readings are recorded, not simulated",
                   "fusionlog import")  # fmt: skip
    assert not (logs / "s.mcap").exists()


def test_sweep_on_a_replay_is_a_one_line_error(logs: Path) -> None:
    f = logs / "replay.toml"
    f.write_text(_BASE + 'source = "xy.txt"\nvalues = ["x", "y"]\n')
    res = cli("sweep", f, "--vary", "model.n0=0.1,0.2", "--workers", "0", "--out-dir", logs / "o")
    one_line_error(res, "a replay is one recorded run")
    assert not (logs / "o").exists()


def test_the_example_logs_are_remade_byte_for_byte(tmp_path: Path) -> None:
    """pipeline/data/make_more_logs.py writes the committed ROS 1 bag, truth table and TUM
    files again, the same bytes (no CPU-dependent kernels in it)."""
    import runpy

    root = Path(__file__).resolve().parents[1]
    script = root / "pipeline" / "data" / "make_more_logs.py"
    runpy.run_path(str(script), run_name="make_more_logs")["main"](["--out", str(tmp_path)])
    for name in ("gps_ros1.bag", "gps_truth.tsv", "tum_slam.txt", "tum_mocap.txt"):
        assert (tmp_path / name).read_bytes() == (root / "pipeline" / "data" / name).read_bytes()
