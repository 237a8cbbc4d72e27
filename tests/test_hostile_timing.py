"""Issue 19, timing keys: periods and offsets that cannot exist on a nanosecond schedule, and
scenarios whose instants would not fit in memory, refused with one line before anything is
allocated (`fusionlog simulate`, `run`, `sweep` through the CLI)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from cli_helpers import cli, ok, one_line_error

SCENARIO = """\
[scenario]
name = "hostile"
steps = STEPS
runs = 2
seed = 1
dt = DT

[model]
kind = "constant-velocity"
n0 = 0.16

[prior]
mean = [0.0, 0.0]
cov = [[1.0, 0.0], [0.0, 1.0]]

[[sensors]]
name = "s1"
H = [1.0, 0.0]
R = 0.1
TIMING1

[[sensors]]
name = "s2"
H = [0.0, 1.0]
R = 0.2
TIMING2
"""


def write(tmp_path: Path, timing1: str = "", timing2: str = "", steps: int = 20,
          dt: str = "0.1") -> Path:  # fmt: skip
    text = SCENARIO.replace("STEPS", str(steps)).replace("DT", dt)
    p = tmp_path / "sc.toml"
    p.write_text(text.replace("TIMING1", timing1).replace("TIMING2", timing2))
    return p


def listing(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir())


@pytest.mark.parametrize("value", ["1e-12", "9e-11", "1e-300", "4e-10", "1e18", "1e308"])
@pytest.mark.parametrize("sensor", [0, 1])
def test_period_outside_the_nanosecond_clock(tmp_path: Path, value: str, sensor: int) -> None:
    timing = [f"period = {value}", ""] if sensor == 0 else ["", f"period = {value}"]
    sc = write(tmp_path, *timing)
    res = cli("simulate", sc, "-o", tmp_path / "s.mcap")
    one_line_error(res, str(sc), f"sensors[{sensor}].period", "outside [1e-09, 1e+09] s")
    assert listing(tmp_path) == ["sc.toml"]


@pytest.mark.parametrize("value", ["1e-12", "1e10"])
def test_offset_outside_the_nanosecond_clock(tmp_path: Path, value: str) -> None:
    sc = write(tmp_path, f"period = 1e9\noffset = {value}")
    res = cli("simulate", sc, "-o", tmp_path / "s.mcap")
    one_line_error(res, "sensors[0].", "outside [1e-09, 1e+09] s")
    assert listing(tmp_path) == ["sc.toml"]


@pytest.mark.parametrize("offset", ["0.1", "0.25"])
def test_offset_without_period_must_be_below_dt(tmp_path: Path, offset: str) -> None:
    sc = write(tmp_path, "", f"offset = {offset}")
    res = cli("simulate", sc, "-o", tmp_path / "s.mcap")
    one_line_error(res, "sensors[1].offset", "must be < the period", "dt = 0.1 s")
    assert listing(tmp_path) == ["sc.toml"]


def test_offset_below_dt_without_period_is_accepted(tmp_path: Path) -> None:
    sc = write(tmp_path, "", "offset = 0.05")
    ok("simulate", sc, "-o", tmp_path / "s.mcap")
    # s2 measures at 0.05, 0.15, ...: irregular instants, the union with s1's k dt
    lines = ok("inspect", tmp_path / "s.mcap").stdout
    assert "/sensors/s2" in lines


def test_one_nanosecond_period_on_a_short_horizon_is_accepted(tmp_path: Path) -> None:
    # the bound is inclusive: 1 ns sampling over 20 ns (dt = 10 ns, 2 steps) is 21 instants
    sc = write(tmp_path, "period = 1e-9", steps=2, dt="1e-8")
    res = ok("simulate", sc, "-o", tmp_path / "s.mcap")
    assert "2 runs x 21 steps" in res.stdout


def test_billions_of_instants_refused_before_allocating(tmp_path: Path) -> None:
    # 1 ns over 2 s: about 2e9 instants; refused by the count (no schedule is built: the test
    # would take minutes and gigabytes otherwise)
    sc = write(tmp_path, "period = 1e-9")
    res = cli("simulate", sc, "-o", tmp_path / "s.mcap")
    line = one_line_error(res, str(sc), "sensors[0].period", "2000000", "instants", "GiB")
    assert "single run" in line and "this machine has" in line
    assert listing(tmp_path) == ["sc.toml"]


def test_more_instants_than_a_step_index_holds(tmp_path: Path) -> None:
    sc = write(tmp_path, "period = 1e-9", steps=100)  # 1e10 sampling times in 10 s
    one_line_error(cli("simulate", sc, "-o", tmp_path / "s.mcap"), "sensors[0].period", "uint32")


@pytest.mark.parametrize("where", ["file", "--steps"])
def test_a_billion_steps_refused_before_allocating(tmp_path: Path, where: str) -> None:
    if where == "file":
        sc = write(tmp_path, steps=1_000_000_000)
        res = cli("simulate", sc, "-o", tmp_path / "s.mcap")
        key = "scenario.steps"
    else:
        sc = write(tmp_path)
        res = cli("simulate", sc, "-o", tmp_path / "s.mcap", "--steps", "1000000000")
        key = "--steps"
    one_line_error(res, str(sc), key, "1000000001 instants", "GiB")
    assert listing(tmp_path) == ["sc.toml"]


def test_run_refuses_too(tmp_path: Path) -> None:
    sc = write(tmp_path, "period = 1e-12")
    res = cli("run", sc, "--out-dir", tmp_path / "out")
    one_line_error(res, "sensors[0].period", "outside")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("values", ["1e-12,0.2", "1e-300", "1e18", "1e-9"])
def test_sweep_over_periods_refuses_the_bad_point(tmp_path: Path, values: str) -> None:
    sc = write(tmp_path, "period = 0.2")
    res = cli("sweep", sc, "--vary", f"sensors.s1.period={values}", "--exact-only",
              "--out-dir", tmp_path / "out")  # fmt: skip
    one_line_error(res, "[point 0: sensors.s1.period=", "sensors[0].period")
    assert not (tmp_path / "out").exists()


def test_a_billion_steps_of_an_identity_scenario_refused_before_allocating(
    tmp_path: Path,
) -> None:
    root = Path(__file__).resolve().parents[1]
    text = (root / "pipeline" / "aircraft_identity.toml").read_text()
    sc = tmp_path / "sc.toml"
    sc.write_text(re.sub(r"(?m)^steps = .*$", "steps = 1000000000", text))
    for args in (
        ["simulate", sc, "-o", tmp_path / "s.mcap"],
        ["run", sc, "--out-dir", tmp_path / "o"],
    ):
        one_line_error(cli(*args), str(sc), "1000000001 instants", "GiB")
    assert listing(tmp_path) == ["sc.toml"]
