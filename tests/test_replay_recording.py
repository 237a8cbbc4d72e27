"""A replay's recording opens on what one log needs (io/rrd/log_recording.py): the trajectory in the
plane (each sensor's readings, the estimates, the truth), each state over time with ±2σ, NIS
per sensor with its χ² band, the normalised innovations; ranges not flattened by the start."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from cli_helpers import ok

from fusionlog.io.rrd import read_recording
from fusionlog.io.rrd.log_recording import plane_states, replay_blueprint, view_range

REPLAY = """
[scenario]
name = "small"
state_names = ["x", "vx", "y", "vy"]
[model]
kind = "constant-velocity"
axes = 2
n0 = 0.1
[prior]
mean = [0.0, 0.0, 0.0, 0.0]
cov = [[100.0, 0.0, 0.0, 0.0], [0.0, 100.0, 0.0, 0.0], [0.0, 0.0, 100.0, 0.0],
       [0.0, 0.0, 0.0, 100.0]]
[[sensors]]
name = "pos"
source = "pos.txt"
values = ["x", "y"]
H = [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]
R = [[0.04, 0.0], [0.0, 0.04]]
[[sensors]]
name = "vel"
source = "vel.txt"
values = ["vx", "vy"]
H = [[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
R = [[0.01, 0.0], [0.0, 0.01]]
[truth]
source = "truth.txt"
values = ["x", "y"]
states = ["x", "y"]
match = "interpolate"
max_diff = 0.2
[estimate]
architectures = ["CKF", "MSC"]
"""


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("small")
    rng = np.random.default_rng(3)
    t = np.arange(0, 20, 0.1)
    x, y = np.cos(t / 3) * 5, np.sin(t / 3) * 5
    zx, zy = x + rng.normal(0, 0.2, t.size), y + rng.normal(0, 0.2, t.size)
    rows = "\n".join(f"{a:.2f} {b:.5f} {c:.5f}" for a, b, c in zip(t, zx, zy, strict=True))
    (d / "pos.txt").write_text("time x y\n" + rows + "\n")
    tv = t[::2] + 0.05
    rows = "\n".join(
        f"{a:.2f},{-np.sin(a / 3) * 5 / 3:.5f},{np.cos(a / 3) * 5 / 3:.5f}" for a in tv
    )
    (d / "vel.txt").write_text("time,vx,vy\n" + rows + "\n")
    tt = np.arange(0, 20, 0.15)
    rows = "\n".join(f"{a:.2f};{np.cos(a / 3) * 5:.6f};{np.sin(a / 3) * 5:.6f}" for a in tt)
    (d / "truth.txt").write_text("time;x;y\n" + rows + "\n")
    (d / "small.toml").write_text(REPLAY)
    ok("run", d / "small.toml", "--out-dir", d / "run")
    return d / "run" / "evaluation.rrd"


def _static_entities(path: Path) -> set[str]:
    from rerun.chunk import RrdReader

    return {
        str(ch.entity_path)
        for ch in RrdReader(str(path)).store().stream().to_chunks()
        if ch.is_static
    }


def test_replay_recording_has_trajectory_innovations_and_nis_per_sensor(recording) -> None:
    static = _static_entities(recording)
    for e in ("/trajectory/truth", "/trajectory/estimates/CKF", "/trajectory/estimates/MSC",
              "/trajectory/measured/pos"):  # fmt: skip
        assert e in static, e
    assert "/trajectory/measured/vel" not in static  # it reads velocities, not the plane
    series = read_recording(recording)["series"]
    for arch in ("CKF", "MSC"):
        for sensor in ("pos", "vel"):
            assert f"metrics/nis/{arch}/{sensor}" in series
            assert f"metrics/nis/{arch}/{sensor}/upper" in series
            for c in ("z0", "z1"):
                nu = series[f"innovations/{sensor}/{c}/{arch}"]
                have = nu[np.isfinite(nu)]
                assert have.size > 10 and 0.2 < np.std(have) < 3.0  # normalised
    assert np.all(series["innovations/bounds/upper"] == 2.0)
    # each state over time with its ±2σ band and the readings of the sensor that measures it
    for k in ("runs/0/x/CKF/mean", "runs/0/x/CKF/upper", "runs/0/x/measured/pos",
              "runs/0/vx/measured/vel", "runs/0/x/truth"):  # fmt: skip
        assert k in series, k


def test_view_range_is_not_flattened_by_the_start() -> None:
    k = np.arange(1000)
    trace = 0.5 + 0.01 * np.sin(k / 10.0)
    trace[:3] = [1e4, 50.0, 5.0]  # a prior's transient
    lo, hi = view_range([trace], floor=0.0)
    assert 0.4 < lo < 0.49 and 0.51 < hi < 0.6, (lo, hi)


def test_replay_blueprint_tabs() -> None:
    n, K1 = 4, 200
    names = ["x", "vx", "y", "vy"]
    measured = {0: {"pos": np.zeros(K1)}, 2: {"pos": np.zeros(K1)}, 1: {"vel": np.zeros(K1)}}
    assert plane_states(names, measured) == (0, 2)
    est = {"CKF": (np.zeros((K1, n)), np.ones((K1, n)))}
    band = (np.ones(K1), np.zeros(K1), np.full(K1, 6.0))
    nis = {"CKF": {"pos": band, "vel": band}}
    inn = {"CKF": {"pos": np.zeros((K1, 2)), "vel": np.zeros((K1, 2))}}
    bp = replay_blueprint(names, (0, 2), {0: (np.zeros((K1, n)), est)}, nis, inn,
                          {"CKF": np.ones(K1)}, (np.zeros(K1), np.full(K1, 9.0)),
                          {"CKF": np.ones(K1)}, "time")  # fmt: skip
    tabs = [c.name for c in bp.root_container.contents]
    assert tabs[0].startswith("Trajectory (x, y)")
    assert tabs[1:] == ["States", "NIS", "Innovations", "Errors"]
    assert not any("Fig. 4" in str(t) for t in tabs)
    nis_views = [v.name for v in bp.root_container.contents[2].contents]
    assert nis_views == ["NIS of pos (grey: χ² band)", "NIS of vel (grey: χ² band)"]


def test_a_long_log_keeps_each_buckets_extremes_and_mean(recording, monkeypatch) -> None:
    """Above DECIMATE_ABOVE instants every series (metrics, NIS, innovations, bands, the first
    run's states and readings, APE/RPE) is three points per bucket of instants, at its first,
    middle and last instant: the bucket's finite minimum and maximum in the order they come,
    and its mean between them, checked here against the full recording of the same log;
    the recording says so, and `[evaluate] full_resolution = true` keeps every instant."""
    import json

    from fusionlog.core import decimate

    small = recording.parent.parent
    monkeypatch.setattr(decimate, "DECIMATE_ABOVE", 40)
    monkeypatch.setattr(decimate, "BUCKETS", 10)
    ok("run", small / "small.toml", "--out-dir", small / "long", "--force")
    rec, full = read_recording(small / "long" / "evaluation.rrd"), read_recording(recording)
    instants = len(full["steps"])
    assert instants == 300 and np.array_equal(full["steps"], np.arange(300))
    b = 30  # ceil(300 / 10) instants per bucket
    prop = rec["properties"]["decimation"]
    assert prop["instants"] == "300" and prop["bucket"] == str(b)
    starts = np.arange(0, instants, b)
    assert np.array_equal(rec["steps"], np.stack([starts, starts + 14, starts + 29], 1).ravel())
    checked = 0
    for key, v in full["series"].items():
        got = rec["series"][key].reshape(-1, 3)
        for j, a in enumerate(starts):
            bucket = v[a : a + b]
            bucket = bucket[np.isfinite(bucket)]
            if not len(bucket):
                assert np.isnan(got[j]).all(), (key, j)
                continue
            lo, hi = bucket.min(), bucket.max()
            first_lo = (
                np.flatnonzero(v[a : a + b] == lo)[0] <= np.flatnonzero(v[a : a + b] == hi)[0]
            )
            assert tuple(got[j, [0, 2]]) == ((lo, hi) if first_lo else (hi, lo)), (key, j)
            assert got[j, 1] == pytest.approx(bucket.mean(), rel=1e-12, abs=1e-300), (key, j)
            checked += 1
    assert checked > 500  # 76 series of 10 buckets
    for key in ("runs/0/x/CKF/mean", "runs/0/x/measured/pos", "metrics/nis/CKF/pos"):
        assert key in rec["series"]
    assert json.loads(rec["properties"]["summary"]["json"]) == json.loads(
        read_recording(recording)["properties"]["summary"]["json"]
    )
    text = (
        (small / "small.toml")
        .read_text()
        .replace("[estimate]", "[evaluate]\nfull_resolution = true\n[estimate]")
    )
    (small / "full.toml").write_text(text)
    ok("run", small / "full.toml", "--out-dir", small / "full", "--force")
    kept = read_recording(small / "full" / "evaluation.rrd")
    assert "decimation" not in kept["properties"]
    for key, v in full["series"].items():
        np.testing.assert_array_equal(kept["series"][key], v, err_msg=key)


def test_decimation_keeps_each_buckets_min_and_max_whatever_the_blocks() -> None:
    """`core.decimate` fed in blocks of any size gives the same points as fed at once, each
    bucket's min, mean and max (NaN left out, NaN for an empty bucket) computed here."""
    from fusionlog.core.decimate import Decimator, bucket_size, point_steps

    rng = np.random.default_rng(5)
    v = rng.normal(size=(1003, 2))
    v[rng.random(1003) < 0.2, 0] = np.nan
    v[70:105, 1] = np.nan  # bucket 7 (70..79) empty in column 1
    b = 10
    whole = Decimator(b)
    whole.add(v)
    pieces = Decimator(b)
    for a in range(0, 1003, 97):
        pieces.add(v[a : a + 97])
    out = whole.result()
    np.testing.assert_array_equal(pieces.result(), out)
    assert out.shape == (3 * 101, 2)
    steps = point_steps(1003, b)
    assert steps[-3:].tolist() == [1000, 1001, 1002] and steps[:3].tolist() == [0, 4, 9]
    for j in range(101):
        for c in range(2):
            seg = v[j * b : (j + 1) * b, c]
            fin = seg[np.isfinite(seg)]
            pts = out[3 * j : 3 * j + 3, c]
            if not len(fin):
                assert np.isnan(pts).all()
                continue
            assert {pts[0], pts[2]} == {fin.min(), fin.max()}
            assert pts[1] == pytest.approx(fin.mean(), rel=1e-12)
    assert bucket_size(30_000) == 1 and bucket_size(10**6) == 1000  # 1 000 buckets
    assert bucket_size(10**6, full_resolution=True) == 1


def test_each_sensor_has_one_colour_in_every_view(recording) -> None:
    """A sensor's readings are drawn in the same colour in the States views of every state it
    measures and in the trajectory, and two sensors never share one (pos measures x and y,
    vel vx and vy: each the only reading of its state, so a colour per view would repeat)."""
    from rerun.chunk import RrdReader

    colours: dict[str, set[int]] = {}
    for ch in RrdReader(str(recording)).store().stream().to_chunks():
        path = str(ch.entity_path)
        if ch.is_static and "/measured/" in path and path.startswith(("/runs/0/", "/traj")):
            st = ch.to_record_batch().to_pydict()
            col = (st.get("SeriesPoints:colors") or st.get("Points2D:colors"))[0][0]
            colours.setdefault(path.rsplit("/", 1)[1], set()).add(col)
    assert set(colours) == {"pos", "vel"}
    assert all(len(c) == 1 for c in colours.values()), colours
    assert colours["pos"] != colours["vel"]


def test_nis_legend_lists_the_band_once_and_every_architecture(recording) -> None:
    """Every architecture's χ² band of a sensor is named alike (as the NEES band), so a NIS
    view's legend has the band and one entry per architecture, not one per band and
    architecture (21 entries for seven architectures pushed most of them off the legend)."""
    from rerun.chunk import RrdReader

    names: dict[str, set[str]] = {}
    for ch in RrdReader(str(recording)).store().stream().to_chunks():
        path = str(ch.entity_path)
        if ch.is_static and path.startswith("/metrics/nis/"):
            sensor = path.split("/")[4]
            names.setdefault(sensor, set()).add(ch.to_record_batch().to_pydict()
                                                ["SeriesLines:names"][0][0])  # fmt: skip
    for sensor in ("pos", "vel"):
        assert names[sensor] == {
            "χ² 95% lower", "χ² 95% upper", f"CKF ({sensor})", f"MSC ({sensor})"
        }, names[sensor]  # fmt: skip
