"""Issue 30 item 4, a recorded log's delays (DESIGN.md "Late measurements"): `arrival =
"log_time"` on a replay sensor takes each message's log time as its arrival and `time` (its
header stamp) as when it was measured.

The replay is a JSON-encoded MCAP written here with header stamps lagging their log times by
chosen amounts. References written from the definitions: reprocess = a scalar Kalman filter
rerun at each instant on exactly the messages logged by then; neglect = an event-driven filter
taking the messages in log order and dropping one older than its last update.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import cli, ok, one_line_error
from long_helpers import stamped_mcap

import fusionlog as fl

LOGS = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "logs"
Q_C, R_A, R_B = 0.3, 0.5, 0.2  # random-walk intensity (per s), the two sensors' variances
NS = 1_000_000_000
# sensor a on time every 0.1 s; sensor b stamped at 0.05 + 0.1 i, logged late by these (s)
B_DELAYS = [0.12, 0.03, 0.25, 0.04, 0.0, 0.31, 0.07, 0.16, 0.02, 0.09]
T0 = 1_700_000_000 * NS


def write_log(path: Path, seed: int = 3) -> dict[str, list[tuple[int, int, float]]]:
    """Two topics of {header.stamp, v}: (stamp ns, log ns, value) per message."""
    rng = np.random.default_rng(seed)
    msgs = {
        "/a": [(T0 + i * NS // 10, T0 + i * NS // 10, float(rng.normal())) for i in range(10)],
        "/b": [
            (T0 + (i * 100 + 50) * NS // 1000, T0 + (i * 100 + 50) * NS // 1000 + round(d * NS),
             float(rng.normal()))
            for i, d in enumerate(B_DELAYS)
        ],
    }  # fmt: skip
    stamped_mcap(path, list(msgs), [(lg, t, st, v) for t, ms in msgs.items() for st, lg, v in ms])
    return msgs


def replay(tmp_path: Path, *, arrival: bool = True, late: str | None = None, extra: str = "",
           name: str = "late_log", source: str = "log.mcap", time: str = "time = \"header.stamp\"",
           prior: bool = True) -> Path:  # fmt: skip
    key = 'arrival = "log_time"\n' if arrival else ""
    est = '[estimate]\narchitectures = ["CKF"]\n' + (f'late = "{late}"\n' if late else "")
    pri = "[prior]\nmean = [0.0]\ncov = [[4.0]]\n" if prior else ""
    text = f"""
[scenario]
name = "{name}"
state_names = ["x"]

[model]
kind = "continuous"
A = [[0.0]]
Qc = [[{Q_C}]]

{pri}
[[sensors]]
name = "a"
source = "log.mcap"
topic = "/a"
values = ["v"]
time = "header.stamp"
H = [[1.0]]
R = {R_A}

[[sensors]]
name = "b"
source = "{source}"
topic = "/b"
values = ["v"]
{time}
H = [[1.0]]
R = {R_B}
{key}{extra}
{est}"""
    path = tmp_path / f"{name}.toml"
    path.write_text(text)
    return path


def events(msgs):
    """(stamp s, log s, value, R) of every message, from the first stamp."""
    out = []
    for t, r in (("/a", R_A), ("/b", R_B)):
        out += [((s - T0) / NS, (lg - T0) / NS, v, r) for s, lg, v in msgs[t]]
    return out


def kf(instants, used):
    """The scalar random-walk KF from the prior at instants[0], updated with `used` readings
    (stamp, value, R) at their stamps; (x, P) at each instant."""
    x, P, t = 0.0, 4.0, instants[0]
    by = {}
    for s, v, r in used:
        by.setdefault(s, []).append((v, r))
    out = []
    for tk in instants:
        P += Q_C * (tk - t)
        t = tk
        for v, r in by.get(round(tk, 9), []):
            g = P / (P + r)
            x, P = x + g * (v - x), (1 - g) * P
        out.append((x, P))
    return out


def test_reprocess_is_a_kf_on_exactly_the_messages_logged_by_each_instant(tmp_path):
    msgs = write_log(tmp_path / "log.mcap")
    path = replay(tmp_path)
    sim = fl.simulate(path)
    est = fl.estimate(path, sim, ["CKF"])["CKF"]  # the delays are the data's: taken from sim
    ev = events(msgs)
    instants = sorted({round(s, 9) for s, _, _, _ in ev})
    np.testing.assert_allclose(sim.times, instants, rtol=0, atol=1e-9)
    for k, tk in enumerate(instants):
        arrived = [(round(s, 9), v, r) for s, lg, v, r in ev if lg <= tk + 1e-9]
        x, P = kf(instants[: k + 1], arrived)[-1]
        np.testing.assert_allclose(est.mean[0, k, 0], x, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(est.cov[0, k, 0, 0], P, rtol=1e-9, atol=1e-14)


def test_neglect_drops_what_is_older_than_the_last_update(tmp_path):
    msgs = write_log(tmp_path / "log.mcap")
    sim = fl.simulate(replay(tmp_path))
    est = fl.estimate(sim.scenario, sim, ["CKF"], late="neglect")["CKF"]
    ev = sorted((lg, s, v, r) for s, lg, v, r in events(msgs))
    instants = sorted({round(s, 9) for _, s, _, _ in ev})
    x, P, t, e, dropped = 0.0, 4.0, instants[0], 0, 0
    for k, tk in enumerate(instants):
        while e < len(ev) and ev[e][0] <= tk + 1e-9:  # arrived by t_k, in log order
            _, s, v, r = ev[e]
            e += 1
            if s < t - 1e-9:
                dropped += 1
                continue
            P += Q_C * (s - t)
            t = s
            g = P / (P + r)
            x, P = x + g * (v - x), (1 - g) * P
        np.testing.assert_allclose(est.mean[0, k, 0], x, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(est.cov[0, k, 0, 0], P + Q_C * (tk - t), rtol=1e-9)
    assert dropped >= 3  # the log's delays make neglect drop readings (else no test)


def test_without_arrival_the_numbers_are_unchanged_bit_for_bit(tmp_path):
    write_log(tmp_path / "log.mcap")
    base = replay(tmp_path, arrival=False, name="on_time")
    sim = fl.simulate(base)
    assert not sim.arrival
    est = fl.estimate(base, sim, ["CKF"])["CKF"]
    # the reference: every reading used at its stamp (what a replay did before `arrival`)
    late = fl.simulate(replay(tmp_path))
    ref = kf(list(sim.times), [(round(float(sim.times[k]), 9), float(z), r)
                               for n, r in (("a", R_A), ("b", R_B))
                               for k, z in enumerate(late.measurements[n][0, :, 0])
                               if np.isfinite(z)])  # fmt: skip
    np.testing.assert_allclose(est.mean[0, :, 0], [x for x, _ in ref], rtol=1e-9, atol=1e-12)
    ok("run", base, "--out-dir", tmp_path / "a", "--force")
    ok("run", base, "--out-dir", tmp_path / "b", "--force")
    first = json.loads((tmp_path / "a" / "summary.json").read_text())
    assert "late" not in first
    with_arrival = replay(tmp_path, name="with_arrival")
    ok("run", with_arrival, "--out-dir", tmp_path / "c", "--force")
    assert json.loads((tmp_path / "c" / "summary.json").read_text())["late"] == "reprocess"


def test_the_import_writes_each_reading_s_log_time_as_its_arrival(tmp_path):
    """The sensors file: b's messages carry their log times (s from the first instant) as
    the arrival field, a's (no `arrival` key) none; read with the plain mcap + protobuf
    decoder."""
    from test_latency import decoded

    msgs = write_log(tmp_path / "log.mcap")
    ok("import", replay(tmp_path), "-o", tmp_path / "s.mcap")
    b = decoded(tmp_path / "s.mcap", "/sensors/b")
    assert len(b) == len(B_DELAYS)
    for (_, t, _, values, arrival), (stamp, log, v) in zip(b, msgs["/b"], strict=True):
        assert values == [v]
        assert t == pytest.approx((stamp - T0) / NS, abs=1e-12)
        if log == stamp:  # on time: no field
            assert arrival == [] or arrival == pytest.approx([(log - T0) / NS], abs=1e-12)
        else:
            assert arrival == pytest.approx([(log - T0) / NS], abs=1e-12)
    assert all(not m[4] for m in decoded(tmp_path / "s.mcap", "/sensors/a"))
    # `estimate` of the file alone (the recorded replay, its delays from the file) = the API
    ok("estimate", tmp_path / "s.mcap", "-o", tmp_path / "e.mcap", "--late", "neglect")
    ok("evaluate", tmp_path / "s.mcap", tmp_path / "e.mcap", "-o", tmp_path / "e.rrd",
       "--summary", tmp_path / "e.json")  # fmt: skip
    summary = json.loads((tmp_path / "e.json").read_text())
    sim = fl.simulate(replay(tmp_path))
    est = fl.estimate(sim.scenario, sim, ["CKF"], late="neglect")["CKF"]
    assert summary["late"] == "neglect"
    assert summary["architectures"]["CKF"]["mean_trace"] == pytest.approx(
        float(est.cov[0, :, 0, 0].mean()), rel=1e-9
    )


@pytest.mark.parametrize("late", ["reprocess", "retrodict", "neglect"])
def test_run_of_the_replay_under_each_policy(tmp_path, late):
    """`run --late` of the replay: the summary names the policy, and its mean tr(P) is the
    API's estimate of the same readings (reprocess: the KF on the arrived messages)."""
    write_log(tmp_path / "log.mcap")
    path = replay(tmp_path)
    ok("run", path, "--late", late, "--out-dir", tmp_path / "out", "--force")
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["late"] == late
    sim = fl.simulate(path)
    est = fl.estimate(sim.scenario, sim, ["CKF"], late=late)["CKF"]
    got = summary["architectures"]["CKF"]
    assert got["mean_trace"] == pytest.approx(float(est.cov[0, :, 0, 0].mean()), rel=1e-9)


@pytest.mark.parametrize(
    ("kw", "fragments"),
    [
        ({"extra": 'arrival = "receive"'}, ("sensors[1].arrival", "log_time")),
        ({"time": ""}, ("sensors[1].arrival", "header.stamp")),
        ({"prior": False}, ("prior",)),
    ],
)
def test_bad_arrival_is_one_line(tmp_path, kw, fragments):
    write_log(tmp_path / "log.mcap")
    if "extra" in kw:  # a second arrival key would be a TOML error: replace the first
        path = replay(tmp_path, arrival=False, **kw)
    else:
        path = replay(tmp_path, **kw)
    one_line_error(cli("run", path, "--out-dir", tmp_path / "o"), str(path), *fragments)


def test_arrival_on_a_text_table_is_one_line(tmp_path):
    write_log(tmp_path / "log.mcap")
    (tmp_path / "b.csv").write_text("time,v\n0.05,1.0\n0.15,2.0\n")
    path = replay(tmp_path, source="b.csv", time='time = "time"')
    text = path.read_text().replace('topic = "/b"\n', "")
    path.write_text(text)
    one_line_error(cli("import", path, "-o", tmp_path / "s.mcap"), str(path), "sensors[1].arrival",
                   "text table", "log time")  # fmt: skip


@pytest.mark.skipif(not (LOGS / "test1.bag").exists(), reason="the shared logs are not here")
@pytest.mark.parametrize("late", ["reprocess", "retrodict", "neglect"])
def test_the_husky_bag_s_imu_late_under_each_policy(tmp_path, late):
    """test1.bag: the IMU's header stamps lag its log times by ~21-36 ms; the yaw rate from
    the IMU and the wheel odometry, under each policy (~30 s each)."""
    bag = LOGS / "test1.bag"
    text = f"""
[scenario]
name = "husky_yaw_rate"
state_names = ["yaw_rate"]
[model]
kind = "continuous"
A = [[0.0]]
Qc = [[0.05]]
[prior]
mean = [0.0]
cov = [[1.0]]
[[sensors]]
name = "imu"
source = "{bag}"
topic = "/imu/data"
values = ["angular_velocity.y"]
time = "header.stamp"
arrival = "log_time"
H = [[1.0]]
R = 0.0004
[[sensors]]
name = "odom"
source = "{bag}"
topic = "/husky_velocity_controller/odom"
values = ["twist.twist.angular.z"]
time = "header.stamp"
arrival = "log_time"
H = [[1.0]]
R = 0.001
[estimate]
architectures = ["CKF"]
"""
    path = tmp_path / "husky.toml"
    path.write_text(text)
    res = ok("run", path, "--late", late, "--out-dir", tmp_path / "o")
    assert "imu: arrival = log time: delays 20.6749 to 36.3305 ms" in res.stderr + res.stdout
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["late"] == late
