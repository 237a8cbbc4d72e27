"""The evaluation recording: write, verify with the rerun CLI, read back offline, determinism,
atomic write and --force behaviour."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fusionlog.errors import FusionlogError
from fusionlog.io import rrd
from fusionlog.io.rrd import entity_path, read_recording, recording_id_for, write_recording

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


@pytest.fixture(scope="module")
def written(tmp_path_factory) -> tuple[Path, dict]:
    data = synthetic()
    path = tmp_path_factory.mktemp("rrd") / "evaluation.rrd"
    assert write_recording(path, **data) == path
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


def test_escaped_entity_paths(written) -> None:
    path, _ = written
    keys = read_recording(path)["series"]
    assert "metrics/mse/vel\\ x/SKF\\:s2" in keys
    assert "metrics/trace/HKF" in keys


def test_styling_and_blueprint_present(written) -> None:
    from rerun.chunk import RrdReader

    path, _ = written
    reader = RrdReader(str(path))
    assert reader.blueprints(), "default blueprint missing"
    static = {}
    for ch in reader.store().stream().to_chunks():
        if ch.is_static and str(ch.entity_path).startswith("/metrics/trace/"):
            static[str(ch.entity_path)] = ch.to_record_batch().to_pydict()
    ckf = static["/metrics/trace/CKF"]
    assert ckf["SeriesLines:names"] == [["CKF"]]
    assert ckf["SeriesLines:colors"][0][0] == int.from_bytes(bytes([*rrd.arch_color("CKF"), 255]))


def test_identical_writes_compare_equal(tmp_path: Path) -> None:
    a, b, c = tmp_path / "a.rrd", tmp_path / "b.rrd", tmp_path / "c.rrd"
    write_recording(a, **synthetic())
    write_recording(b, **synthetic())
    res = run_cli("rrd", "compare", "--unordered", str(a), str(b))
    assert res.returncode == 0, res.stdout + res.stderr
    other = synthetic()
    other["series"]["HKF"]["dm"] = other["series"]["HKF"]["dm"] + 1e-6
    write_recording(c, **other)
    assert run_cli("rrd", "compare", "--unordered", str(a), str(c)).returncode != 0


def test_without_ckf_no_difference_entities(tmp_path: Path) -> None:
    path = tmp_path / "e.rrd"
    write_recording(path, **synthetic(archs=["HKF", "MSC"]))
    keys = read_recording(path)["series"]
    assert not any(k.startswith("metrics/mse_minus_ckf") for k in keys)
    assert "metrics/mse/pos/MSC" in keys


def test_existing_output_needs_force(tmp_path: Path) -> None:
    path = tmp_path / "out.rrd"
    path.write_bytes(b"keep me")
    with pytest.raises(FusionlogError, match="already exists"):
        write_recording(path, **synthetic())
    assert path.read_bytes() == b"keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.rrd"]
    write_recording(path, **synthetic(), force=True)
    assert read_recording(path)["summary"]["scenario"] == "synthetic"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.rrd"]  # no temp file left


def test_failure_mid_write_leaves_nothing(tmp_path: Path, monkeypatch) -> None:
    path = tmp_path / "sub" / "out.rrd"

    def boom(*args, **kwargs):
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(rrd._Writer, "write_all", boom)
    with pytest.raises(RuntimeError, match="disk on fire"):
        write_recording(path, **synthetic())
    assert not path.exists()
    assert list(path.parent.iterdir()) == []


def test_failure_keeps_previous_output(tmp_path: Path, monkeypatch) -> None:
    path = tmp_path / "out.rrd"
    write_recording(path, **synthetic())
    before = path.read_bytes()
    monkeypatch.setattr(rrd._Writer, "write_all", lambda *a, **k: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        write_recording(path, **synthetic(), force=True)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["out.rrd"]


def test_inconsistent_input_rejected_before_writing(tmp_path: Path) -> None:
    data = synthetic()
    data["series"]["HKF"]["nees"] = np.zeros(3)
    path = tmp_path / "bad.rrd"
    with pytest.raises(FusionlogError, match="HKF: nees has shape"):
        write_recording(path, **data)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "content",
    [None, b"", b"definitely not an rrd file" * 10, "truncated"],
    ids=["missing", "empty", "garbage", "truncated"],
)
def test_read_bad_file_is_one_line_error(tmp_path: Path, written, content) -> None:
    path = tmp_path / "bad.rrd"
    if content == "truncated":
        good = written[0].read_bytes()
        path.write_bytes(good[: len(good) // 3])
    elif content is not None:
        path.write_bytes(content)
    with pytest.raises(FusionlogError) as info:
        read_recording(path)
    msg = str(info.value)
    assert "\n" not in msg and str(path) in msg


def test_read_foreign_recording(tmp_path: Path) -> None:
    import rerun as rr

    path = tmp_path / "foreign.rrd"
    rec = rr.RecordingStream("someone-else", recording_id="x", send_properties=False)
    rec.save(path)
    rec.log("a", rr.Scalars(1.0))
    rec.disconnect()
    with pytest.raises(FusionlogError, match="not a fusionlog recording"):
        read_recording(path)
