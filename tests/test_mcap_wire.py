"""MCAP layer, wire format: the one encoder against the official protobuf classes, the
writer's bytes against that encoder, decoding of any encoding (one message and whole
tables), and decoding by third parties (mcap + mcap-protobuf-support, rerun)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap_helpers import make_data, sample_file, write_file

from fusionlog.io.mcap import (
    ESTIMATE_SCHEMA,
    SENSOR_SCHEMA,
    McapFile,
    decode_message,
    encode_estimate_message,
    encode_values_message,
    protobuf_classes,
)
from fusionlog.io.mcap.columns import decode_table
from fusionlog.io.mcap.wire import decode, format_for_schema

RERUN = Path(sys.executable).parent / "rerun"
HYPO = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@pytest.fixture()
def sample(tmp_path):
    return sample_file(tmp_path / "s.mcap")


# ------------------------------------------------------------------------------------------
# wire compatibility
# ------------------------------------------------------------------------------------------


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


def test_writer_bytes_are_the_public_encoders(tmp_path):
    """The writer encodes through the same functions as encode_values_message /
    encode_estimate_message: every message it wrote is their output for its inputs."""
    from mcap.reader import make_reader

    truth, sens, mean = make_data(3, 5, 3, d=3, n=2)
    rng = np.random.default_rng(1)
    covs = [rng.normal(size=(3, 2, 2)), rng.normal(size=(2, 3, 2, 2))]
    path = tmp_path / "w.mcap"
    write_file(path, truth, sens, mean, covs, 3, times=np.array([0.0, 0.5, 300.25]))
    expected = []
    for b, o in enumerate((0, 3)):
        r = 3 if o == 0 else 2
        for k, t in enumerate((0.0, 0.5, 300.25)):
            expected.append(encode_values_message(k, t, o, truth[o : o + r, k])[0])
            expected.append(encode_values_message(k, t, o, sens[o : o + r, k])[0])
            c = covs[b][k] if b == 0 else covs[b][:, k]
            expected.append(encode_estimate_message(k, t, o, mean[o : o + r, k], c)[0])
    with open(path, "rb") as fh:
        got = [m.data for _, _, m in make_reader(fh).iter_messages(log_time_order=False)]
    assert got == expected


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
    # runs (3, 3, 1) never equal a dim (sensor 4, state 2): swapped fields cannot pass
    truth, sens, mean = make_data(7, 7, 4, d=4, n=2, p_nan=0.3)
    rng = np.random.default_rng(8)
    covs = [rng.normal(size=(4, 2, 2)), rng.normal(size=(3, 4, 2, 2)), rng.normal(size=(4, 2, 2))]
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
    assert len(msgs) == 3 * 4 * 3
    dims = {"/truth": 2, "/sensors/a": 4, "/estimates/CKF": 2}
    for m in msgs:
        o, r, k = m["run_offset"], m["runs"], m["step"]
        assert (o, r) in ((0, 3), (3, 3), (6, 1)) and m["dim"] == dims[m["topic"]]
        assert m["time"] == times[k]
        assert m["log_time"] == m["publish_time"] == round(times[k] * 1e9)
        if m["topic"] == "/truth":
            assert m["schema"] == SENSOR_SCHEMA
            assert np.array_equal(np.reshape(m["values"], (r, 2)), truth[o : o + r, k])
        elif m["topic"] == "/sensors/a":
            got = np.reshape(m["values"], (r, 4))
            assert np.array_equal(got, sens[o : o + r, k], equal_nan=True)
        else:
            assert m["schema"] == ESTIMATE_SCHEMA
            assert np.array_equal(np.reshape(m["mean"], (r, 2)), mean[o : o + r, k])
            c = covs[o // 3][k] if o != 3 else covs[1][:, k]
            assert np.array_equal(np.reshape(m["covariance"], c.shape), c)


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
# chunk decoding in columns (decode_table) against the one-message decoder
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
def test_table_decoding_matches_the_message_decoder(specs, seed):
    """Grouped decoding (same channel and length against one template) gives, message by
    message, what the one-message decoder gives, whatever the encodings mixed in a chunk —
    including messages of one length whose fields lie elsewhere (step 0 with run_offset 1 and
    step 1 with run_offset 0, say)."""
    from mcap.records import Message

    cid_of = {1: "/truth", 2: "/estimates/CKF"}
    formats = {1: format_for_schema(SENSOR_SCHEMA), 2: format_for_schema(ESTIMATE_SCHEMA)}
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
    tab = decode_table(msgs, formats)
    assert tab is not None and len(tab) == len(msgs)
    for i, m in enumerate(msgs):
        step, t, off, runs, dim, p1, p2 = decode(m.data, formats[m.channel_id])
        assert (tab.step[i], tab.time[i], tab.off[i], tab.runs[i], tab.dim[i]) == (
            step,
            t,
            off,
            runs,
            dim,
        )
        assert tab.raw[tab.p1[i] : tab.p1[i] + tab.n1[i]] == bytes(p1)
        assert tab.raw[tab.p2[i] : tab.p2[i] + tab.n2[i]] == bytes(p2)


def test_schema_bytes_are_protobufs_own_serialisation() -> None:
    """The FileDescriptorSet encoded by hand (no google.protobuf at start-up) is byte for byte
    what descriptor_pb2 serialises for the same two messages."""
    from google.protobuf import descriptor_pb2

    from fusionlog.io.mcap.schema import PROTO_FILE, file_descriptor_set, message_fields

    fdp = descriptor_pb2.FileDescriptorProto(name=PROTO_FILE, package="fusionlog", syntax="proto3")
    for name, kind in (("Block", "values"), ("EstimateBlock", "estimate")):
        m = fdp.message_type.add(name=name)
        for fname, number, ftype, label in message_fields(kind):
            m.field.add(name=fname, number=number, type=ftype, label=label)
    assert file_descriptor_set() == descriptor_pb2.FileDescriptorSet(file=[fdp]).SerializeToString()
    F = descriptor_pb2.FieldDescriptorProto
    assert [f[1:] for f in message_fields("values")][:2] == [
        (1, F.TYPE_UINT32, F.LABEL_OPTIONAL),
        (2, F.TYPE_DOUBLE, F.LABEL_OPTIONAL),
    ]
    assert message_fields("values")[-1][1:] == (7, F.TYPE_DOUBLE, F.LABEL_REPEATED)


def test_the_reference_switch_decodes_field_by_field(tmp_path, monkeypatch) -> None:
    """FUSIONLOG_REFERENCE_PATHS=1: no regex for canonical messages (nor the column-wise
    templates built on it), every message decoded by its fields; the file reads the same."""
    from fusionlog.io.mcap.schema import file_descriptor_set
    from fusionlog.io.mcap.wire import format_of_schema_record

    path = sample_file(tmp_path / "s.mcap")
    fds = file_descriptor_set()

    def read() -> dict:
        f = McapFile(path)
        return f.read_all(sorted(f.topics))

    monkeypatch.delenv("FUSIONLOG_REFERENCE_PATHS", raising=False)
    assert format_of_schema_record("protobuf", SENSOR_SCHEMA, fds).fast is not None
    fast = read()
    monkeypatch.setenv("FUSIONLOG_REFERENCE_PATHS", "1")
    assert format_of_schema_record("protobuf", SENSOR_SCHEMA, fds).fast is None
    plain = read()
    assert sorted(plain) == sorted(fast)
    for topic, v in fast.items():
        w = plain[topic]
        for a, b in zip(v if isinstance(v, tuple) else (v,), w if isinstance(w, tuple) else (w,),
                        strict=True):  # fmt: skip
            np.testing.assert_array_equal(a, b, err_msg=topic)
