"""Issue 19, item 5: no numpy warning reaches the user. Scenarios whose numbers overflow (a
huge n0 on irregular instants, a diverging continuous model over a long horizon, a recorded
value of 1e300) run to the end with inf/NaN reported as such, and print nothing on stderr. The
suite runs with warnings as errors (pyproject's filterwarnings), so a numpy RuntimeWarning
would also turn these in-process runs into an internal error (exit 3)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import cli, ok, one_line_error

from fusionlog.core.architectures import estimate
from fusionlog.core.model import ajgl2009
from fusionlog.core.simulate import simulate
from fusionlog.errors import NumericalError

IRREGULAR_N0 = """\
[scenario]
name = "huge_n0"
steps = 20
runs = 5
seed = 1
dt = 0.1

[model]
kind = "constant-velocity"
n0 = 1e300

[truth]
initial_mean = [0.0, 0.0]
initial_cov = [[1.0, 0.0], [0.0, 1.0]]

[[sensors]]
name = "s1"
H = [1.0, 0.0]
R = 0.1
period = 0.15

[[sensors]]
name = "s2"
H = [0.0, 1.0]
R = 0.2
period = 0.25
offset = 0.05
dropout = 0.3
"""

DIVERGING = """\
[scenario]
name = "diverging"
steps = 2000
runs = 5
seed = 1
dt = 0.1

[model]
kind = "continuous"
A = [[2.0]]
Qc = [[1.0]]

[prior]
mean = [0.0]
cov = [[1.0]]

[[sensors]]
name = "s1"
H = [1.0]
R = 0.1
"""

REPLAY = """\
[scenario]
name = "outlier"

[model]
kind = "constant-velocity"
n0 = 1.0

[prior]
mean = [0.0, 0.0]
cov = [[1.0, 0.0], [0.0, 1.0]]

[[sensors]]
name = "s"
source = "d.csv"
values = ["v"]
H = [1.0, 0.0]
R = 1.0
"""


def quiet_run(tmp_path: Path, text: str) -> dict:
    sc = tmp_path / "sc.toml"
    sc.write_text(text)
    res = cli("run", sc, "--out-dir", tmp_path / "out")
    assert res.exit_code in (0, 2), (res.exit_code, res.stderr, res.exception)
    if res.exit_code == 2:  # a one-line NumericalError is an answer too
        assert len(res.stderr.splitlines()) == 1, res.stderr
        return {}
    assert res.stderr == "", res.stderr
    return json.loads((tmp_path / "out" / "summary.json").read_text())


def test_huge_n0_on_irregular_instants_prints_no_warning(tmp_path: Path) -> None:
    s = quiet_run(tmp_path, IRREGULAR_N0)
    assert not s or s["architectures"]["CKF"]["mse"] > 1e200


def test_diverging_continuous_model_prints_no_warning(tmp_path: Path) -> None:
    s = quiet_run(tmp_path, DIVERGING)
    # exp(2 * 200 s) overflows the squared errors: the Monte Carlo MSE has no finite value
    assert not s or s["architectures"]["CKF"]["mse"] is None


@pytest.mark.parametrize("value", ["1e300", "-1e308"])
def test_recorded_value_near_the_float_limit_prints_no_warning(tmp_path: Path, value: str) -> None:
    (tmp_path / "d.csv").write_text(f"time,v\n0.0,1.0\n0.1,{value}\n0.2,2.0\n0.35,1.5\n")
    quiet_run(tmp_path, REPLAY)


def test_simulate_and_sweep_of_the_diverging_model_print_no_warning(tmp_path: Path) -> None:
    sc = tmp_path / "sc.toml"
    sc.write_text(DIVERGING)
    res = cli("sweep", sc, "--vary", "model.A=[[2.0]],[[0.5]]", "--workers", "0", "--out-dir",
              tmp_path / "o")  # fmt: skip
    assert res.exit_code == 0 and res.stderr == "", (res.stderr, res.exception)


def test_an_estimate_that_overflows_names_the_file_the_architecture_and_the_step(
    tmp_path: Path,
) -> None:
    """replay_robot with one motion-capture reading of 1e308: the one-run path hands the log to
    the plans, whose step overflows; the line names the sensors file as well."""
    root = Path(__file__).resolve().parents[1] / "pipeline"
    (tmp_path / "data").mkdir()
    for name in ("robot_ros2.mcap", "truth.csv"):
        (tmp_path / "data" / name).write_bytes((root / "data" / name).read_bytes())
    header, *rows = (root / "data" / "mocap.csv").read_text().splitlines()
    cells = rows[50].split(",")
    cells[1] = "1e308"
    rows[50] = ",".join(cells)
    (tmp_path / "data" / "mocap.csv").write_text("\n".join([header, *rows]) + "\n")
    sc = tmp_path / "replay_robot.toml"
    sc.write_text((root / "replay_robot.toml").read_text())
    ok("import", sc, "-o", tmp_path / "s.mcap")
    res = cli("estimate", tmp_path / "s.mcap", "-o", tmp_path / "e.mcap")
    one_line_error(res, "s.mcap: architecture ", ", step ", "overflows")
    assert not (tmp_path / "e.mcap").exists()


OVERFLOWING_TRUTH = """\
[scenario]
name = "linbad"
steps = 4
runs = 20
seed = 1
dt = 1.0
[model]
F = [[1e120]]
Q = [[1.0]]
[prior]
mean = [0.0]
cov = [[1.0]]
[[sensors]]
name = "s"
H = [[1.0]]
R = 1.0
[estimate]
architectures = ["CKF"]
"""


def test_a_simulation_that_overflows_names_the_scenario_file(tmp_path: Path) -> None:
    """The true state passes the float range at step 3: simulate, run and an in-process sweep
    give one line naming the scenario file (and the sweep's grid point) and the step (it named
    neither file nor anything but "simulation"), and write nothing."""
    sc = tmp_path / "linbad.toml"
    sc.write_text(OVERFLOWING_TRUTH)
    frags = (f"{sc}: simulation: the true state overflows at step 3",)
    one_line_error(cli("simulate", sc, "-o", tmp_path / "s.mcap"), *frags)
    one_line_error(cli("run", sc, "--out-dir", tmp_path / "r"), *frags)
    res = cli("sweep", sc, "--vary", "scenario.steps=3,4", "--workers", "0",
              "--out-dir", tmp_path / "w")  # fmt: skip
    # a sweep names the grid point too (issue 28)
    one_line_error(res, f"{sc} [point 0: scenario.steps=3]: simulation: the true state overflows "
                   "at step 3")  # fmt: skip
    # (run's --out-dir, made before the simulation, is removed with the failure)
    assert sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*")) == [
        "linbad.toml"
    ]


@pytest.mark.parametrize("arch", ["CKF", "HKF", "MSC-GMF"])
def test_an_infinite_reading_is_named_at_its_step(arch):
    """A shared plan applied as one dense map mixes every step (inf x 0 is NaN everywhere):
    the failure still names the step of the reading, as the step recursion finds it."""
    system = ajgl2009()
    _, z = simulate(system, 10, 1, 0, 3)
    z[1, 5, 0] = np.inf
    with pytest.raises(NumericalError, match=rf"architecture {arch}, step 5: the estimate"):
        estimate(system, z, arch)


def test_an_infinite_reading_in_a_sensors_file_is_named_with_its_topic_and_step(
    tmp_path: Path,
) -> None:
    """A sensors file (written by another tool) with one reading of -inf: the line named an
    overflow of CKF "at step 0" -- the plans' product spreads inf * 0 = NaN to the steps
    before it -- instead of the reading itself (NaN marks a missing reading, inf none)."""
    import numpy as np

    from fusionlog.io.mcap import McapFile, McapWriter

    root = Path(__file__).resolve().parents[1] / "pipeline"
    ok("simulate", root / "ajgl2009.toml", "-o", tmp_path / "s.mcap", "--runs", "20",
       "--steps", "8")  # fmt: skip
    mf = McapFile(tmp_path / "s.mcap")
    topics = sorted(mf.topics)
    data, times = mf.read_all(topics), mf.times()
    data["/sensors/s2"][3, 4, 0] = -np.inf
    with open(tmp_path / "inf.mcap", "wb") as f, McapWriter(f) as w:
        for name, record in mf.metadata.items():
            w.add_metadata(name, record)
        for k, t in enumerate(times):
            for topic in topics:
                w.write_values(topic, k, float(t), 0, data[topic][:, k])
    for extra in ([], ["--block-runs", "2", "--arch", "FBS"]):
        res = cli("estimate", tmp_path / "inf.mcap", "-o", tmp_path / "e.mcap", *extra)
        one_line_error(res, "inf.mcap: /sensors/s2: an infinite reading at step 4, run 3")
    assert not (tmp_path / "e.mcap").exists()


def test_run_names_its_outputs_not_their_temporary_files(tmp_path: Path) -> None:
    """R = 1e-300 with dropouts: a covariance rounds to a negative variance, which evaluation
    refuses; `run` names estimates.mcap, not the temporary file it was being written to."""
    root = Path(__file__).resolve().parents[1] / "pipeline"
    text = (root / "ajgl2009_dropout.toml").read_text()
    sc = tmp_path / "tiny_r.toml"
    sc.write_text(
        "\n".join("R = 1e-300" if ln.startswith("R = ") else ln for ln in text.split("\n"))
    )
    line = one_line_error(cli("run", sc, "--runs", "200", "--out-dir", tmp_path / "o"))
    assert ".tmp" not in line and "fusionlog-" not in line, line
    assert not (tmp_path / "o").exists()
