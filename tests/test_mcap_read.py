"""MCAP layer, reading: round trips through McapWriter and McapFile at any block sizes,
memory bounds, files of other writers (official protobuf classes, proto2, no index), the
writing-order checks, and the writer's fusionlog.layout record."""

from __future__ import annotations

import json
import tempfile
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.writer import IndexType, Writer
from mcap_helpers import concat_blocks, make_data, mcap_writer, write_file

from fusionlog.errors import FusionlogError
from fusionlog.io.mcap import (
    ESTIMATE_SCHEMA,
    LAYOUT_META,
    SENSOR_SCHEMA,
    McapFile,
    file_descriptor_set,
    protobuf_classes,
)

HYPO = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])

# ------------------------------------------------------------------------------------------
# round trips
# ------------------------------------------------------------------------------------------


@st.composite
def layouts(draw):
    runs = draw(st.integers(1, 9))
    return dict(
        runs=runs,
        steps=draw(st.integers(1, 4)),
        d=draw(st.integers(1, 3)),
        n=draw(st.integers(1, 3)),
        write_block=draw(st.integers(1, runs)),
        read_block=draw(st.integers(1, runs + 2)),
        cov_mode=draw(st.sampled_from(["same", "per_block", "per_run", "mixed", "step_mixed"])),
        # small chunks: blocks of runs (and the windows read again) start inside chunks
        chunk_size=draw(st.sampled_from([300, 4096, 1 << 20])),
        seed=draw(st.integers(0, 2**16)),
    )


@HYPO
@given(layouts())
def test_round_trip_any_block_sizes(lay):
    runs, steps, n, wb, rb = (
        lay["runs"],
        lay["steps"],
        lay["n"],
        lay["write_block"],
        lay["read_block"],
    )
    truth, sens, mean = make_data(lay["seed"], runs, steps, lay["d"], n)
    rng = np.random.default_rng(lay["seed"] + 1)
    same = rng.normal(size=(steps, n, n))
    covs, full, shared_of = [], np.empty((runs, steps, n, n)), []
    for b, o in enumerate(range(0, runs, wb)):
        r = min(wb, runs - o)
        mode = lay["cov_mode"] if lay["cov_mode"] != "mixed" else ("per_block", "per_run")[b % 2]
        if mode == "same":
            c = same
        elif mode == "per_block":
            c = rng.normal(size=(steps, n, n))
        else:
            c = rng.normal(size=(r, steps, n, n))
            if mode == "step_mixed":  # odd steps shared by the block's runs, even ones per run
                c[:, 1::2] = c[:1, 1::2]
        covs.append(c)
        full[o : o + r] = c
        # A one-run message's covariance has n*n values: the reader sees it as shared.
        shared_of.append((o, r, c if c.ndim == 3 else c[0] if r == 1 else None))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "x.mcap"
        write_file(path, truth, sens, mean, covs, wb, chunk_size=lay["chunk_size"])
        f = McapFile(path)
        assert f.runs() == runs and f.steps() == steps
        assert np.array_equal(f.times(), np.arange(steps) * 0.5)
        topics = ["/truth", "/sensors/a", "/estimates/CKF"]
        offsets, got = concat_blocks(f, topics, rb)
        expect_offsets = [(o, min(rb, runs - o)) for o in range(0, runs, rb)]
        assert offsets == expect_offsets
        assert np.array_equal(np.concatenate(got["/truth"]), truth)
        assert np.array_equal(np.concatenate(got["/sensors/a"]), sens, equal_nan=True)
        assert np.array_equal(np.concatenate([m for m, _ in got["/estimates/CKF"]]), mean)
        for (lo, r), (_, cov) in zip(offsets, got["/estimates/CKF"], strict=True):
            parts = [s for o, rr, s in shared_of if o < lo + r and o + rr > lo]
            if all(p is not None for p in parts) and all(
                np.array_equal(p, parts[0]) for p in parts
            ):
                assert cov.shape == (steps, n, n)
                assert np.array_equal(cov, parts[0])
            else:
                assert cov.shape == (r, steps, n, n)
                assert np.array_equal(cov, full[lo : lo + r])


@pytest.mark.parametrize("write_block", [700, 260])
def test_round_trip_blocks_of_many_runs(tmp_path, write_block):
    """Messages of many runs (a simulation's 10^3-10^4 runs per message, copied into their
    step one at a time; some of 260 runs below that size) read back in output blocks that
    start inside them, as whole files and in windows read again."""
    runs, steps = 900, 5
    truth, sens, mean = make_data(7, runs, steps, d=2, n=2)
    covs = [np.eye(2)[None].repeat(steps, 0)] * (-(-runs // write_block))
    path = tmp_path / "big.mcap"
    write_file(path, truth, sens, mean, covs, write_block, chunk_size=1 << 14)
    f = McapFile(path)
    topics = ["/truth", "/sensors/a", "/estimates/CKF"]
    for rb in (runs, 512, 333, 1):
        offsets, got = concat_blocks(f, topics, rb)
        assert offsets == [(o, min(rb, runs - o)) for o in range(0, runs, rb)]
        assert np.array_equal(np.concatenate(got["/truth"]), truth)
        assert np.array_equal(np.concatenate(got["/sensors/a"]), sens, equal_nan=True)
        assert np.array_equal(np.concatenate([m for m, _ in got["/estimates/CKF"]]), mean)


def test_read_all_metadata_topics_and_schemas(tmp_path):
    truth, sens, mean = make_data(0, 5, 3)
    path = tmp_path / "a.mcap"
    write_file(path, truth, sens, mean, [np.eye(2)[None].repeat(3, 0)] * 3, 2)
    f = McapFile(path)
    assert f.topics == {"/truth": 9, "/sensors/a": 9, "/estimates/CKF": 9}
    assert f.metadata["fusionlog.scenario"] == {"name": "t", "toml": "[scenario]\n"}
    assert f.metadata["fusionlog.provenance"] == {"seed": "1"}
    assert f.schema_of("/truth") == SENSOR_SCHEMA
    assert f.schema_of("/estimates/CKF") == ESTIMATE_SCHEMA
    assert f.kind_of("/truth") == "values" and f.dim_of("/sensors/a") == 2
    data = f.read_all(["/truth", "/sensors/a", "/estimates/CKF"])
    assert np.array_equal(data["/truth"], truth)
    assert np.array_equal(data["/sensors/a"], sens, equal_nan=True)
    m, c = data["/estimates/CKF"]
    assert np.array_equal(m, mean) and np.array_equal(c, np.eye(2)[None].repeat(3, 0))
    assert data["/truth"].flags.writeable and c.flags.writeable
    with pytest.raises(FusionlogError, match="no topic /nope"):
        f.read_all(["/nope"])


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_compressions_and_small_chunks(tmp_path, compression):
    truth, sens, mean = make_data(3, 20, 6)
    path = tmp_path / "c.mcap"
    covs = [np.eye(2)[None].repeat(6, 0)] * 4
    write_file(path, truth, sens, mean, covs, 5, compression=compression, chunk_size=2000)
    data = McapFile(path).read_all(["/truth", "/sensors/a"])
    assert np.array_equal(data["/truth"], truth)
    assert np.array_equal(data["/sensors/a"], sens, equal_nan=True)


def test_memory_bounded_many_blocks_and_one_huge_block(tmp_path):
    """Reading holds about two output blocks and two chunks, not the file.

    Both the case of many file blocks and of one file block much wider than the output blocks
    (read again per window) are checked with tracemalloc, which sees numpy and bytes buffers.
    """
    steps, d = 20, 4
    rng = np.random.default_rng(0)
    many = tmp_path / "many.mcap"
    with mcap_writer(many, compression="none", chunk_size=64 * 1024) as w:
        for o in range(0, 400 * 100, 100):
            for k in range(steps):
                w.write_values("/truth", k, k * 0.1, o, rng.normal(size=(100, d)))
    wide = tmp_path / "wide.mcap"
    x = rng.normal(size=(16000, steps, d))  # one message = 512 kB = one chunk
    with mcap_writer(wide, compression="none", chunk_size=1024) as w:
        for k in range(steps):
            w.write_values("/truth", k, k * 0.1, 0, x[:, k])
    for path, total_bytes, block in ((many, 40000 * steps * d * 8, 100), (wide, x.nbytes, 250)):
        f = McapFile(path)
        f.runs()
        tracemalloc.start()
        seen = 0
        for off, r, data in f.iter_run_blocks(["/truth"], block):
            assert off == seen and data["/truth"].shape == (r, steps, d)
            if path == wide:
                assert np.array_equal(data["/truth"], x[off : off + r])
            seen += r
            del data
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert seen == f.runs()
        # Expected peak: a few chunks (64 kB / 512 kB here) plus a few output blocks.
        assert peak < total_bytes / 3, (path.name, peak, total_bytes)


def test_empty_file_and_closed_writer(tmp_path):
    path = tmp_path / "empty.mcap"
    with mcap_writer(path) as w:
        w.add_metadata("fusionlog.provenance", {"command": "test"})
    f = McapFile(path)
    assert f.topics == {} and f.steps() == 0 and f.runs() == 0 and f.times().shape == (0,)
    assert f.metadata["fusionlog.provenance"] == {"command": "test"}
    assert f.metadata[LAYOUT_META]["instants"] == "0" and f.metadata[LAYOUT_META]["runs"] == "0"
    with pytest.raises(RuntimeError):
        w.write_values("/truth", 0, 0.0, 0, np.ones((1, 1)))


def test_reads_file_written_with_official_protobuf_classes(tmp_path):
    Block, EstimateBlock = protobuf_classes()
    truth, _, mean = make_data(1, 4, 3)
    path = tmp_path / "official.mcap"
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start(profile="", library="someone-else")
        sb = w.register_schema(SENSOR_SCHEMA, "protobuf", file_descriptor_set())
        se = w.register_schema(ESTIMATE_SCHEMA, "protobuf", file_descriptor_set())
        ct = w.register_channel("/truth", "protobuf", sb)
        ce = w.register_channel("/estimates/X", "protobuf", se)
        for o in (0, 2):
            for k in range(3):
                t = round(k * 0.1 * 1e9)
                m = Block(step=k, time=k * 0.1, run_offset=o, runs=2, dim=2)
                m.values.extend(truth[o : o + 2, k].ravel())
                w.add_message(ct, log_time=t, publish_time=t, data=m.SerializeToString())
                e = EstimateBlock(step=k, time=k * 0.1, run_offset=o, runs=2, dim=2)
                e.mean.extend(mean[o : o + 2, k].ravel())
                e.covariance.extend(np.eye(2).ravel() * (k + 1))
                w.add_message(ce, log_time=t, publish_time=t, data=e.SerializeToString())
        w.finish()
    f = McapFile(path)
    assert f.library == "someone-else" and f.runs() == 4 and f.steps() == 3
    data = f.read_all(["/truth", "/estimates/X"])
    assert np.array_equal(data["/truth"], truth)
    m, c = data["/estimates/X"]
    assert np.array_equal(m, mean)
    assert np.array_equal(c, np.eye(2)[None] * np.arange(1, 4)[:, None, None])


def test_hand_written_one_run_log_with_foreign_proto2_schema(tmp_path):
    """A 'real' one-run sensor log: own package, other field numbers, proto2 unpacked doubles."""
    F = descriptor_pb2.FieldDescriptorProto
    fdp = descriptor_pb2.FileDescriptorProto(name="lab/reading.proto", package="lab")
    m = fdp.message_type.add(name="Reading")
    for name, num, typ in [
        ("values", 1, F.TYPE_DOUBLE),
        ("time", 3, F.TYPE_DOUBLE),
        ("step", 10, F.TYPE_UINT64),
        ("run_offset", 11, F.TYPE_UINT32),
        ("runs", 12, F.TYPE_UINT32),
        ("dim", 13, F.TYPE_UINT32),
        ("comment", 20, F.TYPE_STRING),
    ]:
        label = F.LABEL_REPEATED if name == "values" else F.LABEL_OPTIONAL
        m.field.add(name=name, number=num, type=typ, label=label)
    pool = descriptor_pool.DescriptorPool()
    pool.Add(fdp)
    Reading = message_factory.GetMessageClass(pool.FindMessageTypeByName("lab.Reading"))
    fds = descriptor_pb2.FileDescriptorSet(file=[fdp]).SerializeToString()
    z = np.array([[1.0, np.nan], [2.0, 0.5], [np.nan, np.nan], [4.0, -1.0]])
    times = [0.0, 0.2, 0.4, 0.6]
    path = tmp_path / "real.mcap"
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start()
        sid = w.register_schema("lab.Reading", "protobuf", fds)
        cid = w.register_channel("/sensors/gps", "protobuf", sid)
        other = w.register_channel("/log", "json", w.register_schema("Log", "jsonschema", b"{}"))
        for k, t in enumerate(times):
            msg = Reading(step=k, time=t, runs=1, dim=2, comment="hi")  # run_offset left unset
            msg.values.extend(z[k])
            data = msg.SerializeToString()
            assert data[0] == (1 << 3 | 1)  # proto2: not packed, one tag per double
            w.add_message(cid, log_time=int(t * 1e9), publish_time=int(t * 1e9), data=data)
            w.add_message(other, log_time=int(t * 1e9), publish_time=int(t * 1e9), data=b"{}")
        w.finish()
    f = McapFile(path)
    assert f.topics == {"/sensors/gps": 4, "/log": 4}
    assert f.schema_of("/sensors/gps") == "lab.Reading" and f.kind_of("/log") is None
    assert f.runs() == 1 and f.steps() == 4 and f.times().tolist() == times
    got = f.read_all(["/sensors/gps"])["/sensors/gps"]
    assert got.shape == (1, 4, 2)
    assert np.array_equal(got[0], z, equal_nan=True)
    with pytest.raises(FusionlogError, match="/log has schema Log"):
        f.read_all(["/log"])


@pytest.mark.parametrize("variant", ["no_chunks", "no_summary"])
def test_files_without_index_are_read_linearly(tmp_path, variant):
    Block, _ = protobuf_classes()
    path = tmp_path / f"{variant}.mcap"
    kw = (
        dict(use_chunking=False)
        if variant == "no_chunks"
        else dict(
            repeat_channels=False,
            repeat_schemas=False,
            use_statistics=False,
            use_summary_offsets=False,
            index_types=IndexType(0),
        )
    )
    with open(path, "wb") as fh:
        w = Writer(fh, **kw)
        w.start()
        cid = w.register_channel(
            "/truth",
            "protobuf",
            w.register_schema(SENSOR_SCHEMA, "protobuf", file_descriptor_set()),
        )
        w.add_metadata("fusionlog.scenario", {"a": "1"})
        for o in range(3):
            for k in range(2):
                msg = Block(
                    step=k, time=k * 1.0, run_offset=o, runs=1, dim=1, values=[o * 10.0 + k]
                )
                w.add_message(cid, log_time=k, publish_time=k, data=msg.SerializeToString())
        w.finish()
    f = McapFile(path)
    assert f.topics == {"/truth": 6} and f.metadata == {"fusionlog.scenario": {"a": "1"}}
    offsets, got = concat_blocks(f, ["/truth"], 2)
    assert offsets == [(0, 2), (2, 1)]
    assert np.concatenate(got["/truth"])[:, :, 0].tolist() == [[0, 1], [10, 11], [20, 21]]


@pytest.mark.parametrize("chunk_size", [300, 1 << 20])
def test_one_topic_of_many_read_through_the_message_indexes(tmp_path, chunk_size):
    """Reading a quarter of the messages takes them through the chunks' message indexes (the
    rest are not split out of the chunk); the arrays are those of reading every topic."""
    truth, sens, mean = make_data(3, 7, 4)
    covs = [np.random.default_rng(0).normal(size=(4, 2, 2))] * 3
    path = tmp_path / "x.mcap"
    write_file(path, truth, sens, mean, covs, 3, chunk_size=chunk_size)
    f = McapFile(path)
    for topic in ("/truth", "/sensors/a"):
        _, alone = concat_blocks(f, [topic], 2)
        _, all_ = concat_blocks(f, ["/truth", "/sensors/a", "/estimates/CKF"], 2)
        assert all(
            np.array_equal(x, y, equal_nan=True)
            for x, y in zip(alone[topic], all_[topic], strict=True)
        )
    assert np.array_equal(np.concatenate(alone["/sensors/a"]), sens, equal_nan=True)


# ------------------------------------------------------------------------------------------
# layout violations
# ------------------------------------------------------------------------------------------


def _raw_file(path, messages):
    """messages: (run_offset, runs, step); one /truth channel, dim 1."""
    Block, _ = protobuf_classes()
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start()
        sid = w.register_schema(SENSOR_SCHEMA, "protobuf", file_descriptor_set())
        cid = w.register_channel("/truth", "protobuf", sid)
        for o, r, k in messages:
            msg = Block(step=k, time=float(k), run_offset=o, runs=r, dim=1, values=[0.0] * r)
            w.add_message(cid, log_time=k, publish_time=k, data=msg.SerializeToString())
        w.finish()


@pytest.mark.parametrize(
    "messages, match",
    [
        ([(0, 1, 0), (1, 1, 0), (0, 1, 1), (1, 1, 1)], "block order"),  # interleaved blocks
        ([(0, 1, 0), (0, 1, 1), (2, 1, 0), (2, 1, 1)], "block order"),  # gap in runs
        ([(0, 1, 0), (0, 1, 1), (1, 1, 0)], "1 of 2 steps"),  # missing step
        ([(0, 1, 0), (0, 1, 1), (0, 1, 1)], "appears twice"),
        ([(0, 2, 0), (0, 1, 1)], "disagree on runs"),
    ],
)
def test_layout_violations_are_reported(tmp_path, messages, match):
    path = tmp_path / "bad.mcap"
    _raw_file(path, messages)
    with pytest.raises(FusionlogError, match=match) as e:
        for _ in McapFile(path).iter_run_blocks(["/truth"], 1):
            pass
    assert str(path) in str(e.value) and "\n" not in str(e.value)


# ------------------------------------------------------------------------------------------
# the writer's layout record
# ------------------------------------------------------------------------------------------


def test_layout_record_describes_the_file(tmp_path):
    truth, sens, mean = make_data(2, 7, 5, d=3, n=2)
    path = tmp_path / "l.mcap"
    write_file(path, truth, sens, mean, [np.eye(2)[None].repeat(5, 0)] * 3, 3)
    meta = McapFile(path).metadata[LAYOUT_META]
    assert meta == {
        "format": "1",
        "instants": "5",
        "runs": "7",
        "blocks": "3",
        "dt": "0.5",
        "topics": '{"/estimates/CKF": 2, "/sensors/a": 3, "/truth": 2}',
    }


def test_layout_record_with_irregular_times(tmp_path):
    truth, sens, mean = make_data(2, 4, 4)
    times = np.array([0.0, 0.1, 0.25, 1e-9 * 3 + 0.25])
    path = tmp_path / "irr.mcap"
    write_file(path, truth, sens, mean, [np.eye(2)[None].repeat(4, 0)] * 2, 2, times=times)
    f = McapFile(path)
    assert "dt" not in f.metadata[LAYOUT_META]
    assert f.times().tolist() == times.tolist() and f.runs() == 4 and f.steps() == 4
    assert np.array_equal(f.read_all(["/truth"])["/truth"], truth)


def test_layout_record_of_a_sparse_long_log(tmp_path):
    """A topic with messages at some instants and irregular times, over more instants than
    the record is written and parsed at once: the record's lists are `json.dumps`' text of
    the steps and times written, and the file reads back with them."""
    rng = np.random.default_rng(7)
    S = 20_000
    times = np.cumsum(rng.uniform(0.001, 0.002, S)) - 0.001
    at = {"/sensors/a": np.flatnonzero(rng.random(S) < 0.7), "/sensors/b": np.arange(1, S, 3)}
    path = tmp_path / "sparse.mcap"
    has = {topic: set(steps.tolist()) for topic, steps in at.items()}
    with mcap_writer(path) as w:
        for k, t in enumerate(times.tolist()):
            w.write_values("/truth", k, t, 0, np.zeros((1, 1)))
            for topic in at:
                if k in has[topic]:
                    w.write_values(topic, k, t, 0, np.full((1, 1), k, float))
    f = McapFile(path)
    meta = f.metadata[LAYOUT_META]
    assert meta["sparse"] == json.dumps({t: s.tolist() for t, s in at.items()}, sort_keys=True)
    assert meta["times"] == json.dumps(times.tolist())
    assert f.times().tobytes() == times.tobytes()
    for topic, steps in at.items():
        np.testing.assert_array_equal(np.flatnonzero(f.topic_steps(topic)), steps)
        got = np.concatenate([d[topic][0, :, 0] for _, _, d in f.iter_time_blocks([topic], 999)])
        np.testing.assert_array_equal(np.flatnonzero(~np.isnan(got)), steps)
        np.testing.assert_array_equal(got[steps], steps)


def test_copied_layout_record_is_replaced_by_the_writers_own(tmp_path):
    truth, sens, mean = make_data(2, 6, 3)
    big = tmp_path / "big.mcap"
    write_file(big, truth, sens, mean, [np.eye(2)[None].repeat(3, 0)] * 3, 2)
    copy = tmp_path / "copy.mcap"
    src = McapFile(big)
    with mcap_writer(copy) as w:
        for name, meta in src.metadata.items():
            w.add_metadata(name, meta)
        for k in range(2):  # a smaller file: 1 run, 2 steps
            w.write_values("/truth", k, k * 0.5, 0, truth[:1, k])
    f = McapFile(copy)
    assert f.metadata[LAYOUT_META]["runs"] == "1" and f.metadata[LAYOUT_META]["instants"] == "2"
    assert f.runs() == 1 and f.steps() == 2


def _foreign_file(path, layout: dict[str, str] | None, runs=3, steps=2):
    """A file of mcap's own writer (one /truth topic, blocks of one run), with ``layout`` as
    its fusionlog.layout record: a record the reader must check, not trust."""
    Block, _ = protobuf_classes()
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start()
        sid = w.register_schema(SENSOR_SCHEMA, "protobuf", file_descriptor_set())
        cid = w.register_channel("/truth", "protobuf", sid)
        if layout is not None:
            w.add_metadata(LAYOUT_META, layout)
        for o in range(runs):
            for k in range(steps):
                msg = Block(step=k, time=k * 0.25, run_offset=o, runs=1, dim=1, values=[o + k])
                w.add_message(cid, log_time=k, publish_time=k, data=msg.SerializeToString())
        w.finish()


GOOD = {
    "format": "1",
    "instants": "2",
    "runs": "3",
    "blocks": "3",
    "dt": "0.25",
    "topics": '{"/truth": 1}',
}


@pytest.mark.parametrize(
    "layout",
    [
        None,
        GOOD,
        {**GOOD, "runs": "4"},
        {**GOOD, "blocks": "2"},
        {**GOOD, "instants": "3", "blocks": "2"},  # 3 x 2 messages, as many as the file has
        {**GOOD, "dt": "0.5"},
        {**GOOD, "topics": '{"/truth": 2}'},
        {**GOOD, "topics": '{"/other": 1}'},
        {**GOOD, "format": "2"},
        {**GOOD, "dt": "x"},
        {k: v for k, v in GOOD.items() if k != "dt"},
        # the steps of a topic with some instants, and the times, as the record lists them
        {**GOOD, "sparse": '{"/truth": [0, 1]}'},
        {**GOOD, "sparse": '{"/truth": [1]}'},
        {**GOOD, "sparse": '{"/truth": [1, 0]}'},
        {**GOOD, "sparse": '{"/truth": [0, 0]}'},
        {**GOOD, "sparse": '{"/truth": [0, 2]}'},
        {**GOOD, "sparse": '{"/truth": [0, 1.5]}'},
        {**GOOD, "sparse": '{"/truth": [0, 1,]}'},
        {**GOOD, "sparse": '{"/truth": [0, 1]'},
        {**GOOD, "sparse": '{"/other": [0]}'},
        {**{k: v for k, v in GOOD.items() if k != "dt"}, "times": "[0.0, 0.25]"},
        {**{k: v for k, v in GOOD.items() if k != "dt"}, "times": "[0.0, 0.5]"},
        {**{k: v for k, v in GOOD.items() if k != "dt"}, "times": "[0.0, 0.25, 0.5]"},
        {**{k: v for k, v in GOOD.items() if k != "dt"}, "times": "[0.0,]"},
        {**{k: v for k, v in GOOD.items() if k != "dt"}, "times": '[0.0, "x"]'},
    ],
)
def test_layout_record_is_checked_against_the_file(tmp_path, layout):
    """Whatever the record says, the structure is the file's (a wrong record is not used)."""
    path = tmp_path / "f.mcap"
    _foreign_file(path, layout)
    f = McapFile(path)
    assert f.runs() == 3 and f.steps() == 2 and f.times().tolist() == [0.0, 0.25]
    assert f.dim_of("/truth") == 1
    got = f.read_all(["/truth"])["/truth"]
    assert got[:, :, 0].tolist() == [[0, 1], [1, 2], [2, 3]]


# ------------------------------------------------------------------------------------------
# per-message covariance of a values topic (a one-run log that carries its own R)
# ------------------------------------------------------------------------------------------


def test_per_message_covariance_round_trip(tmp_path: Path) -> None:
    """A Block's optional covariance: written for some messages, read back where it is, NaN
    where it is not; the readings are unaffected; the plain protobuf class decodes it."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    path = tmp_path / "c.mcap"
    rng = np.random.default_rng(4)
    vals = rng.normal(size=(6, 1, 2))
    covs = {1: np.array([[[2.0, 0.1], [0.1, 3.0]]]), 4: np.array([[[0.5, 0.0], [0.0, 0.7]]])}
    with mcap_writer(path) as w:
        for k in range(6):
            w.write_values("/truth", k, 0.1 * k, 0, vals[k])
            if k % 2 == 0 or k in covs:
                w.write_values("/sensors/a", k, 0.1 * k, 0, vals[k], covs.get(k))
    f = McapFile(path)
    got = f.message_covariances("/sensors/a")
    assert got.shape == (6, 2, 2)
    for k in range(6):
        if k in covs:
            np.testing.assert_array_equal(got[k], covs[k][0])
        else:
            assert np.isnan(got[k]).all()
    assert f.message_covariances("/truth") is None
    data = f.read_all(["/sensors/a"])["/sensors/a"]
    np.testing.assert_array_equal(data[0, [0, 1, 2, 4]], vals[[0, 1, 2, 4], 0])
    assert np.isnan(data[0, [3, 5]]).all()
    with open(path, "rb") as fh:
        seen = {
            msg.log_time: list(dec.covariance)
            for _, ch, msg, dec in make_reader(
                fh, decoder_factories=[DecoderFactory()]
            ).iter_decoded_messages(topics=["/sensors/a"])
        }
    assert seen[100_000_000] == [2.0, 0.1, 0.1, 3.0] and seen[0] == []


@pytest.mark.parametrize("runs_per_block", [1, 2])
def test_message_covariance_in_a_file_of_several_runs_is_refused(
    tmp_path: Path, runs_per_block: int
) -> None:
    """Per-message covariances are for one-run logs: a file of two runs (in one block or in
    two) with one is refused, in one line naming the topic, when its blocks are read."""
    path = tmp_path / "c.mcap"
    cov = np.array([[[2.0, 0.1], [0.1, 3.0]]] * runs_per_block)
    with mcap_writer(path) as w:
        for off in range(0, 2, runs_per_block):
            for k in range(2):
                v = np.full((runs_per_block, 2), float(k))
                w.write_values("/sensors/a", k, 0.1 * k, off, v, cov if k == 1 else None)
    f = McapFile(path)
    assert f.runs() == 2
    msg = r"/sensors/a: step 1 .*a message covariance in a file of 2 runs \(per-message"
    with pytest.raises(FusionlogError, match=msg + r" covariances are for one-run logs\)"):
        f.read_all(["/sensors/a"])
