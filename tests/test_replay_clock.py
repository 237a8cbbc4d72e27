"""Issue 28 part 3: the outputs of a replay line up. estimates.mcap keeps the recording's clock
(DESIGN.md "MCAP files": log_time of an estimate = log_time of the sensor messages at that
instant, the original absolute time; `time` counts seconds from the first instant), which the
recording's `time` timeline (a duration, DESIGN.md "The .rrd recording") counts too; `inspect`
and `summary` tell a recorded log from a simulation (no "seed 0", no "M = 1 runs"); a
single-sensor replay names its NIS row by the sensor, not "all". Files read with the plain
`mcap` reader and its protobuf decoder, the sources' times from their own text."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import ok
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from fusionlog.io.rrd import read_recording

ROOT = Path(__file__).resolve().parent.parent
PIPELINE = ROOT / "pipeline"


def _messages(path: Path) -> dict[str, list[tuple[int, int, float]]]:
    """{topic: [(step, log_time, time)]} of a file, in file order, fusionlog not involved."""
    out: dict[str, list[tuple[int, int, float]]] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, message, msg in reader.iter_decoded_messages(log_time_order=False):
            out.setdefault(channel.topic, []).append((msg.step, message.log_time, msg.time))
    return out


def _csv_times(path: Path) -> list[int]:
    """The integer nanosecond timestamps of a motion-capture CSV, from its text."""
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    return [int(r[0]) for r in rows[1:] if r and r[0].strip().isdigit()]


@pytest.fixture(scope="module")
def replayed(tmp_path_factory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("clock") / "run"
    res = ok("run", PIPELINE / "replay_robot.toml", "--out-dir", out)
    return out, res.stdout


def test_a_replays_estimates_keep_the_recordings_clock(replayed) -> None:
    out, _ = replayed
    sensors, estimates = _messages(out / "sensors.mcap"), _messages(out / "estimates.mcap")
    clock = {step: t for topic in sensors for step, t, _ in sensors[topic]}  # step -> log_time
    for topic in sensors:  # the sensors' messages of one instant share its log_time
        assert all(clock[step] == t for step, t, _ in sensors[topic]), topic
    # the mocap CSV's own timestamps are the log_time of its messages (the recording's clock)
    mocap = [t for _, t, _ in sensors["/sensors/mocap"]]
    csv_ns = sorted(set(_csv_times(PIPELINE / "data/mocap.csv")))
    assert set(mocap) <= set(csv_ns) and mocap[0] == csv_ns[0] and len(mocap) >= len(csv_ns) - 2
    t0 = min(clock.values())
    assert t0 > 1.5e18  # November 2023, not 0
    assert len(estimates) == 7
    for topic, msgs in estimates.items():
        assert [s for s, _, _ in msgs] == sorted(clock)  # every instant, in order
        for step, log_time, time in msgs:
            assert log_time == clock[step], (topic, step)
            # `time` counts seconds from the first instant (doubles: 1 ns at ~45 s is 2e-11)
            assert abs(time - (log_time - t0) / 1e9) <= 1e-9, (topic, step)


def test_estimate_alone_keeps_the_clock_of_its_sensors_file(replayed, tmp_path: Path) -> None:
    """`fusionlog estimate` of an imported log, not only `run`: the clock comes from the
    sensors file it reads."""
    out, _ = replayed
    est = tmp_path / "e.mcap"
    ok("estimate", out / "sensors.mcap", "-o", est, "--arch", "CKF")
    clock = {s: t for msgs in _messages(out / "sensors.mcap").values() for s, t, _ in msgs}
    mine = _messages(est)["/estimates/CKF"]
    assert [t for _, t, _ in mine] == [clock[s] for s, _, _ in mine]


def test_a_simulation_keeps_its_clock_at_zero(tmp_path: Path) -> None:
    ok("run", ROOT / "tests/golden/small.toml", "--out-dir", tmp_path, "--runs", "3")
    for name in ("sensors.mcap", "estimates.mcap"):
        for msgs in _messages(tmp_path / name).values():
            assert all(t == round(time * 1e9) for _, t, time in msgs), name


def test_the_recordings_time_timeline_counts_seconds_from_the_first_instant(replayed) -> None:
    """evaluation.rrd's `time` timeline is a duration (DESIGN.md): the estimates' `time`
    field, seconds from the first instant, on the same steps."""
    out, _ = replayed
    rec = read_recording(out / "evaluation.rrd")
    ckf = _messages(out / "estimates.mcap")["/estimates/CKF"]
    times = {s: time for s, _, time in ckf}
    steps = np.asarray(rec["steps"])
    assert len(steps) and set(steps.tolist()) <= set(times)
    # the same nanosecond (Rerun truncated the seconds it was given: 4.1625 s, 4.162499999 s);
    # read back as ns / 1e9 like the estimates' (ns - t0) / 1e9: a few ulps at most
    want = [times[s] for s in steps.tolist()]
    np.testing.assert_allclose(rec["times"], want, rtol=0, atol=1e-13)
    assert rec["times"][0] == 0.0 and rec["times"][-1] < 60.0  # a 45 s log, not 1.7e9 s


def test_inspect_and_summary_tell_a_recorded_log_from_a_simulation(replayed) -> None:
    out, stdout = replayed
    first = min(t for msgs in _messages(out / "sensors.mcap").values() for _, t, _ in msgs)
    for name in ("sensors.mcap", "estimates.mcap"):
        text = ok("inspect", out / name).stdout
        assert "seed 0" not in text and "runs: 1" not in text, text
        assert "scenario: replay_robot (a replay of recorded data: one run, no seed)" in text
        assert "one recorded run, instants: 2292" in text, text
        assert f"log_time from {first} ns (2023-11-14 22:13:20 UTC)" in text, text
    head = ok("summary", out / "evaluation.rrd").stdout.splitlines()[0]
    assert head == "replay_robot: one recorded log, K = 2291 (2292 instants)", head
    assert "M = " not in stdout and "seed 0" not in stdout


def test_inspect_and_summary_of_a_simulation_are_unchanged(tmp_path: Path) -> None:
    ok("run", ROOT / "tests/golden/small.toml", "--out-dir", tmp_path, "--runs", "6")
    text = ok("inspect", tmp_path / "sensors.mcap").stdout
    assert "scenario: small (seed 7)" in text and "runs: 6, instants: 11" in text
    assert "a replay" not in text and "recorded run" not in text and "log_time from" not in text
    head = ok("summary", tmp_path / "evaluation.rrd").stdout.splitlines()[0]
    assert head == "small: M = 6 runs, K = 10"


@pytest.fixture(scope="module")
def one_sensor(tmp_path_factory) -> tuple[Path, Path, str]:
    """replay_robot's motion capture alone, without truth: a single-sensor replay whose
    table is the innovations' (NIS per architecture and sensor)."""
    text = (PIPELINE / "replay_robot.toml").read_text()
    head, *sensors = text.split("[[sensors]]")
    mocap = next(s for s in sensors if 'name = "mocap"' in s).split("[truth]")[0]
    doc = head + "[[sensors]]" + mocap
    doc += '\n[estimate]\narchitectures = ["CKF", "HKF", "MSC", "SKF:mocap", "FBS"]\n'
    tmp = tmp_path_factory.mktemp("one")
    path = tmp / "mocap_only.toml"
    path.write_text(doc.replace('"data/', f'"{PIPELINE / "data"}/'))
    res = ok("run", path, "--out-dir", tmp / "run")
    return path, tmp / "run", res.stdout


def _nis_rows(text: str) -> dict[str, str]:
    """{architecture: sensor} of the innovation table's rows."""
    lines = text.splitlines()
    head = next(
        i for i, ln in enumerate(lines) if ln.split()[:3] == ["architecture", "sensor", "NIS"]
    )
    rows = {}
    for ln in lines[head + 2 :]:
        if "%" not in ln or ln[0] == " ":  # every row has its share in the band
            break
        rows[ln.split()[0]] = ln.split()[1]
    return rows


def test_a_single_sensor_replay_names_its_nis_row_by_the_sensor(one_sensor) -> None:
    import fusionlog as fl

    path, out, stdout = one_sensor
    want = dict.fromkeys(["CKF", "HKF", "MSC", "SKF:mocap", "FBS"], "mocap")
    assert _nis_rows(stdout) == want, stdout
    assert _nis_rows(ok("summary", out / "evaluation.rrd").stdout) == want
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["architectures"]["CKF"]["nis"]) >= {"mean", "dof", "fraction_inside"}
    series = read_recording(out / "evaluation.rrd")["series"]
    assert "metrics/nis/CKF/mocap" in series and not any("/all" in k for k in series)
    # `fusionlog evaluate` of the same files, and the Python API's table
    ev_out = out.parent / "ev.rrd"
    res = ok("evaluate", out / "sensors.mcap", out / "estimates.mcap", "-o", ev_out)
    assert _nis_rows(res.stdout) == want
    sc = fl.load(path)
    sim = fl.simulate(sc)
    table = fl.evaluate(sc, sim, fl.estimate(sc, sim, ["CKF", "SKF:mocap"])).table()
    assert _nis_rows(table) == {"CKF": "mocap", "SKF:mocap": "mocap"}
