"""The evaluation recording: write into a file object, verify with the rerun CLI, read back
offline, determinism, the default blueprint in the same file, refused data, damaged files.
Values against independent computations: test_rrd_values.py; write faults: test_rrd_faults.py."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import ok

from fusionlog.errors import FusionlogError
from fusionlog.io.atomic import Outputs
from fusionlog.io.rrd import (
    arch_color,
    entity_path,
    read_recording,
    recording_id_for,
    write_identity_recording,
    write_recording,
)
from fusionlog.io.rrd.legend import legend_box, place_legend

RERUN = Path(sys.executable).parent / "rerun"
if not RERUN.exists():  # pragma: no cover - rerun-sdk always ships the CLI next to python
    RERUN = Path(shutil.which("rerun") or "rerun")

STATES = ["pos", "vel x"]  # a space exercises entity-path escaping
ARCHS = ["CKF", "HKF", "SKF:s2"]  # so does the colon


def synthetic(archs: list[str] = ARCHS, steps: int = 6) -> dict:
    rng = np.random.default_rng(42)
    s, n = steps, len(STATES)
    series = {}
    for j, arch in enumerate(archs):
        mse = rng.random((s, n)) + j
        mse[0] = np.nan  # undefined at step 0: not logged
        series[arch] = {
            "mse": mse,
            "trace": rng.random(s),
            "nees": rng.random(s) + 1.5,
            "dm": rng.random(s) + 1.0,
            "expected_mse": rng.random((s, n)),
            "expected_nees": np.full(s, 2.0),
            "expected_dm": np.full(s, np.sqrt(np.pi / 2)),
        }
    truth = rng.normal(size=(s, n))
    sample_runs = {
        m: (truth + m, {a: (truth + rng.normal(size=(s, n)), rng.random((s, n))) for a in archs})
        for m in (0, 7)
    }
    summary = {
        "scenario": "synthetic",
        "seed": 5,
        "runs": 100,
        "steps": s - 1,
        "state_names": STATES,
        "architectures": {
            a: {
                "mse": 0.1 + i,
                "mse_per_state": [0.1, 0.2],
                "mean_trace": 0.3,
                "anees": 2.0,
                "nees_fraction_inside": 0.8,
                "dm": 1.25,
                "expected": {"mse": 0.1, "anees": 2.0, "dm": 1.2533},
            }
            for i, a in enumerate(archs)
        },
    }
    return {
        "scenario_name": "synthetic",
        "seed": 5,
        "times": np.arange(s) * 0.1,
        "state_names": STATES,
        "series": series,
        "summary": summary,
        "nees_bounds": (np.full(s, 1.6), np.full(s, 2.5)),
        "confidence": 0.95,
        "sample_runs": sample_runs,
        "properties": {
            "scenario": "[scenario]\nname = 'synthetic'\n",
            "provenance": {"fusionlog": "0.1.0", "command": "fusionlog evaluate", "argv": ["a"]},
        },
    }


def run_cli(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "RERUN_ANALYTICS": "0"}
    return subprocess.run(
        [str(RERUN), *args], capture_output=True, text=True, timeout=60, env=env, check=False
    )


def write(path: Path, writer=write_recording, **data) -> Path:
    """Through the one output path, as the stages do."""
    with Outputs([path], force=True) as outs:
        writer(outs.open(path), **data)
        outs.commit()
    return path


@pytest.fixture(scope="module")
def written(tmp_path_factory) -> tuple[Path, dict]:
    data = synthetic()
    path = write(tmp_path_factory.mktemp("rrd") / "evaluation.rrd", **data)
    return path, data


def test_rerun_verify_accepts_file(written) -> None:
    path, _ = written
    res = run_cli("rrd", "verify", str(path))
    assert res.returncode == 0, res.stderr


def test_read_back_series_and_summary(written) -> None:
    path, data = written
    got = read_recording(path)
    assert got["application_id"] == "fusionlog"
    assert got["recording_id"] == recording_id_for("synthetic", 5)
    assert got["name"] == "synthetic"
    assert got["summary"] == data["summary"]
    assert list(got["summary"]["architectures"]) == ARCHS  # order kept
    props = got["properties"]
    assert props["scenario"]["name"] == "synthetic" and props["scenario"]["seed"] == "5"
    assert props["scenario"]["text"] == data["properties"]["scenario"]
    assert props["provenance"]["command"] == "fusionlog evaluate"
    assert props["provenance"]["argv"] == '["a"]'  # non-scalars stored as JSON

    s = len(data["times"])
    np.testing.assert_array_equal(got["steps"], np.arange(s))
    np.testing.assert_allclose(got["times"], data["times"], atol=1e-9)
    ser = got["series"]
    for arch, d in data["series"].items():
        for i, state in enumerate(STATES):
            np.testing.assert_array_equal(
                ser[entity_path("metrics", "mse", state, arch)], d["mse"][:, i]
            )
            np.testing.assert_array_equal(
                ser[entity_path("metrics", "expected", "mse", state, arch)], d["expected_mse"][:, i]
            )
            if arch != "CKF":
                np.testing.assert_allclose(
                    ser[entity_path("metrics", "mse_minus_ckf", state, arch)],
                    d["mse"][:, i] - data["series"]["CKF"]["mse"][:, i],
                    rtol=1e-15,
                )
        for key in ("trace", "nees", "dm"):
            np.testing.assert_array_equal(ser[entity_path("metrics", key, arch)], d[key])
        np.testing.assert_array_equal(ser[entity_path("metrics", "expected", "nees", arch)], 2.0)
        np.testing.assert_array_equal(
            ser[entity_path("metrics", "expected", "dm", arch)], d["expected_dm"]
        )
    assert not any(k.startswith("metrics/mse_minus_ckf") and k.endswith("/CKF") for k in ser)
    np.testing.assert_array_equal(ser["metrics/nees/bounds/lower"], 1.6)
    np.testing.assert_array_equal(ser["metrics/nees/bounds/upper"], 2.5)
    for m, (truth, est) in data["sample_runs"].items():
        for i, state in enumerate(STATES):
            np.testing.assert_array_equal(ser[entity_path("runs", m, state, "truth")], truth[:, i])
            for arch, (mu, sd) in est.items():
                base = ("runs", m, state, arch)
                np.testing.assert_array_equal(ser[entity_path(*base, "mean")], mu[:, i])
                np.testing.assert_allclose(
                    ser[entity_path(*base, "upper")], mu[:, i] + 2 * sd[:, i]
                )
                np.testing.assert_allclose(
                    ser[entity_path(*base, "lower")], mu[:, i] - 2 * sd[:, i]
                )


def test_reading_only_the_summary_keeps_no_series(written) -> None:
    """`fusionlog summary` reads with series=False: the same summary and properties, and none
    of the series (a 10^6-instant log's recording decoded whole took ~2 GB to print a table)."""
    path, _ = written
    full, only = read_recording(path), read_recording(path, series=False)
    for key in ("application_id", "recording_id", "name", "properties", "summary"):
        assert only[key] == full[key], key
    assert only["series"] == {} and only["steps"].size == only["times"].size == 0
    assert json.loads(ok("summary", path, "--json").stdout) == full["summary"]


def test_escaped_entity_paths(written) -> None:
    path, _ = written
    keys = read_recording(path)["series"]
    assert "metrics/mse/vel\\ x/SKF\\:s2" in keys
    assert "metrics/trace/HKF" in keys


def static_styles(path: Path, prefix: str) -> dict[str, dict]:
    from rerun.chunk import RrdReader

    return {
        str(ch.entity_path): ch.to_record_batch().to_pydict()
        for ch in RrdReader(str(path)).store().stream().to_chunks()
        if ch.is_static and str(ch.entity_path).startswith(prefix)
    }


def test_styling_and_blueprint_in_the_same_file(written) -> None:
    from rerun.chunk import RrdReader

    path, _ = written
    reader = RrdReader(str(path))
    bps = reader.blueprints()
    assert len(bps) == 1, "default blueprint missing"
    assert bps[0].application_id == "fusionlog"
    ckf = static_styles(path, "/metrics/trace/")["/metrics/trace/CKF"]
    assert ckf["SeriesLines:names"] == [["CKF"]]
    assert ckf["SeriesLines:colors"][0][0] == int.from_bytes(bytes([*arch_color("CKF"), 255]))


def test_one_legend_entry_per_architecture(written) -> None:
    """Expected values (dots) and the ±2σ band share their architecture's legend name, so the
    legend lists each architecture once (14 entries for 7 architectures covered Fig. 4)."""
    path, _ = written
    names = set()
    for p, st in static_styles(path, "/").items():
        for key in ("SeriesLines:names", "SeriesPoints:names"):
            if key in st and (p.startswith("/metrics/expected/mse/") or p.startswith("/runs/")):
                names.add(st[key][0][0])
    assert names == {*ARCHS, "truth"}


def test_identical_writes_compare_equal(tmp_path: Path) -> None:
    a, b, c = tmp_path / "a.rrd", tmp_path / "b.rrd", tmp_path / "c.rrd"
    write(a, **synthetic())
    write(b, **synthetic())
    res = run_cli("rrd", "compare", "--unordered", str(a), str(b))
    assert res.returncode == 0, res.stdout + res.stderr
    other = synthetic()
    other["series"]["HKF"]["dm"] = other["series"]["HKF"]["dm"] + 1e-6
    write(c, **other)
    assert run_cli("rrd", "compare", "--unordered", str(a), str(c)).returncode != 0


def test_plain_binary_file_works_too(tmp_path: Path) -> None:
    """Any binary file object will do (no path, no Rerun file sink)."""
    path = tmp_path / "plain.rrd"
    with open(path, "wb") as f:
        write_recording(f, **synthetic())
    assert read_recording(path)["summary"]["scenario"] == "synthetic"
    assert run_cli("rrd", "verify", str(path)).returncode == 0


def test_without_ckf_no_difference_entities(tmp_path: Path) -> None:
    path = write(tmp_path / "e.rrd", **synthetic(archs=["HKF", "MSC"]))
    keys = read_recording(path)["series"]
    assert not any(k.startswith("metrics/mse_minus_ckf") for k in keys)
    assert "metrics/mse/pos/MSC" in keys


def test_a_single_instant_is_drawn_as_markers(tmp_path: Path) -> None:
    """steps = 0 (one static fusion): a line of one value is not drawn at all, which left
    Fig. 5 and every Monte Carlo curve of the Overview empty; each series is then a marker of
    its architecture's name and colour, with the same entity paths and values."""
    data = synthetic(steps=1)
    path = write(tmp_path / "e.rrd", **data)
    styles = static_styles(path, "/metrics/")
    for p in ("/metrics/mse/pos/HKF", "/metrics/mse_minus_ckf/pos/HKF", "/metrics/trace/CKF",
              "/metrics/nees/CKF", "/metrics/dm/CKF", "/metrics/nees/bounds/upper"):  # fmt: skip
        assert "SeriesLines:names" not in styles[p], p
        assert styles[p]["SeriesPoints:names"][0], p
    assert styles["/metrics/trace/CKF"]["SeriesPoints:names"] == [["CKF"]]
    assert styles["/metrics/trace/CKF"]["SeriesPoints:colors"][0][0] == int.from_bytes(
        bytes([*arch_color("CKF"), 255])
    )
    series = read_recording(path)["series"]
    np.testing.assert_array_equal(series["metrics/trace/CKF"], data["series"]["CKF"]["trace"])


def view_property(path: Path, column: str) -> dict[str, object]:
    """{view name: its `column` (a blueprint property, e.g. "ScalarAxis:range")} of the views
    of the recording's default blueprint that set it."""
    from rerun.chunk import RrdReader

    reader = RrdReader(str(path))
    names, values = {}, {}
    for ch in reader.store(store=reader.blueprints()[0]).stream().to_chunks():
        batch, e = ch.to_record_batch(), str(ch.entity_path)
        if "ViewBlueprint:display_name" in batch.schema.names:
            names[e] = batch.column("ViewBlueprint:display_name").to_pylist()[0][0]
        if column in batch.schema.names:
            values[e.rsplit("/", 1)[0]] = batch.column(column).to_pylist()[0]
    return {names[v]: x for v, x in values.items()}


def opening_ranges(path: Path) -> dict[str, tuple[float, float]]:
    """{view name: the y range it opens on} of the recording's default blueprint."""
    return {v: tuple(r[0]) for v, r in view_property(path, "ScalarAxis:range").items()}


def test_views_open_past_a_transient_that_would_flatten_them(tmp_path: Path) -> None:
    """A prior's transient 100 times the later values (multirate.toml: the MSE of x falls
    from 27 to 0.07, every curve lay on the axis): Figs. 4-6 open on the values after it,
    zoomable; views without one (vel x here, every view of the paper's example) fit all."""
    data = synthetic(steps=200)
    for j, d in enumerate(data["series"].values()):
        d["mse"][1, 0] = d["expected_mse"][0, 0] = 100.0 * (j + 1)
        d["trace"][0] = 300.0
    ranges = opening_ranges(write(tmp_path / "t.rrd", **data))
    lo, hi = ranges["Fig. 4: MSE of pos (lines: Monte Carlo, dots: expected)"]
    later = [d[k][5:, 0] for d in data["series"].values() for k in ("mse", "expected_mse")]
    assert lo == 0.0 and max(map(np.max, later)) <= hi < 10, (lo, hi)
    lo, hi = ranges["Fig. 5: MSE − MSE of CKF, pos"]
    assert -5 < lo < 1 < hi < 5, (lo, hi)
    lo, hi = ranges["Fig. 6: trace of P"]
    assert lo == 0.0 and 1 <= hi < 10, (lo, hi)
    assert not any("vel x" in name or "NEES" in name for name in ranges)
    assert opening_ranges(write(tmp_path / "s.rrd", **synthetic(steps=200))) == {}


def x_view_ranges(path: Path) -> tuple[int, list]:
    """(number of time-series views, the x view ranges set) of the recording's blueprint."""
    from rerun.chunk import RrdReader

    reader = RrdReader(str(path))
    views, ranges = 0, []
    for ch in reader.store(store=reader.blueprints()[0]).stream().to_chunks():
        batch = ch.to_record_batch()
        if "ViewBlueprint:class_identifier" in batch.schema.names:
            views += batch.column("ViewBlueprint:class_identifier").to_pylist() == [["TimeSeries"]]
        if "TimeAxis:view_range" in batch.schema.names:
            ranges += batch.column("TimeAxis:view_range").to_pylist()[0]
    return views, ranges


def test_every_time_series_view_opens_on_all_its_data(tmp_path: Path) -> None:
    """A view of more than a minute on the `time` timeline opened on -30 s .. +30 s about
    the cursor (heterogeneous.toml, 100 s: half the view empty, 70 s of data off it): every
    time-series view's x axis is set to show everything, evaluation and identity alike."""
    data = synthetic(steps=201)
    data["times"] = np.arange(201) * 0.5
    views, ranges = x_view_ranges(write(tmp_path / "e.rrd", **data))
    assert views == 7 + 2 * 2  # Figs. 4, 5 per state, 6, NEES, DM; two runs of two states
    assert ranges == [{"start": None, "end": None}] * views  # both ends infinite
    views, ranges = x_view_ranges(write(tmp_path / "i.rrd", write_identity_recording,
                                        **identity_data()))  # fmt: skip
    assert views > 0 and ranges == [{"start": None, "end": None}] * views


def test_each_sensor_has_its_own_availability_view(tmp_path: Path) -> None:
    """Without dropouts every share is 1: in one view the sensor drawn last hid the others'
    instants (coordinated_turn.toml's camera under its radar); a view per sensor shows each."""

    data = synthetic(steps=8)
    every, odd = np.ones(8), np.where(np.arange(8) % 2 == 1, 1.0, np.nan)
    path = write(tmp_path / "a.rrd", **data, availability={"radar": every, "cam 2": odd})
    queries = view_property(path, "ViewContents:query")
    sensors = {n.split(":")[0]: q for n, q in queries.items() if "share of runs" in n}
    assert sensors == {"radar": ["+ /sensors/radar/**"], "cam 2": ["+ /sensors/cam\\ 2/**"]}
    series = read_recording(path)["series"]
    np.testing.assert_array_equal(series["sensors/cam\\ 2/measured"], odd)


def test_failure_in_the_writer_leaves_nothing(tmp_path: Path) -> None:
    """Data that cannot be sent (a non-numeric series) fail inside the stream: nothing is
    written, the previous output stays, no temporary file is left."""
    path = tmp_path / "out.rrd"
    write(path, **synthetic())
    before = path.read_bytes()
    data = synthetic()
    data["series"]["HKF"]["dm"] = np.array(["x"] * len(data["times"]), dtype=object)
    with pytest.raises(ValueError), Outputs([path], force=True) as outs:
        write_recording(outs.open(path), **data)
        outs.commit()
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["out.rrd"]


def test_inconsistent_input_rejected_before_writing(tmp_path: Path) -> None:
    data = synthetic()
    data["series"]["HKF"]["nees"] = np.zeros(3)
    path = tmp_path / "bad.rrd"
    with open(path, "wb") as f, pytest.raises(FusionlogError, match="HKF: nees has shape") as e:
        write_recording(f, **data)
    assert str(path) in str(e.value)
    assert path.read_bytes() == b""


@pytest.mark.parametrize(
    "content",
    [None, b"", b"definitely not an rrd file" * 10, "truncated", "no footer", "cut header"],
)
@pytest.mark.parametrize("series", [True, False])
def test_read_bad_file_is_one_line_error(tmp_path: Path, written, content, series) -> None:
    path = tmp_path / "bad.rrd"
    good = written[0].read_bytes()
    if content == "truncated":
        path.write_bytes(good[: len(good) // 3])
    elif content == "no footer":
        path.write_bytes(good[:-1])
    elif content == "cut header":
        path.write_bytes(good[:10])
    elif content is not None:
        path.write_bytes(content)
    with pytest.raises(FusionlogError) as info:
        read_recording(path, series=series)
    msg = str(info.value)
    assert "\n" not in msg and str(path) in msg


@pytest.mark.parametrize("series", [True, False])
def test_read_truncated_anywhere_is_one_line_error(tmp_path: Path, written, series) -> None:
    """Also when only the summary is kept: every chunk is still decoded."""
    good = written[0].read_bytes()
    path = tmp_path / "cut.rrd"
    for cut in np.linspace(1, len(good) - 1, 25).astype(int):
        path.write_bytes(good[:cut])
        with pytest.raises(FusionlogError) as info:
            read_recording(path, series=series)
        assert "\n" not in str(info.value), cut


def foreign(path: Path, summary: str | None) -> Path:
    import rerun as rr

    rec = rr.RecordingStream("someone-else", recording_id="x", send_properties=False)
    stream = rec.binary_stream()
    rec.log("a", rr.Scalars(1.0))
    if summary is not None:
        rec.send_property("summary", rr.AnyValues(json=summary))
    path.write_bytes(stream.read(flush=True))
    rec.disconnect()
    return path


def test_read_foreign_recording(tmp_path: Path) -> None:
    with pytest.raises(FusionlogError, match="not a fusionlog recording"):
        read_recording(foreign(tmp_path / "foreign.rrd", None))


@pytest.mark.parametrize("summary", ["[1, 2]", '"text"', "3", "null", "{", "[" * 100_000])
def test_summary_that_is_not_an_object(tmp_path: Path, summary: str) -> None:
    """A summary property that is a list (or any non-object, or no JSON at all) is refused
    with one line, not an AttributeError later."""
    path = foreign(tmp_path / "odd.rrd", summary)
    with pytest.raises(FusionlogError, match="corrupt summary property") as info:
        read_recording(path)
    assert "\n" not in str(info.value)


# ---------------------------------------------------------------------------- identity writer
def identity_data(steps: int = 5) -> dict:
    rng = np.random.default_rng(3)
    classes = ["fighter", "airliner", "heli copter"]
    n = len(classes)
    p = rng.dirichlet(np.ones(n), size=steps)
    return {
        "scenario_name": "ident",
        "seed": 1,
        "times": np.arange(steps) * 0.5,
        "classes": classes,
        "series": {
            "BAYES": {
                "accuracy": rng.random(steps),
                "p_true": rng.random(steps),
                "log_loss": rng.random(steps),
                "probability": p,
            },
            "DS": {
                **{
                    k: rng.random(steps)
                    for k in (
                        "accuracy",
                        "p_true",
                        "log_loss",
                        "belief_true",
                        "plausibility_true",
                        "conflict",
                        "accumulated_conflict",
                    )
                },
                "belief": p * 0.5,
                "plausibility": np.minimum(p * 1.5, 1.0),
            },
        },
        "disagreement": rng.random(steps),
        "summary": {"kind": "identity", "scenario": "ident", "architectures": {}},
        "sample_runs": {0: (2, {"BAYES": {"probability": p}})},
    }


def test_identity_recording_round_trip(tmp_path: Path) -> None:
    data = identity_data()
    path = write(tmp_path / "id.rrd", write_identity_recording, **data)
    assert run_cli("rrd", "verify", str(path)).returncode == 0
    got = read_recording(path)
    assert got["recording_id"] == recording_id_for("ident", 1)
    assert got["summary"] == data["summary"]
    ser = got["series"]
    p = data["series"]["BAYES"]["probability"]
    for i, c in enumerate(data["classes"]):
        np.testing.assert_array_equal(
            ser[entity_path("identity", "probability", c, "BAYES")], p[:, i]
        )
        np.testing.assert_array_equal(
            ser[entity_path("runs", 0, "probability", c, "BAYES")], p[:, i]
        )
    np.testing.assert_array_equal(ser["metrics/disagreement"], data["disagreement"])
    from rerun.chunk import RrdReader

    assert len(RrdReader(str(path)).blueprints()) == 1


def test_identity_rejects_unknown_architecture(tmp_path: Path) -> None:
    data = identity_data()
    data["series"]["XYZ"] = data["series"]["BAYES"]
    with open(tmp_path / "x.rrd", "wb") as f, pytest.raises(FusionlogError, match="XYZ"):
        write_identity_recording(f, **data)


# ------------------------------------------------------------------------------ legend place
def test_legend_goes_where_it_hides_nothing() -> None:
    k = np.arange(21.0)
    decaying = [np.exp(-k / 2) + 0.1 * j for j in range(3)]  # top-right empty
    flat_high = [np.full(21, 1.0), np.linspace(0.0, 1.0, 21)]  # top-right occupied
    box = legend_box(3, 8, 2, 3)
    assert place_legend([decaying], box) == (0, "RightTop")
    # the first view has a curve through every corner: the legend goes to the second view
    crossing = [np.linspace(0, 1, 21), np.linspace(1, 0, 21), np.full(21, 0.5)]
    assert place_legend([crossing, decaying], box) == (1, "RightTop")
    # rising curves leave the top-left empty
    assert place_legend([[1 - c for c in decaying][::-1]], box)[1] in ("LeftTop", "RightBottom")
    assert place_legend([flat_high], box)[1] != "RightTop"
    # nothing to look at: first view, default corner
    assert place_legend([[np.full(3, np.nan)], []], box) == (0, "RightTop")
