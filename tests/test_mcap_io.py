"""Tests of the MCAP I/O layer (fusionlog.io.mcap_io): format, round trips, errors, interop."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import textwrap
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.writer import IndexType, Writer

from fusionlog.errors import FusionlogError
from fusionlog.io.mcap_io import (
    ESTIMATE_SCHEMA,
    SENSOR_SCHEMA,
    McapFile,
    McapWriter,
    decode_message,
    encode_estimate_message,
    encode_values_message,
    file_descriptor_set,
    protobuf_classes,
    recover,
)

RERUN = Path(sys.executable).parent / "rerun"
HYPO = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])


# ------------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------------


def make_data(seed: int, runs: int, steps: int, d: int = 2, n: int = 2, p_nan: float = 0.2):
    """Truth (runs, S, n), one sensor (runs, S, d) with NaN gaps, estimate means (runs, S, n)."""
    rng = np.random.default_rng(seed)
    truth = rng.normal(size=(runs, steps, n))
    sens = rng.normal(size=(runs, steps, d))
    sens[rng.random(size=sens.shape) < p_nan] = np.nan
    mean = rng.normal(size=(runs, steps, n))
    return truth, sens, mean


def write_file(path, truth, sens, mean, covs, write_block, times=None, **kw):
    """Write in the documented order; covs[b] is (S,n,n) shared or (r,S,n,n) per run (a step
    where every run has the same matrix is written shared)."""
    runs, steps = truth.shape[:2]
    times = np.arange(steps) * 0.5 if times is None else times
    with McapWriter(path, **kw) as w:
        w.add_metadata("fusionlog.scenario", {"name": "t", "toml": "[scenario]\n"})
        w.add_metadata("fusionlog.provenance", {"seed": "1"})
        for b, o in enumerate(range(0, runs, write_block)):
            r = min(write_block, runs - o)
            for k in range(steps):
                w.write_values("/truth", k, times[k], o, truth[o : o + r, k])
                w.write_values("/sensors/a", k, times[k], o, sens[o : o + r, k])
                c = covs[b][k] if covs[b].ndim == 3 else covs[b][:, k]
                if c.ndim == 3 and (c == c[:1]).all():  # the same for every run: write it once
                    c = c[0]
                w.write_estimate("/estimates/CKF", k, times[k], o, mean[o : o + r, k], c)


def concat_blocks(f: McapFile, topics, block_runs):
    got = {t: [] for t in topics}
    offsets = []
    for off, r, data in f.iter_run_blocks(topics, block_runs):
        offsets.append((off, r))
        for t in topics:
            got[t].append(data[t])
    return offsets, got


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
    with McapWriter(many, compression="none", chunk_size=64 * 1024) as w:
        for o in range(0, 400 * 100, 100):
            for k in range(steps):
                w.write_values("/truth", k, k * 0.1, o, rng.normal(size=(100, d)))
    wide = tmp_path / "wide.mcap"
    x = rng.normal(size=(16000, steps, d))  # one message = 512 kB = one chunk
    with McapWriter(wide, compression="none", chunk_size=1024) as w:
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


# ------------------------------------------------------------------------------------------
# wire compatibility
# ------------------------------------------------------------------------------------------

finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
maybe_nan = st.one_of(finite, st.just(float("nan")), st.just(float("inf")))


@HYPO
@given(
    step=st.integers(0, 2**32 - 1),
    time=st.one_of(st.just(0.0), st.just(-0.0), st.floats(0, 1e9)),
    run_offset=st.integers(0, 2**32 - 1),
    runs=st.integers(1, 4),
    dim=st.integers(1, 3),
    per_run=st.booleans(),
    data=st.data(),
)
def test_encoding_is_byte_identical_to_protobuf(step, time, run_offset, runs, dim, per_run, data):
    Block, EstimateBlock = protobuf_classes()
    vals = np.array(data.draw(st.lists(maybe_nan, min_size=runs * dim, max_size=runs * dim)))
    vals = vals.reshape(runs, dim)
    ours, _, _ = encode_values_message(step, time, run_offset, vals)
    msg = Block(step=step, time=time, run_offset=run_offset, runs=runs, dim=dim)
    msg.values.extend(vals.ravel().tolist())
    assert ours == msg.SerializeToString()
    back = decode_message(msg.SerializeToString(), SENSOR_SCHEMA)
    assert back["step"] == step and back["run_offset"] == run_offset
    assert np.array_equal(back["values"], vals, equal_nan=True)

    cov = np.arange(dim * dim * (runs if per_run else 1), dtype=float)
    cov = cov.reshape((runs, dim, dim) if per_run else (dim, dim))
    ours, _, _ = encode_estimate_message(step, time, run_offset, vals, cov)
    msg = EstimateBlock(step=step, time=time, run_offset=run_offset, runs=runs, dim=dim)
    msg.mean.extend(vals.ravel().tolist())
    msg.covariance.extend(cov.ravel().tolist())
    assert ours == msg.SerializeToString()


def test_decoder_handles_any_field_order_unknown_fields_and_unpacked():
    """Hand-built wire bytes: reversed order, an unknown field, a split and an unpacked field."""

    def tag(num, wt):
        return bytes([num << 3 | wt])

    v1 = np.array([1.0, 2.0]).tobytes()
    v2 = np.array([3.0]).tobytes()
    data = (
        tag(6, 2)
        + bytes([len(v1)])
        + v1  # values, first part
        + tag(9, 2)
        + b"\x03abc"  # unknown length-delimited field
        + tag(5, 0)
        + b"\x01"  # dim
        + tag(4, 0)
        + b"\x03"  # runs
        + tag(6, 1)
        + v2  # values, one unpacked double
        + tag(12, 0)
        + b"\x96\x01"  # unknown varint
        + tag(2, 1)
        + np.float64(2.5).tobytes()  # time
        + tag(1, 0)
        + b"\xac\x02"  # step 300
    )
    m = decode_message(data)
    assert m["step"] == 300 and m["time"] == 2.5 and m["run_offset"] == 0
    assert m["runs"] == 3 and m["dim"] == 1
    assert m["values"].ravel().tolist() == [1.0, 2.0, 3.0]
    Block, _ = protobuf_classes()
    assert list(Block.FromString(data).values) == [1.0, 2.0, 3.0]


def test_writer_output_is_canonical_protobuf(tmp_path, sample):
    """Every message McapWriter wrote re-serializes to the same bytes with the official class."""
    from mcap.reader import make_reader

    Block, EstimateBlock = protobuf_classes()
    with open(sample, "rb") as fh:
        reader = make_reader(fh)
        count = 0
        for schema, _, message in reader.iter_messages(log_time_order=False):
            cls = Block if schema.name == SENSOR_SCHEMA else EstimateBlock
            assert cls.FromString(message.data).SerializeToString() == message.data
            count += 1
    assert count == sum(McapFile(sample).topics.values())


def test_empty_file_and_closed_writer(tmp_path):
    path = tmp_path / "empty.mcap"
    with McapWriter(path) as w:
        w.add_metadata("fusionlog.provenance", {"command": "test"})
    f = McapFile(path)
    assert f.topics == {} and f.steps() == 0 and f.runs() == 0 and f.times().shape == (0,)
    assert f.metadata == {"fusionlog.provenance": {"command": "test"}}
    with pytest.raises(RuntimeError):
        w.write_values("/truth", 0, 0.0, 0, np.ones((1, 1)))


THIRD_PARTY_READER = textwrap.dedent(
    """
    import json, sys
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    out = []
    with open(sys.argv[1], "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        meta = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        for schema, channel, message, msg in reader.iter_decoded_messages(log_time_order=False):
            row = {"topic": channel.topic, "schema": schema.name, "log_time": message.log_time,
                   "publish_time": message.publish_time}
            for field in ("step", "time", "run_offset", "runs", "dim"):
                row[field] = getattr(msg, field)
            for field in ("values", "mean", "covariance"):
                if hasattr(msg, field):
                    row[field] = list(getattr(msg, field))
            out.append(row)
    assert not any(m.startswith("fusionlog") for m in sys.modules), "fusionlog was imported"
    json.dump({"metadata": meta, "messages": out}, sys.stdout)
    """
)


def test_third_party_decoder_reads_identical_values(tmp_path):
    """Decode with only mcap + mcap_protobuf, in a process where fusionlog is not importable."""
    truth, sens, mean = make_data(7, 5, 4, d=2, n=2, p_nan=0.3)
    rng = np.random.default_rng(8)
    covs = [rng.normal(size=(4, 2, 2)), rng.normal(size=(2, 4, 2, 2))]
    times = np.array([0.0, 0.1, 0.25, 1e-9 * 3])
    path = tmp_path / "tp.mcap"
    write_file(path, truth, sens, mean, covs, 3, times=times)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    script = tmp_path / "reader.py"
    script.write_text(THIRD_PARTY_READER)
    proc = subprocess.run(
        [sys.executable, "-I", str(script), str(path)],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout)
    assert result["metadata"]["fusionlog.provenance"] == {"seed": "1"}
    msgs = result["messages"]
    assert len(msgs) == 3 * 4 * 2
    for m in msgs:
        o, r, k = m["run_offset"], m["runs"], m["step"]
        assert m["time"] == times[k]
        assert m["log_time"] == m["publish_time"] == round(times[k] * 1e9)
        if m["topic"] == "/truth":
            assert m["schema"] == SENSOR_SCHEMA and m["dim"] == 2
            assert np.array_equal(np.reshape(m["values"], (r, 2)), truth[o : o + r, k])
        elif m["topic"] == "/sensors/a":
            got = np.reshape(m["values"], (r, 2))
            assert np.array_equal(got, sens[o : o + r, k], equal_nan=True)
        else:
            assert m["schema"] == ESTIMATE_SCHEMA
            assert np.array_equal(np.reshape(m["mean"], (r, 2)), mean[o : o + r, k])
            c = covs[0][k] if o == 0 else covs[1][:, k]
            assert np.array_equal(np.reshape(m["covariance"], c.shape), c)


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


def test_writer_rejects_misuse(tmp_path):
    with McapWriter(tmp_path / "w.mcap") as w:
        w.write_values("/truth", 0, 0.0, 0, np.zeros((2, 1)))
        with pytest.raises(ValueError, match="twice"):
            w.write_values("/truth", 0, 0.0, 0, np.zeros((2, 1)))
        with pytest.raises(ValueError, match="runs"):
            w.write_values("/truth", 1, 0.1, 0, np.zeros((3, 1)))
        with pytest.raises(ValueError, match="expected 2"):
            w.write_values("/truth", 0, 0.0, 5, np.zeros((2, 1)))
        with pytest.raises(ValueError, match="dim"):
            w.write_values("/truth", 1, 0.1, 0, np.zeros((2, 3)))
        with pytest.raises(ValueError, match="written as values"):
            w.write_estimate("/truth", 1, 0.1, 0, np.zeros((2, 1)), np.eye(1))
        with pytest.raises(ValueError, match="time"):
            w.write_values("/truth", 1, -1.0, 0, np.zeros((2, 1)))
        with pytest.raises(ValueError, match="cov"):
            w.write_estimate("/e", 0, 0.0, 0, np.zeros((2, 2)), np.eye(3))
        with pytest.raises(TypeError):
            w.add_metadata("m", {"a": 1})  # type: ignore[dict-item]
    assert McapFile(tmp_path / "w.mcap").topics == {"/truth": 1}


# ------------------------------------------------------------------------------------------
# damaged and wrong inputs
# ------------------------------------------------------------------------------------------


@pytest.fixture()
def sample(tmp_path):
    truth, sens, mean = make_data(5, 40, 10)
    path = tmp_path / "s.mcap"
    write_file(path, truth, sens, mean, [np.eye(2)[None].repeat(10, 0)] * 8, 5, chunk_size=4096)
    return path


@pytest.mark.parametrize("cut", ["half", "footer"])
def test_truncated_file_error_and_recover(tmp_path, sample, cut):
    raw = sample.read_bytes()
    bad = tmp_path / f"cut_{cut}.mcap"
    bad.write_bytes(raw[: len(raw) // 2] if cut == "half" else raw[:-20])
    with pytest.raises(FusionlogError) as e:
        McapFile(bad)
    msg = str(e.value)
    assert "truncated" in msg and str(bad) in msg and "\n" not in msg
    assert f"fusionlog inspect --recover {bad}" in msg
    rec = recover(bad)
    full = McapFile(sample).topics
    assert rec["error"] is not None
    assert set(rec["topics"]) == set(full)
    assert rec["metadata"]["fusionlog.provenance"] == {"seed": "1"}
    assert rec["steps"] == 10
    if cut == "half":
        assert all(0 < rec["topics"][t] < full[t] for t in full)
        assert 0 < rec["complete_runs"] < 40 and rec["complete_runs"] % 5 == 0
    else:
        assert rec["topics"] == full and rec["complete_runs"] == 40
        assert rec["last_complete_step"] == 9
    assert 0 <= rec["last_complete_step"] <= 9


def test_recover_on_intact_file(sample):
    rec = recover(sample)
    assert rec["error"] is None and rec["topics"] == McapFile(sample).topics
    assert rec["complete_runs"] == 40 and rec["last_complete_step"] == 9
    assert rec["library"].startswith("foxglove-sdk")  # McapWriter writes through the SDK


@pytest.mark.parametrize("compression", ["none", "zstd"])
def test_corrupt_chunk_is_reported(tmp_path, compression):
    truth, sens, mean = make_data(5, 40, 10)
    path = tmp_path / "s.mcap"
    covs = [np.eye(2)[None].repeat(10, 0)] * 8
    write_file(path, truth, sens, mean, covs, 5, compression=compression, chunk_size=4096)
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        first = make_reader(f).get_summary().chunk_indexes[0]
    raw = bytearray(path.read_bytes())
    i = first.chunk_start_offset + first.chunk_length // 2  # inside the chunk's record data
    raw[i : i + 40] = bytes(b ^ 0x5A for b in raw[i : i + 40])
    bad = tmp_path / "corrupt.mcap"
    bad.write_bytes(bytes(raw))
    with pytest.raises(FusionlogError, match="corrupt") as e:
        McapFile(bad).read_all(["/truth"])
    assert str(bad) in str(e.value) and "\n" not in str(e.value)


def test_not_mcap_missing_and_empty(tmp_path):
    txt = tmp_path / "notes.mcap"
    txt.write_text("hello, this is not an MCAP file at all\n")
    with pytest.raises(FusionlogError, match="not an MCAP file") as e:
        McapFile(txt)
    assert str(txt) in str(e.value)
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    with pytest.raises(FusionlogError, match="not an MCAP file"):
        McapFile(empty)
    with pytest.raises(FusionlogError, match="no such file") as e:
        McapFile(tmp_path / "missing.mcap")
    assert "missing.mcap" in str(e.value)
    with pytest.raises(FusionlogError, match="directory"):
        McapFile(tmp_path)
    with pytest.raises(FusionlogError, match="no such file"):
        recover(tmp_path / "missing.mcap")


# ------------------------------------------------------------------------------------------
# atomic output
# ------------------------------------------------------------------------------------------


def test_existing_output_is_refused_before_anything_happens(tmp_path, sample):
    before = sample.read_bytes()
    mtime = sample.stat().st_mtime_ns
    listing = sorted(os.listdir(sample.parent))
    with pytest.raises(FusionlogError, match=r"exists; use --force to overwrite") as e:
        McapWriter(sample)
    assert str(e.value) == f"{sample}: exists; use --force to overwrite"
    assert sample.read_bytes() == before and sample.stat().st_mtime_ns == mtime
    assert sorted(os.listdir(sample.parent)) == listing
    with McapWriter(sample, force=True) as w:
        w.write_values("/truth", 0, 0.0, 0, np.ones((1, 1)))
    assert McapFile(sample).topics == {"/truth": 1}
    assert sorted(os.listdir(sample.parent)) == listing


@pytest.mark.parametrize("exc", [RuntimeError, KeyboardInterrupt])
def test_exception_inside_with_leaves_nothing(tmp_path, exc):
    out = tmp_path / "new" / "deeper" / "out.mcap"
    with pytest.raises(exc):
        with McapWriter(out) as w:
            w.write_values("/truth", 0, 0.0, 0, np.ones((1, 1)))
            assert len(list(out.parent.iterdir())) == 1  # the temp file, next to the target
            raise exc()
    assert not out.exists()
    assert list(out.parent.iterdir()) == []


def test_clean_write_creates_parent_and_leaves_no_temp(tmp_path):
    out = tmp_path / "a" / "b" / "x.mcap"
    with McapWriter(out) as w:
        w.write_values("/truth", 0, 0.0, 0, np.ones((1, 1)))
    assert [p.name for p in out.parent.iterdir()] == ["x.mcap"]
    mode = out.stat().st_mode & 0o777
    umask = os.umask(0)
    os.umask(umask)
    assert mode == 0o666 & ~umask


# ------------------------------------------------------------------------------------------
# Rerun interop
# ------------------------------------------------------------------------------------------


@pytest.mark.skipif(not RERUN.exists() and not shutil.which("rerun"), reason="no rerun CLI")
def test_rerun_check_and_convert_to_typed_columns(tmp_path, sample):
    rerun = str(RERUN) if RERUN.exists() else shutil.which("rerun")
    env = {**os.environ, "RERUN_ANALYTICS": "0"}
    check = subprocess.run([rerun, "mcap", "check", str(sample)], capture_output=True, env=env)
    assert check.returncode == 0, check.stderr
    rrd = tmp_path / "out.rrd"
    conv = subprocess.run(
        [
            rerun,
            "mcap",
            "convert",
            str(sample),
            "-o",
            str(rrd),
            "-d",
            "protobuf",
            "-d",
            "metadata",
            "--application-id",
            "t",
            "--recording-id",
            "r",
        ],
        capture_output=True,
        env=env,
    )
    assert conv.returncode == 0, conv.stderr
    import pyarrow as pa
    import pyarrow.compute as pc
    from rerun.chunk import RrdReader

    rows, values = 0, []
    types = {}
    for chunk in RrdReader(str(rrd)).store().stream().to_chunks():
        batch = chunk.to_record_batch()
        for name, col in zip(batch.schema.names, batch.columns, strict=True):
            types[(str(chunk.entity_path), name)] = col.type
        if str(chunk.entity_path) == "/sensors/a":
            col = batch.column("fusionlog.Block:message").flatten()
            rows += len(col)
            values.append(pc.struct_field(col, "values").flatten().to_numpy(zero_copy_only=False))
    t = types[("/truth", "fusionlog.Block:message")]
    item = t.value_type
    assert pa.types.is_struct(item)
    assert item.field("values").type.equals(pa.list_(pa.field("item", pa.float64(), False)))
    est = types[("/estimates/CKF", "fusionlog.EstimateBlock:message")].value_type
    assert pa.types.is_list(est.field("covariance").type)
    assert any(path == "/__mcap_metadata" for path, _ in types)
    assert rows == McapFile(sample).topics["/sensors/a"]
    _, sens, _ = make_data(5, 40, 10)
    got = np.concatenate(values)
    assert got.size == sens.size and np.isnan(got).sum() == np.isnan(sens).sum()


# ------------------------------------------------------------------------------------------
# chunk decoding in columns (McapFile._table) against the one-message decoder
# ------------------------------------------------------------------------------------------


def _varint_bytes(v: int, pad: int = 0) -> bytes:
    out = bytearray()
    while True:
        b = v & 0x7F
        v >>= 7
        if v or pad:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)
        if not v:
            pad -= 1
            if not pad:
                out.append(0)
                return bytes(out)


def _wire(fields: dict, style: str, payloads: list[tuple[int, bytes]]) -> bytes:
    """One message's bytes: fields {number: int | float}, payloads [(number, packed bytes)].

    style: "canonical" (number order, zeros omitted), "reversed" (reverse order, zeros written),
    "padded" (canonical order, every varint one byte longer than needed), "split" (payloads in
    two packed pieces), "unpacked" (one tag per double).
    """
    parts = []
    for num, v in sorted(fields.items(), reverse=style == "reversed"):
        if not v and style != "reversed":
            continue
        if isinstance(v, float):
            parts.append(bytes([num << 3 | 1]) + np.float64(v).tobytes())
        else:
            parts.append(bytes([num << 3]) + _varint_bytes(v, 1 if style == "padded" else 0))
    for num, p in payloads:
        if not p:
            continue
        if style == "unpacked":
            parts.extend(bytes([num << 3 | 1]) + p[i : i + 8] for i in range(0, len(p), 8))
        elif style == "split" and len(p) > 8:
            for q in (p[:8], p[8:]):
                parts.append(bytes([num << 3 | 2]) + _varint_bytes(len(q)) + q)
        else:
            parts.append(bytes([num << 3 | 2]) + _varint_bytes(len(p)) + p)
    return b"".join(parts)


@pytest.fixture(scope="module")
def two_channel_file(tmp_path_factory):
    """A file with a Block channel (1) and an EstimateBlock channel (2), for their layouts."""
    path = tmp_path_factory.mktemp("tbl") / "t.mcap"
    with McapWriter(path) as w:
        w.write_values("/truth", 0, 0.0, 0, np.zeros((1, 1)))
        w.write_estimate("/estimates/CKF", 0, 0.0, 0, np.zeros((1, 1)), np.eye(1))
    return McapFile(path)


message_spec = st.tuples(
    st.sampled_from(["/truth", "/estimates/CKF"]),
    st.sampled_from([0, 1, 127, 128, 16383, 16384, 2**21, 2**32 - 1]),  # step: varint lengths
    st.sampled_from([0.0, 1.0, 0.5]),
    st.sampled_from([0, 1, 300]),  # run_offset
    st.integers(1, 2),  # runs
    st.integers(1, 2),  # dim
    st.booleans(),  # per-run covariance
    st.sampled_from(["canonical"] * 4 + ["reversed", "padded", "split", "unpacked"]),
)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(specs=st.lists(message_spec, min_size=1, max_size=40), seed=st.integers(0, 99))
def test_table_decoding_matches_the_message_decoder(two_channel_file, specs, seed):
    """Grouped decoding (same channel and length against one template) gives, message by
    message, what the one-message decoder gives, whatever the encodings mixed in a chunk —
    including messages of one length whose fields lie elsewhere (step 0 with run_offset 1 and
    step 1 with run_offset 0, say)."""
    from mcap.records import Message

    from fusionlog.io.mcap_io import _decode, _layout_for_name

    f = two_channel_file
    cid_of = {f._topics[t].channel_ids[0]: t for t in ("/truth", "/estimates/CKF")}
    rng = np.random.default_rng(seed)
    msgs = []
    for topic, step, t, off, runs, dim, per_run, style in specs:
        fields = {1: step, 2: t, 3: off, 4: runs, 5: dim}
        payloads = [(6, rng.normal(size=runs * dim).tobytes())]
        if topic != "/truth":
            payloads.append((7, rng.normal(size=dim * dim * (runs if per_run else 1)).tobytes()))
        cid = next(c for c, name in cid_of.items() if name == topic)
        data = _wire(fields, style, payloads)
        msgs.append(Message(channel_id=cid, log_time=0, data=data, publish_time=0, sequence=0))
    tab = f._table(msgs, set(cid_of))
    assert tab is not None and len(tab) == len(msgs)
    for i, m in enumerate(msgs):
        schema = SENSOR_SCHEMA if cid_of[m.channel_id] == "/truth" else ESTIMATE_SCHEMA
        step, t, off, runs, dim, p1, p2 = _decode(m.data, _layout_for_name(schema))
        assert (tab.step[i], tab.time[i], tab.off[i], tab.runs[i], tab.dim[i]) == (
            step,
            t,
            off,
            runs,
            dim,
        )
        assert tab.raw[tab.p1[i] : tab.p1[i] + tab.n1[i]] == bytes(p1)
        assert tab.raw[tab.p2[i] : tab.p2[i] + tab.n2[i]] == bytes(p2)


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
