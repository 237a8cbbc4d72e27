"""The import of text tables at 10^6 rows (issue 34): each file read once for all its streams,
in blocks (pyarrow's CSV parser), the sensors file written a window of instants at once.

References, written here from the formats: the rows read with Python's csv module, the times
from their digits with ``decimal`` (half to even), the values with ``float``; the sensors file
written one ``McapWriter.write_values`` per message (whose bytes test_mcap_wire checks against
the official protobuf classes). The bad inputs' messages are written out by hand: they are the
line-by-line reader's, naming the file, the stream and the line, exit 2."""

from __future__ import annotations

import csv
import io
import tracemalloc
from decimal import ROUND_HALF_EVEN, Decimal
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import cli, ok, one_line_error
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader

from fusionlog.io.mcap import VALUES, McapWriter
from fusionlog.io.mcap.run_steps import RunColumn
from fusionlog.io.replay import read_streams
from fusionlog.io.replay.text_fast import TextRequest, read_table_streams

EXP = {"s": 9, "ms": 6, "us": 3, "ns": 0}
MODEL = (
    '[scenario]\nname = "fast_csv"\nstate_names = ["p", "v"]\n'
    '[model]\nkind = "constant-velocity"\nn0 = 0.5\n'
    "[prior]\nmean = [1.0, 0.0]\ncov = [[1.0, 0.0], [0.0, 1.0]]\n"
)


def ns_of(text: str, unit: str) -> int:
    """Whole nanoseconds of a decimal time, half to even (the reference)."""
    d = Decimal(text.strip()).scaleb(EXP[unit])
    return int(d.to_integral_value(rounding=ROUND_HALF_EVEN))


def stream(path: Path, tcol: str, vcols: list[str], unit: str, delim: str):
    """(times ns, values) of a table's stream: rows with an empty/NaN/inf value skipped, the
    rest sorted by time (stable)."""
    with open(path, newline="") as f:
        rows = list(csv.reader(f, delimiter=delim))
    head = [h.strip() for h in rows[0]]
    t, v = [], []
    for row in rows[1:]:
        vals = [float(row[head.index(c)]) if row[head.index(c)].strip() else np.nan
                for c in vcols]  # fmt: skip
        if np.isfinite(vals).all():
            t.append(ns_of(row[head.index(tcol)], unit))
            v.append(vals)
    order = sorted(range(len(t)), key=t.__getitem__)
    return [t[i] for i in order], np.array([v[i] for i in order])


def _seconds(rng: np.random.Generator, n: int) -> list[str]:
    """Irregular times in s from 1305031102.160407 with 6 to 12 decimals, some exactly half
    way between two nanoseconds (…5, …500), increasing."""
    base = Decimal("1305031102.160407")
    steps = rng.integers(2_000_000_000, 8_000_000_000, n)  # picoseconds
    steps[rng.random(n) < 0.2] = 4_000_000_500  # half a nanosecond: half to even
    out = []
    t = base
    for s in steps.tolist():
        t += Decimal(s).scaleb(-12)
        out.append(f"{t:.{rng.integers(6, 13)}f}")
    return out


def _values(rng: np.random.Generator, n: int, missing: float) -> list[str]:
    x = [repr(float(v)) for v in rng.normal(size=n)]
    for i in np.flatnonzero(rng.random(n) < missing).tolist():
        x[i] = ["", "nan", " ", "-inf"][i % 4]  # a missing reading: the row skipped
    return x


@pytest.fixture
def logs(tmp_path: Path) -> Path:
    """Sensor a and the truth in log1.csv (comma, s), sensor b in log2.csv (semicolon, ms,
    another clock's instants); 70 000 rows: more than one window of the writer and one
    out-of-order row."""
    rng = np.random.default_rng(34)
    n = 70_000
    t1 = _seconds(rng, n)
    t1[100], t1[101] = t1[101], t1[100]  # out of time order: sorted, noted
    a, p, v = _values(rng, n, 0.05), _values(rng, n, 0.0), _values(rng, n, 0.0)
    rows = zip(t1, a, p, v, strict=True)
    (tmp_path / "log1.csv").write_text(
        "time , a,p,v\n" + "".join(f"{x}, {y},{z},{w}\n" for x, y, z, w in rows)
    )
    ms = [f"{ns_of(x, 's') / Decimal(10**6) + Decimal('0.0015'):f}" for x in t1[::3]]
    b = _values(rng, len(ms), 0.1)
    (tmp_path / "log2.csv").write_text(
        "stamp;b\r\n" + "".join(f"{x};{y}\r\n" for x, y in zip(ms, b, strict=True))
    )
    sensors = "".join(
        f'[[sensors]]\nname = "{x}"\nsource = "{src}"\nvalues = ["{x}"]\n{time}'
        "H = [[1.0, 0.0]]\nR = 1.0\n"
        for x, src, time in (("a", "log1.csv", ""),
                             ("b", "log2.csv", 'time = "stamp"\ntime_unit = "ms"\n'))
    )  # fmt: skip
    (tmp_path / "replay.toml").write_text(
        MODEL + sensors + '[truth]\nsource = "log1.csv"\nvalues = ["p", "v"]\n'
        'states = ["p", "v"]\nmatch = "exact"\n'
    )
    return tmp_path


def _messages(data: bytes) -> tuple[list, dict]:
    """Each message (topic, log_time, publish_time, bytes) in file order, and the layout."""
    reader = make_reader(io.BytesIO(data))
    msgs = [(ch.topic, m.log_time, m.publish_time, bytes(m.data))
            for _, ch, m in reader.iter_messages(log_time_order=False)]  # fmt: skip
    meta = {m.name: m.metadata for m in make_reader(io.BytesIO(data)).iter_metadata()}
    return msgs, meta["fusionlog.layout"]


def _reference(logs: Path) -> bytes:
    """The sensors file one write_values per message: instants the sorted union of a's and
    b's times, at each the truth (exact match) then a then b."""
    ta, va = stream(logs / "log1.csv", "time", ["a"], "s", ",")
    tb, vb = stream(logs / "log2.csv", "stamp", ["b"], "ms", ";")
    tt, vt = stream(logs / "log1.csv", "time", ["p", "v"], "s", ",")
    instants = sorted(set(ta) | set(tb))
    by = [dict(zip(x, y, strict=True)) for x, y in ((tt, vt), (ta, va), (tb, vb))]
    f = io.BytesIO()
    with McapWriter(f, time_origin_ns=instants[0]) as w:
        for k, t in enumerate(instants):
            s = (t - instants[0]) / 1e9
            for topic, got in zip(("/truth", "/sensors/a", "/sensors/b"), by, strict=True):
                if t in got:
                    w.write_values(topic, k, s, 0, got[t][None])
    return f.getvalue()


def test_import_is_the_file_written_message_by_message(logs: Path) -> None:
    """Irregular decimal times of two files and clocks (half-way nanoseconds), empty and NaN
    cells, an out-of-order row, CRLF lines, spaces around cells: the same messages, byte for
    byte, in the same order, with the same log times and layout record."""
    res = ok("import", logs / "replay.toml", "-o", logs / "s.mcap")
    assert "note: a: 1 row out of time order (sorted)" in res.stdout
    got, layout = _messages((logs / "s.mcap").read_bytes())
    want, want_layout = _messages(_reference(logs))
    assert len(got) == len(want) > 70_000
    assert got == want
    assert layout == want_layout


def test_a_table_is_read_once_for_all_its_streams_with_exact_times(logs: Path) -> None:
    """read_table_streams (one pass) gives each stream's exact ns and values as read_streams,
    which gives the reference's."""
    reqs = [TextRequest("a", ("a",), None, "s"), TextRequest("truth", ("p", "v"), None, "s")]
    fast = read_table_streams(logs / "log1.csv", None, None, reqs)
    assert all(s is not None for s in fast)
    for s, (tcol, vcols) in zip(fast, (("time", ["a"]), ("time", ["p", "v"])), strict=True):
        t, v = stream(logs / "log1.csv", tcol, vcols, "s", ",")
        assert s.times_ns.tolist() == t
        assert np.array_equal(s.values, v)
    both = read_streams([(logs / "log1.csv", {"values": ["a"]}, "a"),
                         (logs / "log2.csv", {"values": ["b"], "time": "stamp",
                                              "time_unit": "ms"}, "b")])  # fmt: skip
    t, v = stream(logs / "log2.csv", "stamp", ["b"], "ms", ";")
    assert both[1].times_ns.tolist() == t and np.array_equal(both[1].values, v)
    assert both[0].times_ns.tolist() == fast[0].times_ns.tolist()


_DIGITS = st.text("0123456789", min_size=0, max_size=12)


@settings(
    max_examples=60,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
@given(
    whole=st.lists(st.text("0123456789", max_size=9), min_size=3, max_size=3),
    frac=st.lists(st.one_of(st.none(), _DIGITS), min_size=3, max_size=3),
    unit=st.sampled_from(["s", "ms", "us", "ns"]),
    values=st.lists(st.one_of(st.floats(allow_nan=False, allow_infinity=False).map(repr),
                              st.from_regex(r"\A[+-]?[0-9]{1,25}(\.[0-9]{0,25})?"
                                            r"([eE][+-]?[0-9]{1,3})?\Z"),
                              st.sampled_from(["", "NaN", "-inf", "Infinity", "5e-324",
                                               "2.4703282292062328e-324", "1e400"])),
                    min_size=3, max_size=3),
)  # fmt: skip
def test_cells_read_in_blocks_are_the_digits_exactly(tmp_path, whole, frac, unit, values):
    """Times of 0-12 whole and 0-12 fraction digits in every unit = Decimal's half to even;
    values = Python's float (long mantissas, subnormals, overflow to inf skips the row)."""
    cells = [w + ("" if f is None else "." + f) for w, f in zip(whole, frac, strict=True)]
    cells = [c if any(ch.isdigit() for ch in c) else "0" for c in cells]
    times = sorted(cells, key=lambda c: ns_of(c, unit))
    if len({ns_of(c, unit) for c in times}) < 3:
        return  # two rows at one instant: an error, read line by line (below)
    p = tmp_path / "t.csv"
    p.write_text("time,x\n" + "".join(f"{t},{x}\n" for t, x in zip(times, values, strict=True)))
    (s,) = read_table_streams(p, None, None, [TextRequest("x", ("x",), None, unit)])
    (small,) = read_table_streams(p, None, None, [TextRequest("x", ("x",), None, unit)], 16)
    assert (s is None and small is None) or (
        np.array_equal(s.times_ns, small.times_ns) and np.array_equal(s.values, small.values)
    )  # blocks of a line or two: the same
    keep = [i for i, x in enumerate(values) if np.isfinite(float(x) if x.strip() else np.nan)]
    if not keep:
        assert s is None  # no row: the line-by-line reader's error
        return
    assert s.times_ns.tolist() == [ns_of(times[i], unit) for i in keep]
    assert s.values[:, 0].tolist() == [float(values[i]) for i in keep]


def _import_error(logs: Path, file: str, text: str) -> str:
    (logs / file).write_text(text)
    return one_line_error(cli("import", logs / "replay.toml", "-o", logs / "s.mcap"))


@pytest.mark.parametrize(
    ("file", "line", "col", "cell", "says"),
    [("log1.csv", 5, 1, "1.2.3", "sensors[0] (a): line 5: column 'a': '1.2.3' is not a number"),
     ("log1.csv", 4, 2, "x", "truth: line 4: column 'p': 'x' is not a number"),
     ("log2.csv", 3, 1, "0x1", "sensors[1] (b): line 3: column 'b': '0x1' is not a number")],
)  # fmt: skip
def test_a_malformed_number_is_the_line_by_line_message(logs, file, line, col, cell, says):
    """The stream whose column holds it is named (in the replay's order), with its line."""
    with open(logs / file, newline="") as f:
        rows = f.read().splitlines(keepends=True)
    sep = ";" if file == "log2.csv" else ","
    fields = rows[line - 1].rstrip("\r\n").split(sep)
    fields[col] = cell
    rows[line - 1] = sep.join(fields) + "\n"
    err = _import_error(logs, file, "".join(rows))
    assert err == f"fusionlog: error: {logs / file}: {says}"


def test_duplicate_short_negative_rows_are_the_line_by_line_messages(logs: Path) -> None:
    rows = (logs / "log1.csv").read_text().splitlines(keepends=True)
    t = rows[2].split(",")[0]
    dup = rows[:2] + [f"{t},1.0,2.0,3.0\n"] * 2 + rows[3:]
    t = ns_of(t, "s")
    assert _import_error(logs, "log1.csv", "".join(dup)) == (
        f"fusionlog: error: {logs / 'log1.csv'}: sensors[0] (a): duplicate instant {t} ns: "
        "line 3 and line 4 have the same time"
    )
    short = rows[:6] + ["1305031200.5,1.0\n"] + rows[6:]
    assert _import_error(logs, "log1.csv", "".join(short)) == (
        f"fusionlog: error: {logs / 'log1.csv'}: sensors[0] (a): line 7: 2 fields where the "
        "header has 4 (delimiter ',')"
    )
    neg = rows[:2] + ["-1.5,1,2,3\n"] + rows[2:]
    assert _import_error(logs, "log1.csv", "".join(neg)) == (
        f"fusionlog: error: {logs / 'log1.csv'}: sensors[0] (a): line 3: time -1500000000 ns "
        "is negative (before 1970): a log's 64-bit nanosecond clock cannot hold it"
    )


def test_a_bad_cell_blocks_into_the_file_names_its_line(tmp_path: Path) -> None:
    """A table of ~14 MB (more than one block): the bad cell near its end, its line named."""
    n = 400_000
    body = "".join(f"{i},{i % 97}.25\n" for i in range(n))
    (tmp_path / "t.csv").write_text("time,x\n" + body + f"{n},1e\n")
    (tmp_path / "r.toml").write_text(
        MODEL + '[[sensors]]\nname = "x"\nsource = "t.csv"\nvalues = ["x"]\ntime_unit = "ns"\n'
        "H = [[1.0, 0.0]]\nR = 1.0\n"
    )
    err = one_line_error(cli("import", tmp_path / "r.toml", "-o", tmp_path / "s.mcap"))
    assert err == (
        f"fusionlog: error: {tmp_path / 't.csv'}: sensors[0] (x): line {n + 2}: column 'x': "
        "'1e' is not a number"
    )


def _peak(path: Path) -> tuple[int, int]:
    """tracemalloc's peak while a table of three streams is read in blocks of 64 kB, and the
    bytes of the Series it returns."""
    reqs = [TextRequest(w, v, None, "ns") for v, w in
            ((("a",), "a"), (("b",), "b"), (("p", "v"), "truth"))]  # fmt: skip
    tracemalloc.start()
    try:
        out = read_table_streams(path, None, None, reqs, 1 << 16)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    return peak, sum(s.times_ns.nbytes + s.values.nbytes for s in out)


@pytest.mark.memory
def test_reading_in_blocks_holds_arrays_not_rows(tmp_path: Path) -> None:
    """The peak grows with the rows as the returned arrays do (their collection and one copy:
    ≤ 2.5x), not as per-row Python objects (a float and its list slot: 4x an 8-byte value);
    the blocks' share (the same block size for both) cancels."""
    rng = np.random.default_rng(1)
    sizes = []
    for n in (60_000, 120_000):
        x = rng.normal(size=(n, 4))
        p = tmp_path / f"{n}.csv"
        p.write_text(
            "time,a,b,p,v\n"
            + "".join(
                f"{i * 5_000_000},{r[0]!r},{r[1]!r},{r[2]!r},{r[3]!r}\n"
                for i, r in enumerate(x.tolist())
            )
        )
        sizes.append(_peak(p) if sizes else (_peak(p), _peak(p))[1])  # first: imports
    (p1, b1), (p2, b2) = sizes
    assert b2 - b1 == 60_000 * (3 * 8 + 4 * 8)
    assert p2 - p1 <= 2.5 * (b2 - b1), (p2 - p1, b2 - b1)


def test_a_window_with_present_instants_and_arrivals_is_the_one_by_one_file() -> None:
    """write_run_steps with `present` (topics each at their own instants, one first present
    after the first window) and a sensor's arrivals and covariances = one write_values per
    message."""
    rng = np.random.default_rng(3)
    w = 9000
    times = np.cumsum(rng.uniform(0.001, 0.01, w))
    times[0] = 0.0
    present = rng.random((w, 3)) < [0.3, 0.9, 0.5]
    present[:5000, 2] = False  # /sensors/b first appears after one window of 4096
    present[present.sum(axis=1) == 0, 1] = True
    cols = [RunColumn("/truth", VALUES, rng.normal(size=(w, 2))),
            RunColumn("/sensors/a", VALUES, rng.normal(size=(w, 1)), rng.normal(size=(w, 1, 1)),
                      times + rng.uniform(0, 0.05, w)),
            RunColumn("/sensors/b", VALUES, rng.normal(size=(w, 2)))]  # fmt: skip
    origin = 1_700_000_000_123_456_789
    at_once, one = io.BytesIO(), io.BytesIO()
    with McapWriter(at_once, time_origin_ns=origin) as wr:
        wr.declare_arrival()
        wr.write_run_steps(0, times[:3000], [c.rows(0, 3000) for c in cols], present[:3000])
        wr.write_run_steps(3000, times[3000:], [c.rows(3000, w) for c in cols], present[3000:])
    with McapWriter(one, time_origin_ns=origin) as wr:
        wr.declare_arrival()
        for k in range(w):
            for c, col in enumerate(cols):
                if present[k, c]:
                    cov = None if col.second is None else col.second[k][None]
                    arr = None if col.arrival is None else float(col.arrival[k])
                    wr.write_values(col.topic, k, float(times[k]), 0, col.first[k][None], cov,
                                    arrival=arr)  # fmt: skip
    assert at_once.getvalue() == one.getvalue()
    with McapWriter(io.BytesIO()) as wr, pytest.raises(ValueError, match="every instant"):
        wr.write_run_steps(0, times[:2], cols[:1], np.array([[True], [False]]))
