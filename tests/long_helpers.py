"""What the long-log tests (tests/test_long_*.py, issue 34) share: a log run whole and in blocks
of time (the hidden setting FUSIONLOG_TIME_BLOCK), the two runs' files compared (summaries,
estimates, recordings) at the tolerances each test states, counts of the blocks a path took,
the tracemalloc peaks of whole `run`s at several lengths, and the late sensors' scenario text.
"""

from __future__ import annotations

import json
import math
import tracemalloc
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import ok

from fusionlog.io.mcap import McapFile
from fusionlog.io.rrd import read_recording

# -- running whole and in blocks ---------------------------------------------------------------


def time_block(mp: pytest.MonkeyPatch, block: int | str | None) -> None:
    """Blocks of time of `block` instants (None: the default, longer than the tests' logs)."""
    if block is None:
        mp.delenv("FUSIONLOG_TIME_BLOCK", raising=False)
    else:
        mp.setenv("FUSIONLOG_TIME_BLOCK", str(block))


def run(scenario: Path, out: Path, block: int | str | None, mp: pytest.MonkeyPatch, *extra) -> Path:
    """`fusionlog run SCENARIO --out-dir OUT --force EXTRA` in blocks of `block` instants."""
    time_block(mp, block)
    ok("run", scenario, "--out-dir", out, "--force", *extra)
    return out


def whole_and_blocked(scenario: Path, tmp: Path, block: int | str, *extra, horizons=None,
                      spy: Callable | None = None):  # fmt: skip
    """`run` of `scenario` whole (tmp/whole) and in blocks of `block` instants (tmp/blocked);
    for the blocked run only, steady plans of `horizons` (`long_log.HORIZONS`) and `spy(mp)`
    (what counts its blocks). Returns (whole, blocked, what `spy` returned)."""
    import fusionlog.core.architectures.long_log as long_log

    mp = pytest.MonkeyPatch()
    try:
        whole = run(scenario, tmp / "whole", None, mp, *extra)
        if horizons is not None:
            mp.setattr(long_log, "HORIZONS", horizons)
        spied = None if spy is None else spy(mp)
        blocked = run(scenario, tmp / "blocked", block, mp, *extra)
    finally:
        mp.undo()
    return whole, blocked, spied


class Spy:
    """Counts, while the monkeypatch lasts, the calls of the functions or methods named in
    `calls` and what the generator functions named in `blocks` yield (the blocks of time a
    path took), each as an attribute of its keyword: ``Spy(mp, calls={"evaluated":
    (LongEvaluator, "add")}).evaluated``."""

    def __init__(self, mp: pytest.MonkeyPatch, *, calls=None, blocks=None) -> None:
        for key, (owner, name) in (calls or {}).items():
            mp.setattr(owner, name, self._calls(key, getattr(owner, name)))
        for key, (owner, name) in (blocks or {}).items():
            mp.setattr(owner, name, self._yields(key, getattr(owner, name)))

    def _add(self, key: str) -> None:
        setattr(self, key, getattr(self, key) + 1)

    def _calls(self, key: str, inner: Callable) -> Callable:
        setattr(self, key, 0)

        def wrapped(*a, **kw):
            self._add(key)
            return inner(*a, **kw)

        return wrapped

    def _yields(self, key: str, inner: Callable) -> Callable:
        setattr(self, key, 0)

        def wrapped(*a, **kw):
            for got in inner(*a, **kw):
                self._add(key)
                yield got

        return wrapped


def count_calls(mp: pytest.MonkeyPatch, owner, name: str) -> Spy:
    """A `Spy` of the calls of `owner.name` (a public function of one path): its `count`."""
    return Spy(mp, calls={"count": (owner, name)})


# -- comparing the two runs' files ---------------------------------------------------------------


def summaries_close(a, b, *, rtol: float, atol: float, nan: bool = False, exact_atol=None,
                    skip: Sequence[str] = (), bound_rtol=None, path: str = "") -> None:  # fmt: skip
    """Two summaries (JSON trees) alike: the same keys, lengths and other values; floats within
    `rtol` relative or `atol` absolute (`exact_atol` for the exact values and the bound's,
    paths holding ``.expected.`` or ``.bound.``); NaN equal to NaN where `nan`; dict keys in
    `skip` passed over; with `bound_rtol`, of a ``.bound`` entry its keys and its worst ratio
    (within `bound_rtol`) only."""
    kw = dict(rtol=rtol, atol=atol, nan=nan, exact_atol=exact_atol, skip=skip)
    kw["bound_rtol"] = bound_rtol
    if isinstance(a, dict):
        assert a.keys() == b.keys(), path
        if bound_rtol is not None and path.endswith(".bound"):
            assert math.isclose(a["worst"], b["worst"], rel_tol=bound_rtol), (path, a, b)
            return
        for k in a:
            if k not in skip:
                summaries_close(a[k], b[k], path=f"{path}.{k}", **kw)
    elif isinstance(a, list):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            summaries_close(x, y, path=f"{path}[{i}]", **kw)
    elif isinstance(a, float) and isinstance(b, float):
        if nan and math.isnan(a):
            assert math.isnan(b), path
            return
        exact = exact_atol is not None and (".expected." in path or ".bound." in path)
        tol = exact_atol if exact else atol
        assert math.isclose(a, b, rel_tol=rtol, abs_tol=tol), (path, a, b)
    else:
        assert a == b, (path, a, b)


def summaries(*folders: Path) -> list[dict]:
    """Each folder's summary.json."""
    return [json.loads((d / "summary.json").read_text()) for d in folders]


#: A tolerance of estimates_close: bit for bit
EQUAL = "equal"


@dataclass(frozen=True)
class OfLargest:
    """A tolerance of estimates_close: `r` times the largest entry of the whole run's, absolute
    (and `rtol` relative)."""

    r: float
    rtol: float = 0.0


def estimates_close(whole: Path, blocked: Path, archs: Sequence[str], mean, cov) -> None:
    """Each architecture's means and covariances in blocked/estimates.mcap against whole's:
    `mean`, `cov` each `EQUAL`, `OfLargest(r)` or (rtol, atol)."""
    topics = [f"/estimates/{a}" for a in archs]
    a = McapFile(whole / "estimates.mcap").read_all(topics)
    b = McapFile(blocked / "estimates.mcap").read_all(topics)
    for t in topics:
        for i, tol in ((0, mean), (1, cov)):
            arrays_close(b[t][i], a[t][i], tol, t)


def arrays_close(got, want, tol, what: str = "") -> None:
    """`got` against `want` within `tol` (`EQUAL`, `OfLargest(r)` or (rtol, atol))."""
    if tol == EQUAL:
        np.testing.assert_array_equal(got, want, err_msg=what)
    elif isinstance(tol, OfLargest):
        atol = tol.r * np.abs(want).max()
        np.testing.assert_allclose(got, want, rtol=tol.rtol, atol=atol, err_msg=what)
    else:
        np.testing.assert_allclose(got, want, rtol=tol[0], atol=tol[1], err_msg=what)


def series_close(whole: Path, blocked: Path, rtol: float, atol: float, exact_atol=None) -> None:
    """The two recordings draw the same series at the same steps: within `rtol` relative or
    `atol` absolute (`exact_atol` for the exact values' and the bound's series)."""
    a, b = (read_recording(d / "evaluation.rrd") for d in (whole, blocked))
    np.testing.assert_array_equal(a["steps"], b["steps"])
    assert a["series"].keys() == b["series"].keys()
    for key, v in a["series"].items():
        exact = exact_atol is not None and ("expected" in key or "bound" in key)
        tol = exact_atol if exact else atol
        np.testing.assert_allclose(b["series"][key], v, rtol=rtol, atol=tol, err_msg=key)


# -- memory ------------------------------------------------------------------------------------


def pipeline_peaks(tmp: Path, mp: pytest.MonkeyPatch, scenario: Path, archs, sizes, block: int,
                   above: int, buckets: int, **load) -> list[int]:  # fmt: skip
    """The Python allocations' peak (tracemalloc: numpy's arrays included) of a whole `run`
    of `scenario` with each number of steps in `sizes` (`load`: load_scenario's other
    arguments), in blocks of `block` instants, a recording decimated to `buckets` buckets
    (three points each) above `above` instants. The first size's peak holds what is imported
    on first use."""
    from fusionlog.core import decimate
    from fusionlog.scenario import load_scenario
    from fusionlog.stages.run import run_pipeline

    time_block(mp, block)
    mp.setattr(decimate, "DECIMATE_ABOVE", above)
    mp.setattr(decimate, "BUCKETS", buckets)
    peaks = []
    for K in sizes:
        sc = load_scenario(scenario, steps=K, **load)
        tracemalloc.start()
        try:
            run_pipeline(sc, tmp / str(K), archs=archs, force=True)
            peaks.append(tracemalloc.get_traced_memory()[1])
        finally:
            tracemalloc.stop()
    return peaks


# -- the late sensors' scenario ------------------------------------------------------------------

#: A constant-velocity target (q = 0.16) seen by position sensors, one run at 1 s instants.
LATE_HEADER = """
[scenario]
name = "{name}"
steps = {steps}
runs = 1
seed = {seed}
dt = 1.0
state_names = ["position", "velocity"]
[model]
{model}
[prior]
mean = [100.0, -1.0]
cov = [[1.0, 0.0], [0.0, 1.0]]
"""

CONSTANT_VELOCITY = 'kind = "constant-velocity"\nn0 = 0.16'


def position_sensor(name: str, R: float, latency: str | None = None, extra: str = "") -> str:
    """A `[[sensors]]` table of a position sensor (H = [1, 0]), late by `latency` (TOML)."""
    late = "" if latency is None else f"latency = {latency}\n"
    return f'[[sensors]]\nname = "{name}"\nH = [[1.0, 0.0]]\nR = {R}\n{late}{extra}'


#: s1 on time, s2 1 s late and s3 3 s late (R 1, 2 and 0.5)
LATE_SENSORS = (
    position_sensor("s1", 1.0)
    + position_sensor("s2", 2.0, "1.0")
    + position_sensor("s3", 0.5, "3.0")
)


def late_toml(name: str, seed: int, steps: int, sensors: str, archs: Sequence[str], late: str,
              model: str = CONSTANT_VELOCITY) -> str:  # fmt: skip
    """The scenario's text: `LATE_HEADER`, the sensors' tables and `[estimate]`."""
    head = LATE_HEADER.format(name=name, steps=steps, seed=seed, model=model)
    estimate = f'[estimate]\narchitectures = {json.dumps(list(archs))}\nlate = "{late}"\n'
    return head + sensors + estimate


# -- a recorded replay with a late sensor --------------------------------------------------------

NS = 1_000_000_000
#: the recordings' clock (ns)
T0 = 1_700_000_000 * NS


def stamped_mcap(path: Path, topics: Sequence[str], events) -> None:
    """A JSON MCAP (mcap's own Writer) of readings ``{"header": {"stamp": ...}, "v": v}``:
    `events` (log time ns, topic, stamp ns, v) written in log-time order."""
    from mcap.writer import Writer

    schema = {"type": "object", "properties": {"header": {"type": "object"},
                                               "v": {"type": "number"}}}  # fmt: skip
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("Reading", "jsonschema", json.dumps(schema).encode())
        ch = {t: w.register_channel(t, "json", sid) for t in topics}
        for lg, t, stamp, v in sorted(events):
            body = {"header": {"stamp": {"sec": stamp // NS, "nanosec": stamp % NS}}, "v": v}
            w.add_message(ch[t], log_time=lg, data=json.dumps(body).encode(), publish_time=lg)
        w.finish()


def random_walk(qc: float) -> str:
    """`[model]` and `[prior]` of the recorded replays' random walk (A 0, Qc `qc`)."""
    return (f'[model]\nkind = "continuous"\nA = [[0.0]]\nQc = [[{qc}]]\n'
            "[prior]\nmean = [0.0]\ncov = [[4.0]]\n")  # fmt: skip


def recorded_toml(name: str, archs: Sequence[str], late: str, truth: str = "") -> str:
    """The scenario of `stamped_mcap`'s log.mcap: a random walk (Qc 0.4) seen by a on time
    (R 0.49) and b (R 0.16) arriving at its messages' log times; `truth` its `[truth]`."""
    sensor = 'source = "log.mcap"\nvalues = ["v"]\ntime = "header.stamp"\nH = [[1.0]]\n'
    return f"""
[scenario]
name = "{name}"
state_names = ["x"]
{random_walk(0.4)}[[sensors]]
name = "a"
topic = "/a"
{sensor}R = 0.49
[[sensors]]
name = "b"
topic = "/b"
{sensor}R = 0.16
arrival = "log_time"
{truth}[estimate]
architectures = {json.dumps(list(archs))}
late = "{late}"
"""


#: the per-message recordings' clock (s)
T0_S = 1_700_000_000


def per_message_recording(folder: Path, per_sensor: int, seed: int, name: str, archs,
                          late: bool = False) -> tuple[Path, dict]:  # fmt: skip
    """A replay of two position sensors at their own irregular instants: `a` in a JSON MCAP
    whose messages carry their own variance (0.05..5, the field `c`) -- with `late`, logged
    0..0.12 s after their stamp `t` (``arrival = "log_time"``) --, `b` in a CSV with one R,
    on time; the truth (p, v) at every instant in a CSV (constant velocity, n0 0.5). Returns
    the replay file and a's data {"t", "z", "r"}."""
    from test_replay_sources import write_json_mcap

    rng = np.random.default_rng(seed)
    ta = np.round(np.cumsum(rng.uniform(0.02, 0.06, per_sensor)), 4)
    tb = np.round(np.cumsum(rng.uniform(0.02, 0.06, per_sensor)) + 0.00005, 5)
    t = np.union1d(ta, tb)
    v = 1.0 + 0.2 * np.cumsum(rng.normal(size=len(t))) * 0.05
    p = np.concatenate([[0.0], np.cumsum(v[:-1] * np.diff(t))])
    ra = np.exp(rng.uniform(np.log(0.05), np.log(5.0), per_sensor))
    za = p[np.searchsorted(t, ta)] + np.sqrt(ra) * rng.normal(size=per_sensor)
    zb = p[np.searchsorted(t, tb)] + np.sqrt(0.5) * rng.normal(size=per_sensor)
    msgs = [
        (int((T0_S + x) * 1e9), {"t": T0_S + float(x), "z": float(z), "c": [float(r)]})
        for x, z, r in zip(ta, za, ra, strict=True)
    ]
    if late:
        logged = ta + rng.uniform(0.0, 0.12, per_sensor)
        msgs = sorted(
            (int(round((T0_S + g) * 1e9)), m) for g, (_, m) in zip(logged, msgs, strict=True)
        )
    write_json_mcap(folder / "a.mcap", {"/a": msgs})
    (folder / "b.csv").write_text(
        "time,b\n" + "".join(f"{T0_S + x:.5f},{float(z)!r}\n" for x, z in zip(tb, zb, strict=True))
    )
    rows = zip(t, p, v, strict=True)
    (folder / "truth.csv").write_text(
        "time,p,v\n" + "".join(f"{T0_S + x:.5f},{float(a)!r},{float(b)!r}\n" for x, a, b in rows)
    )
    arrival = 'arrival = "log_time"\n' if late else ""
    replay = folder / "replay.toml"
    replay.write_text(
        f'[scenario]\nname = "{name}"\nstate_names = ["p", "v"]\n'
        '[model]\nkind = "constant-velocity"\nn0 = 0.5\n'
        "[prior]\nmean = [0.0, 1.0]\ncov = [[1.0, 0.0], [0.0, 1.0]]\n"
        '[[sensors]]\nname = "a"\nsource = "a.mcap"\ntopic = "/a"\nvalues = ["z"]\n'
        f'time = "t"\ncovariance = "c"\n{arrival}H = [[1.0, 0.0]]\nR = 1.0\n'
        '[[sensors]]\nname = "b"\nsource = "b.csv"\nvalues = ["b"]\nH = [[1.0, 0.0]]\n'
        "R = 0.5\n"
        '[truth]\nsource = "truth.csv"\nvalues = ["p", "v"]\nstates = ["p", "v"]\n'
        'match = "exact"\n'
        f"[estimate]\narchitectures = {json.dumps(list(archs))}\n"
    )  # fmt: skip
    return replay, {"t": ta, "z": za, "r": ra}


def csv_replay_toml(name: str, tail: str = "") -> str:
    """A replay of `log.csv` (time in ns): two position sensors a and b (R = 1) of a
    constant-velocity model with a prior, the truth of the position p matched exactly; `tail`:
    more tables (an `[estimate]`)."""
    sensors = "".join(
        f'[[sensors]]\nname = "{x}"\nsource = "log.csv"\nvalues = ["{x}"]\ntime_unit = "ns"\n'
        "H = [[1.0, 0.0]]\nR = 1.0\n"
        for x in "ab"
    )
    return (
        f'[scenario]\nname = "{name}"\nstate_names = ["p", "v"]\n'
        '[model]\nkind = "constant-velocity"\nn0 = 0.5\n'
        "[prior]\nmean = [1.0, 0.0]\ncov = [[1.0, 0.0], [0.0, 1.0]]\n"
        + sensors
        + '[truth]\nsource = "log.csv"\nvalues = ["p"]\nstates = ["p"]\ntime_unit = "ns"\n'
        'match = "exact"\n' + tail
    )


def irregular_csv_replay(folder: Path, rows: int, scenario: str, pad: str = ""):
    """`folder`/log.csv of `rows` instants 5 ms +- 40 % apart (ns), sensors a and b reading the
    position p with unit noise, each missing at 5 % of the rows, and `pad` as one more column
    not read (wider rows); `folder`/replay.toml of `scenario`; the scenario loaded."""
    from fusionlog.scenario import load_scenario

    rng = np.random.default_rng(34)
    t = np.cumsum(np.round(5_000_000 * (1 + 0.4 * rng.uniform(-1, 1, rows)))).astype(np.int64)
    p = 1.0 + np.cumsum(0.01 * np.cumsum(rng.normal(size=rows))) * 0.005
    a, b = p + rng.normal(size=rows), p + rng.normal(size=rows)
    a[rng.random(rows) < 0.05] = np.nan
    b[rng.random(rows) < 0.05] = np.nan
    extra = f",{pad}" if pad else ""
    with open(folder / "log.csv", "w") as f:
        f.write("time,a,b,p" + (",pad" if pad else "") + "\n")
        f.writelines(
            f"{u},{x:.6f},{y:.6f},{z:.9f}{extra}\n".replace("nan", "")
            for u, x, y, z in zip(t, a, b, p, strict=True)
        )
    (folder / "replay.toml").write_text(scenario)
    return load_scenario(folder / "replay.toml")
