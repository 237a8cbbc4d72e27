"""The ``fusionlog.layout`` record of a long log (issue 34): past `LISTED` instants a log with
irregular times or a sparse topic gets the record without its lists, and the reader learns them
from a scan of the file; a regular, dense log keeps its ``dt``; a file whose record lists them
(the single-record form every earlier writer wrote, made here by hand with mcap's own writer)
still opens through them. The reference is what was written: the times and each topic's steps
and values handed to the writer."""

from __future__ import annotations

import json
import tracemalloc

import numpy as np
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.writer import Writer
from mcap_helpers import mcap_writer

from fusionlog.io.mcap import McapFile
from fusionlog.io.mcap.layout import LAYOUT_META, LISTED
from fusionlog.io.mcap.run_steps import RunColumn
from fusionlog.io.mcap.schema import SENSOR_SCHEMA, VALUES, file_descriptor_set

S = LISTED + 3000  # past the lists' length, by less than a block of time
TOPICS = ("/truth", "/sensors/a", "/sensors/b")


def _log(seed: int, steps: int, regular: bool = False, sparse: bool = True):
    """Times (S,) s, and each topic's steps and values (one value: 1000 topic + step)."""
    rng = np.random.default_rng(seed)
    times = np.arange(steps) * 0.005
    if not regular:
        times = np.concatenate(([0.0], np.cumsum(rng.uniform(0.003, 0.007, steps - 1))))
    at = {"/truth": np.arange(steps)}
    at["/sensors/a"] = np.flatnonzero(rng.random(steps) < 0.7) if sparse else np.arange(steps)
    at["/sensors/b"] = np.arange(1, steps, 3) if sparse else np.arange(steps)
    at["/truth"] = np.union1d(at["/truth"], at["/sensors/a"])  # every instant has a message
    return times, at


def _write(path, times, at, window=1 << 14):
    """The log through `write_run_steps`, a window of instants at a time (as the import)."""
    with mcap_writer(path) as w:
        for k0 in range(0, len(times), window):
            k1 = min(len(times), k0 + window)
            present = np.zeros((k1 - k0, len(TOPICS)), bool)
            cols = []
            for c, topic in enumerate(TOPICS):
                steps = at[topic][(at[topic] >= k0) & (at[topic] < k1)]
                present[steps - k0, c] = True
                vals = (1000.0 * c + np.arange(k0, k1, dtype=float))[:, None]
                cols.append(RunColumn(topic, VALUES, vals))
            w.write_run_steps(k0, times[k0:k1], cols, present)


def _check_reads_back(f: McapFile, times, at):
    assert f.times().tobytes() == np.asarray(times, float).tobytes()
    for c, topic in enumerate(TOPICS):
        np.testing.assert_array_equal(np.flatnonzero(f.topic_steps(topic)), at[topic])
        got = np.concatenate([d[topic][0, :, 0] for _, _, d in f.iter_time_blocks([topic], 20_000)])
        np.testing.assert_array_equal(np.flatnonzero(~np.isnan(got)), at[topic])
        np.testing.assert_array_equal(got[at[topic]], 1000.0 * c + at[topic])


def test_a_long_irregular_sparse_log_leaves_the_lists_out_and_reads_back(tmp_path):
    times, at = _log(1, S)
    _write(tmp_path / "s.mcap", times, at)
    f = McapFile(tmp_path / "s.mcap")
    meta = dict(f.metadata[LAYOUT_META])
    assert meta["unlisted"] == "times sparse" and meta["instants"] == str(S)
    assert "times" not in meta and "sparse" not in meta and "dt" not in meta
    _check_reads_back(f, times, at)


def test_a_long_regular_log_with_a_sparse_topic_lists_its_dt_not_its_steps(tmp_path):
    times, at = _log(2, S, regular=True)
    _write(tmp_path / "s.mcap", times, at)
    f = McapFile(tmp_path / "s.mcap")
    meta = dict(f.metadata[LAYOUT_META])
    assert meta["unlisted"] == "sparse" and "sparse" not in meta
    _check_reads_back(f, times, at)


def test_a_long_regular_dense_log_keeps_its_dt(tmp_path):
    times, at = _log(3, S, regular=True, sparse=False)
    _write(tmp_path / "s.mcap", times, at)
    f = McapFile(tmp_path / "s.mcap")
    meta = dict(f.metadata[LAYOUT_META])
    assert meta["dt"] == repr(0.005) and "unlisted" not in meta and "times" not in meta
    _check_reads_back(f, times, at)


def test_a_short_irregular_sparse_log_still_lists_them(tmp_path):
    times, at = _log(4, 5000)
    _write(tmp_path / "s.mcap", times, at)
    f = McapFile(tmp_path / "s.mcap")
    meta = dict(f.metadata[LAYOUT_META])
    assert "unlisted" not in meta
    assert meta["times"] == json.dumps(times.tolist())
    sparse = {t: at[t].tolist() for t in ("/sensors/a", "/sensors/b")}
    assert meta["sparse"] == json.dumps(sparse, sort_keys=True)
    _check_reads_back(McapFile(tmp_path / "s.mcap"), times, at)


def _protobuf_block():
    fds = descriptor_pb2.FileDescriptorSet.FromString(file_descriptor_set())
    pool = descriptor_pool.DescriptorPool()
    for fd in fds.file:
        pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(SENSOR_SCHEMA))


def test_a_long_log_whose_record_lists_them_still_opens(tmp_path):
    """The single-record form (format 1, every time and sparse step listed as JSON), written
    by hand past `LISTED` instants with mcap's own writer."""
    times, at = _log(5, S)
    Block = _protobuf_block()
    path = tmp_path / "old.mcap"
    record = {
        "format": "1", "instants": str(S), "runs": "1", "blocks": "1",
        "topics": json.dumps(dict.fromkeys(TOPICS, 1), sort_keys=True),
        "sparse": json.dumps({t: at[t].tolist() for t in TOPICS[1:]}, sort_keys=True),
        "times": json.dumps(times.tolist()),
    }  # fmt: skip
    has = [np.zeros(S, bool) for _ in TOPICS]
    for h, topic in zip(has, TOPICS, strict=True):
        h[at[topic]] = True
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start()
        sid = w.register_schema(SENSOR_SCHEMA, "protobuf", file_descriptor_set())
        cids = [w.register_channel(t, "protobuf", sid) for t in TOPICS]
        for k, t in enumerate(times.tolist()):
            for c, cid in enumerate(cids):
                if has[c][k]:
                    v = [1000.0 * c + k]
                    msg = Block(step=k, time=t, run_offset=0, runs=1, dim=1, values=v)
                    ns = round(t * 1e9)
                    w.add_message(cid, log_time=ns, publish_time=ns, data=msg.SerializeToString())
        w.add_metadata(LAYOUT_META, record)
        w.finish()
    f = McapFile(path)
    _check_reads_back(f, times, at)
    assert f.metadata[LAYOUT_META]["instants"] == str(S)


def _writer_peak(tmp_path, steps: int) -> int:
    times, at = _log(6, steps)
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        _write(tmp_path / f"w{steps}.mcap", times, at)
        return tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()


@pytest.mark.memory
def test_writing_a_long_sparse_irregular_log_holds_no_lists(tmp_path):
    """What grows with the instants in the writer is only its check that no step is written
    twice (`StepSet`: 12 bytes for each run of consecutive steps of a topic; here ~0.2 + 0.67
    runs an instant for the sparse topics): no times (8 bytes an instant) nor the record's text
    (~30 bytes an instant) as the single record needed. The log's own arrays are made before
    measuring."""
    small, large = 2 * LISTED, 6 * LISTED
    _writer_peak(tmp_path, 20_000)  # modules and caches loaded
    peaks = [_writer_peak(tmp_path, n) for n in (small, large)]
    per = (peaks[1] - peaks[0]) / (large - small)
    assert per < 12 * (0.21 + 0.67) + 2, f"{per:.1f} bytes per added instant"
