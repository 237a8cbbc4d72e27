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


def test_a_long_log_keeps_the_states_and_decimates_the_overview(recording, monkeypatch) -> None:
    """Above OVERVIEW_POINTS instants the overview series keep every n-th value, the first
    run's estimates, truth and readings every value, and the recording says which."""
    import json

    from fusionlog.io.rrd import decimation as dec

    small = recording.parent.parent
    monkeypatch.setattr(dec, "OVERVIEW_POINTS", 40)
    ok("run", small / "small.toml", "--out-dir", small / "long", "--force")
    rec = read_recording(small / "long" / "evaluation.rrd")
    full, short = rec["series"], read_recording(recording)["series"]
    for key in ("runs/0/x/CKF/mean", "runs/0/x/measured/pos", "runs/0/x/truth"):
        np.testing.assert_array_equal(np.isfinite(full[key]), np.isfinite(short[key]), key)
    prop = rec["properties"]["decimation"]
    instants = len(short["runs/0/x/CKF/mean"])  # 200 position and 100 velocity instants
    n = -(-instants // 40)
    assert prop["instants"] == str(instants) == "300" and f"every {n}th" in prop["decimated"]
    for key in ("metrics/nis/CKF/pos", "innovations/pos/z0/CKF", "runs/0/x/CKF/upper"):
        n_full, n_dec = np.isfinite(short[key]).sum(), np.isfinite(full[key]).sum()
        assert n_dec == -(-n_full // n), (key, n_full, n_dec)
    assert "every instant" in prop["full_resolution"]
    assert json.loads(rec["properties"]["summary"]["json"])["scenario"] == "small"


def test_decimation_strides() -> None:
    from fusionlog.io.rrd.decimation import decimation

    assert decimation(100_000, 10) == (None, {})
    stride, prop = decimation(1_000_000, 10)
    assert stride("metrics/nis/CKF/gps") == 10 and stride("runs/0/x/CKF/upper") == 10
    assert stride("runs/0/x/CKF/mean") == 1 and stride("runs/0/x/measured/gps") == 1
    stride, _ = decimation(1_000_000, 40)  # 4e7 values: every 4th
    assert stride("runs/0/x/truth") == 4


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
