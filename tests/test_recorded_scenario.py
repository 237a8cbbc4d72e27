"""The scenario a sensors file records (`fusionlog.scenario`) is rebuilt as it was run, without
the value checks it passed when it was simulated (issue 29: `fusionlog evaluate` put the record
through the whole loader again), and a foreign record is still refused in one line."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import cli

from fusionlog.errors import FusionlogError
from fusionlog.io.mcap import McapFile
from fusionlog.scenario import load_scenario, scenario_from_metadata, scenario_with
from fusionlog.stages.common import scenario_from_file

PIPELINE = Path(__file__).resolve().parents[1] / "pipeline"


def _arrays(obj, prefix=""):
    """Every array and number reachable through the dataclass fields of `obj`, by path."""
    out = {}
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        for f in dataclasses.fields(obj):
            out |= _arrays(getattr(obj, f.name), f"{prefix}.{f.name}")
    elif isinstance(obj, (tuple, list)):
        for i, v in enumerate(obj):
            out |= _arrays(v, f"{prefix}[{i}]")
    elif isinstance(obj, dict):
        for k, v in obj.items():
            out |= _arrays(v, f"{prefix}[{k!r}]")
    elif isinstance(obj, (np.ndarray, int, float, str, bool)) or obj is None:
        out[prefix] = obj
    return out


@pytest.mark.parametrize(
    "name",
    ["ajgl2009.toml", "gustafsson_correlated.toml", "multirate.toml", "aircraft_identity.toml"],
)
def test_the_recorded_scenario_is_the_simulated_one(tmp_path: Path, name: str) -> None:
    """Rebuilt from the record, the scenario has the loaded file's every matrix, setting and
    name, bit for bit (the runs, steps and seed the simulation was run with)."""
    out = tmp_path / "s.mcap"
    args = ("--runs", "3", "--steps", "7", "--seed", "5")
    res = cli("simulate", PIPELINE / name, "-o", out, *args)
    assert res.exit_code == 0, res.output
    recorded = scenario_from_file(McapFile(out))
    loaded = scenario_with(load_scenario(PIPELINE / name), runs=3, steps=7, seed=5)
    got, want = _arrays(recorded), _arrays(loaded)
    want.pop(".path")  # the record has no file of its own
    got.pop(".path")
    assert got.keys() == want.keys()
    for key, w in want.items():
        if isinstance(w, np.ndarray):
            np.testing.assert_array_equal(got[key], w, err_msg=key)
        else:
            assert got[key] == w, key


@pytest.mark.parametrize(
    ("change", "fragment"),
    [
        (
            lambda m: m | {"toml": m["toml"].replace("[scenario]", "[scenario]\nspeed = 3", 1)},
            "speed",
        ),
        (lambda m: m | {"toml": m["toml"].replace("[scenario]", "[scenario", 1)}, "invalid TOML"),
        (lambda m: {k: v for k, v in m.items() if k != "runs"}, "runs"),
        (lambda m: m | {"kind": "weather"}, "weather"),
        (lambda m: m | {"steps": "x"}, "x"),
    ],
)
def test_a_foreign_record_is_refused_in_one_line(tmp_path: Path, change, fragment: str) -> None:
    """A record that is not one fusionlog wrote (a key no scenario has, no TOML, a setting
    missing or not a number, an unknown kind) is refused with one line naming it."""
    out = tmp_path / "s.mcap"
    assert cli("simulate", PIPELINE / "ajgl2009.toml", "-o", out, "--runs", "2").exit_code == 0
    meta = change(dict(McapFile(out).metadata["fusionlog.scenario"]))
    with pytest.raises(FusionlogError) as e:
        scenario_from_metadata(meta, "rec")
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith("rec") and fragment in msg, msg
