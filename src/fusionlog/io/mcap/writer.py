"""McapWriter: fusionlog's sensor and estimate streams into an MCAP file object.

**Writing order** (what the reader relies on to read with bounded memory): runs are split into
contiguous blocks starting at run 0 (``run_offset`` = 0, r0, r0 + r1, ...); for each block of
runs, for each step k = 0..K, for each topic, exactly one message. All messages of one block
are thus contiguous in the file, so a reader can assemble a block of runs from one sequential
pass and then forget it. Inside a block the order of steps and topics does not matter to the
reader. The writer checks this order cheaply, so a bug in a stage fails here rather than when
the file is read. ``log_time`` = ``publish_time`` = round(time · 1e9) ns.

The writer writes into a file object it is given (normally a
:class:`fusionlog.io.atomic.CheckedFile` from ``Outputs.open``, which owns the temporary file,
the fsync and the commit); it never sees a path, checks no existence and renames nothing.
"""

from __future__ import annotations

import math
import operator
import os
import struct
from collections import deque
from collections.abc import Sequence
from itertools import compress
from typing import Any

import foxglove
import numpy as np
from foxglove.mcap import MCAPCompression, MCAPWriteOptions, MCAPWriter
from mcap.exceptions import McapError
from mcap.reader import SeekingReader

from fusionlog.errors import OutputError

from .arrival import arrival_field
from .bookkeeping import FirstTimes, StepCounts, StepSet, TopicState, first_block_layout
from .chunks import one_line
from .layout import LAYOUT_META, LISTED, Layout
from .run_steps import RunColumn, encode_run_steps, log_times, present_runs
from .schema import ESTIMATE, ESTIMATE_SCHEMA, SENSOR_SCHEMA, VALUES, file_descriptor_set
from .sink import SignalGuard, Sink
from .wire import (
    UINT32_MAX,
    encode_step_time,
)

__all__ = ["McapWriter"]

_F8 = np.dtype("<f8")
_WINDOW = 4096  # instants encoded at once by write_run_steps (~3 MB for seven estimates)
_COMPRESSION = {"zstd": MCAPCompression.Zstd, "lz4": MCAPCompression.Lz4, "none": None}


def _payload(a: np.ndarray) -> bytes | memoryview:
    """The bytes of a float64 array in C order for the message's one join: a C-contiguous
    array's own buffer (joined without a copy of its own; a 10^4-run covariance payload is
    1.3 MB), else a gathered copy (tobytes is C order whatever the strides)."""
    return memoryview(a).cast("B") if a.flags.c_contiguous else a.tobytes()


class McapWriter:
    """Write a fusionlog MCAP file into ``file`` (write, seek and flush; e.g. a CheckedFile).

    The MCAP records are written by the Foxglove SDK's MCAP writer (Rust, ``foxglove-sdk``): the
    pure-Python ``mcap.writer`` spends ~7 µs per message, which capped a one-run log near 10^5
    messages/s. Its header names that library (``foxglove-sdk-python/... mcap-rust/...``);
    which fusionlog wrote the file is in the ``fusionlog.provenance`` metadata.

    Chunks are uncompressed by default: random float64 payloads shrink by only ~7 % under zstd,
    which cost about a third of the estimate stage and most of the per-message write rate; the
    chunk and data-section CRCs (checked on reading) still catch corruption.

    Use as a context manager (or call :meth:`close`): leaving the block normally finalises the
    file and reads its summary back to check that it holds every message handed over; leaving
    it with an exception stops writing (the owner of ``file`` deletes it). The first failed
    write raises its OutputError from the call that met it. The file object is not closed.

    The writer owns the ``fusionlog.layout`` metadata record (see :mod:`.layout`), written at
    the end; a ``fusionlog.layout`` passed to :meth:`add_metadata` (copied from another file)
    is left out.
    """

    def __init__(
        self,
        file: Any,
        *,
        compression: str = "none",
        chunk_size: int = 1024 * 1024,
        time_origin_ns: int = 0,
    ) -> None:
        if isinstance(file, (str, bytes, os.PathLike)):
            raise TypeError(
                "McapWriter writes into a file object (fusionlog.io.atomic.Outputs.open), "
                f"not a path: {file!r}"
            )
        if not all(callable(getattr(file, m, None)) for m in ("write", "seek", "flush")):
            raise TypeError("McapWriter needs a binary file object with write, seek and flush")
        if compression not in _COMPRESSION:
            raise ValueError(f"compression must be one of {sorted(_COMPRESSION)}")
        self.file = file
        name = getattr(file, "target", None) or getattr(file, "name", None) or "MCAP output"
        self.name = str(name)
        self._sink = Sink(file, self.name)
        self._schemas: dict[str, foxglove.Schema] = {}
        #: whether the schema declares the Block's ``arrival`` (`declare_arrival`)
        self._arrival_schema = False
        self._topic_states: dict[str, TopicState] = {}
        self._messages = 0
        self._block_offset, self._block_runs = -1, 0  # block of runs being written
        self._blocks = 0
        self._first_times = FirstTimes()  # step -> time, in the first block of runs
        self._first_steps: dict[str, StepCounts] = {}  # topic -> its steps in the first block
        self._hstep: int = -1  # step and time whose encoded fields are in _head
        self._htime: float = math.nan
        self._head = b""
        self._t_ns = 0
        self._origin = 0
        self.set_time_origin(time_origin_ns)
        # A context of its own per file: channels and sinks do not leak between files.
        self._ctx = foxglove.Context()
        options = MCAPWriteOptions(
            compression=_COMPRESSION[compression],
            chunk_size=chunk_size,
            profile="",
            compression_threads=0,  # same bytes whatever the machine
        )
        self._writer: MCAPWriter | None = None
        self._guarded = SignalGuard.acquire()
        try:
            self._writer = foxglove.open_mcap(self._sink, context=self._ctx, writer_options=options)
            self._check_sink()
        except BaseException:
            self.abort()
            raise

    def set_time_origin(self, time_origin_ns: int) -> None:
        """log_time = time_origin_ns + time in ns: an imported log keeps its recorded timestamps
        while its `time` fields count seconds from its first instant, and files written from it
        (a replay's estimates: `McapFile.time_origin_ns` of its sensors file) keep them too.
        Set by the constructor, or here before the first message."""
        origin = operator.index(time_origin_ns)
        if not 0 <= origin < 2**63:
            raise ValueError(f"time_origin_ns must fit in 63 bits, got {origin}")
        if self._messages and origin != self._origin:
            raise ValueError("the clock of a file is set before its first message")
        self._origin = origin

    def __enter__(self) -> McapWriter:
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is not None:
            self.abort()
            return
        self.close()

    def _check_sink(self) -> None:
        """Raise what the sink kept during the last Rust call: a signal's (its original handler
        runs now, and usually raises), or the first failed write."""
        sink = self._sink
        if sink.pending:
            sink.deliver_signals()
        if sink.error is not None:
            raise sink.error

    def abort(self) -> None:
        """Stop writing: nothing more reaches the file (which its owner deletes). Raises only
        what a signal that came meanwhile raises."""
        writer, self._writer = self._writer, None
        self._forget()
        if writer is not None:
            if self._sink.error is None:
                self._sink.error = OutputError(f"{self.name}: writing was abandoned")
            try:
                writer.close()  # into the sink, which drops the bytes
            except Exception:
                pass
        if self._guarded:
            self._guarded = False
            SignalGuard.release()
        self._sink.deliver_signals()

    def close(self) -> None:
        """Write the layout record, finalise the file, and check that it reads back with every
        message handed over (the SDK only logs, does not raise, a message it failed to
        record). The file object stays open: its owner fsyncs and commits it."""
        if self._writer is None:
            self._check_sink()  # closed already, or aborted: its error again
            return
        try:
            layout = self._layout()
            self._forget()
            if layout is not None:
                self._writer.write_metadata(LAYOUT_META, layout.to_metadata())
                self._check_sink()
            writer, self._writer = self._writer, None
            try:
                writer.close()
            except RuntimeError as e:
                if not self._sink.alert:
                    raise OutputError(f"{self.name}: cannot write: {one_line(e)}") from None
            self._check_sink()
            if self._guarded:
                self._guarded = False
                SignalGuard.release()
            self.file.flush()  # before reading back through another handle
            self._check_written()
        except BaseException:
            self.abort()
            raise

    def _forget(self) -> None:
        """Drop the per-message bookkeeping (a long log's: ~30 MB at 10^6 instants, see
        `.bookkeeping`), which only writing and the layout need, so that a closed writer still
        referenced by its caller does not hold it through the stages that follow."""
        self._forget_seen()
        self._first_times = FirstTimes()
        self._first_steps = {}

    def _forget_seen(self) -> None:
        for st in self._topic_states.values():
            st.seen = StepSet()

    def _trim(self) -> None:
        """Past `LISTED` instants the topics' steps are counted only (`.layout`)."""
        if len(self._first_times) > LISTED:
            for counts in self._first_steps.values():
                counts.drop()

    def _layout(self) -> Layout | None:
        """The file's structure as written (`first_block_layout`)."""
        self._trim()
        dims = {t: st.dim for t, st in self._topic_states.items()}
        runs = max(0, self._block_offset + self._block_runs)
        return first_block_layout(self._first_times, self._first_steps, dims, runs, self._blocks)

    def _check_written(self) -> None:
        path = getattr(self.file, "tmp", None) or getattr(self.file, "name", None)
        readable = getattr(self.file, "readable", None)
        try:
            if isinstance(path, (str, os.PathLike)) and os.path.isfile(path):
                with open(path, "rb") as f:
                    summary = SeekingReader(f).get_summary()
            elif callable(getattr(self.file, "read", None)) and (readable is None or readable()):
                self.file.seek(0)
                summary = SeekingReader(self.file).get_summary()
            else:
                return  # write-only and nameless: nothing to read back
            count = summary.statistics.message_count if summary and summary.statistics else -1
        except (McapError, OSError, ValueError, struct.error, EOFError) as e:
            raise OutputError(f"{self.name}: written file does not read back: {e}") from None
        if count != self._messages:
            raise OutputError(
                f"{self.name}: wrote {self._messages} messages, the file holds {count}"
            )

    def _fail(self) -> None:
        try:
            self._check_sink()
        except BaseException:
            self.abort()
            raise

    def _live_writer(self) -> MCAPWriter:
        if self._writer is None:
            raise RuntimeError("McapWriter is closed")
        return self._writer

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Add a metadata record (e.g. ``fusionlog.scenario``, ``fusionlog.provenance``)."""
        if not all(isinstance(k, str) and isinstance(v, str) for k, v in data.items()):
            raise TypeError(f"metadata {name!r} must map str to str")
        if name == LAYOUT_META:
            return  # the writer's own, written at the end
        self._live_writer().write_metadata(name, dict(data))
        if self._sink.alert:
            self._fail()

    def _new_topic(self, topic: str, kind: str, dim: int) -> TopicState:
        st = self._topic_states.get(topic)
        if st is not None:
            if st.kind != kind:
                raise ValueError(f"topic {topic!r} was written as {st.kind}, not {kind}")
            raise ValueError(f"topic {topic!r} has dim {st.dim}, got a message with dim {dim}")
        if not topic or not isinstance(topic, str):
            raise ValueError(f"bad topic {topic!r}")
        self._live_writer()
        schema_name = SENSOR_SCHEMA if kind == VALUES else ESTIMATE_SCHEMA
        schema = self._schemas.get(schema_name)
        if schema is None:
            schema = foxglove.Schema(
                name=schema_name,
                encoding="protobuf",
                data=file_descriptor_set(self._arrival_schema),
            )
            self._schemas[schema_name] = schema
        channel = foxglove.Channel(
            topic, schema=schema, message_encoding="protobuf", context=self._ctx
        )
        st = TopicState(len(self._topic_states), channel.base.log, kind, dim)
        self._topic_states[topic] = st
        return st

    def _new_block(self, topic: str, run_offset: int, runs: int) -> None:
        run_offset = operator.index(run_offset)
        if run_offset == self._block_offset:
            raise ValueError(
                f"{topic}: block at run {run_offset} has {self._block_runs} runs, got {runs}"
            )
        expected = 0 if self._block_offset < 0 else self._block_offset + self._block_runs
        if run_offset != expected:
            raise ValueError(
                f"{topic}: block of runs starts at {run_offset}, expected {expected} "
                "(blocks of runs must be written in order, contiguously from run 0)"
            )
        if run_offset + runs - 1 > UINT32_MAX:
            raise ValueError("run indices must fit in uint32")
        self._block_offset, self._block_runs = run_offset, runs
        self._blocks += 1
        self._forget_seen()

    def _set_head(self, step: int, time: float) -> None:
        """Encode the step and time fields once per step: every topic of the step shares them."""
        step = operator.index(step)
        time = float(time) + 0.0  # + 0.0 turns -0.0 into 0.0, which proto3 omits
        if not 0 <= step <= UINT32_MAX:
            raise ValueError(f"step must fit in uint32, got {step}")
        if not (time >= 0.0 and math.isfinite(time)):  # log_time is an unsigned ns count
            raise ValueError(f"time must be finite and >= 0, got {time}")
        if self._block_offset == 0:  # the layout record's times: the first block's
            self._first_times.setdefault(step, time)
            if step == LISTED + 1:
                self._trim()
        self._hstep, self._htime = step, time
        self._head, self._t_ns = encode_step_time(step, time), self._origin + round(time * 1e9)

    def _write(
        self,
        topic: str,
        kind: str,
        step: int,
        time: float,
        run_offset: int,
        runs: int,
        dim: int,
        p1: bytes | memoryview,
        p2: bytes | memoryview,
        p3: bytes = b"",
    ) -> None:
        # The hot path: a few dict/set operations and one bytes join per message; everything
        # that only changes per step, per topic or per block is cached.
        if self._writer is None:
            raise RuntimeError("McapWriter is closed")
        st = self._topic_states.get(topic)
        if st is None or st.kind != kind or st.dim != dim:
            st = self._new_topic(topic, kind, dim)
        if run_offset != self._block_offset or runs != self._block_runs:
            self._new_block(topic, run_offset, runs)
        if step != self._hstep or time != self._htime:  # checks the step: uint32
            self._set_head(step, time)
        seen = st.seen
        if step in seen:
            raise ValueError(f"{topic}: step {step} written twice for runs from {run_offset}")
        seen.add(step)
        if run_offset == 0:  # the steps a topic has (every instant, or its own: layout record)
            first = self._first_steps.get(topic)
            if first is None:
                first = self._first_steps[topic] = StepCounts()
            first.add(step)
        if st.mid_key != (run_offset, runs, len(p2)):
            st.set_mid(run_offset, runs, len(p2))
        st.log(b"".join((self._head, st.mid, p1, st.mid2, p2, p3)), self._t_ns)
        self._messages += 1
        if self._sink.alert:  # a write failed or a signal came during this message
            self._fail()

    def declare_arrival(self) -> None:
        """Declare the Block's ``arrival`` field in the file's schema (a sensors file of late
        sensors), before the first message; other files keep the schema without it."""
        if self._schemas:
            raise RuntimeError("declare_arrival: a schema is already written")
        self._arrival_schema = True

    def write_values(
        self,
        topic: str,
        step: int,
        time: float,
        run_offset: int,
        values: np.ndarray,
        covariance: np.ndarray | None = None,
        arrival: np.ndarray | float | None = None,
    ) -> None:
        """Write one ``fusionlog.Block``: ``values`` (runs, dim) at ``step`` for a block of runs,
        with the optional per-message measurement ``covariance`` (runs, dim, dim) and the
        optional ``arrival`` time of the readings (s; one value, or (runs,))."""
        if type(values) is not np.ndarray or values.dtype != _F8:
            values = np.asarray(values, dtype=_F8)
        shape = values.shape
        if len(shape) != 2 or shape[0] < 1 or shape[1] < 1:
            raise ValueError(f"values must have shape (runs >= 1, dim >= 1), got {shape}")
        p2 = b""
        if covariance is not None:
            c = np.asarray(covariance, dtype=_F8)
            if c.shape != (shape[0], shape[1], shape[1]):
                raise ValueError(f"covariance must have shape {(shape[0], shape[1], shape[1])}")
            p2 = c.tobytes()
        p3 = b""
        if arrival is not None:
            if np.size(arrival) not in (1, shape[0]):
                raise ValueError(f"arrival must have one value or {shape[0]}")
            if not self._arrival_schema:
                raise ValueError("arrival: call declare_arrival before the first message")
            p3 = arrival_field(arrival)
        # tobytes() is C order whatever the strides, so no ascontiguousarray copy is needed.
        self._write(
            topic, VALUES, step, time, run_offset, shape[0], shape[1], values.tobytes(), p2, p3
        )

    def write_estimate(
        self,
        topic: str,
        step: int,
        time: float,
        run_offset: int,
        mean: np.ndarray,
        cov: np.ndarray,
    ) -> None:
        """Write one ``fusionlog.EstimateBlock``: mean (runs, n), cov (n, n) or (runs, n, n)."""
        m = mean if type(mean) is np.ndarray and mean.dtype == _F8 else np.asarray(mean, _F8)
        c = cov if type(cov) is np.ndarray and cov.dtype == _F8 else np.asarray(cov, _F8)
        if m.ndim != 2 or m.shape[0] < 1 or m.shape[1] < 1:
            raise ValueError(f"mean must have shape (runs >= 1, n >= 1), got {m.shape}")
        runs, n = m.shape
        if c.shape != (n, n) and c.shape != (runs, n, n):
            raise ValueError(f"cov must have shape ({n}, {n}) or ({runs}, {n}, {n}), got {c.shape}")
        self._write(topic, ESTIMATE, step, time, run_offset, runs, n, _payload(m), _payload(c))

    def write_run_steps(
        self,
        k0: int,
        times: np.ndarray,
        columns: Sequence[RunColumn],
        present: np.ndarray | None = None,
    ) -> None:
        """One run's messages at instants k0..k0+w-1 (``times`` (w,) s): for each instant, for
        each column in order, the message `write_values` (a VALUES column, its covariance and
        arrival optional) or `write_estimate` (an ESTIMATE column: mean and covariance) would
        write, byte for byte, encoded a window of instants at a time (`.run_steps`: a long
        one-run log's ~10^7 messages would cost ~5 µs each one by one). ``present`` (w, C)
        bool: the instants each column has a message at (an imported log's topics, each at its
        own instants; every instant has one), default every instant."""
        if self._writer is None:
            raise RuntimeError("McapWriter is closed")
        t = np.asarray(times, dtype=float) + 0.0  # + 0.0: -0.0 as 0.0, as `_set_head`
        w, C = len(t), len(columns)
        if not w or not columns:
            return
        if not (np.isfinite(t).all() and (t >= 0).all()) or k0 + w - 1 > UINT32_MAX:
            raise ValueError(f"time must be finite and >= 0, steps to {k0 + w - 1} in uint32")
        keep = np.ones((w, C), bool) if present is None else np.asarray(present, bool)
        if keep.shape != (w, C) or not keep.any(axis=1).all():
            raise ValueError(f"present must be ({w}, {C}) with a message at every instant")
        for c in columns:
            if c.kind == ESTIMATE and c.second is None:
                raise ValueError(f"{c.topic}: an estimate needs its covariance")
            if c.arrival is not None and not self._arrival_schema:
                raise ValueError("arrival: call declare_arrival before the first message")
        if self._block_offset != 0 or self._block_runs != 1:
            self._new_block(columns[0].topic, 0, 1)
        states: list[TopicState | None] = [None] * C
        # topics made in the order of their first message, as one by one
        for ci in sorted(np.flatnonzero(keep.any(axis=0)).tolist(),
                         key=lambda ci: (int(keep[:, ci].argmax()), ci)):  # fmt: skip
            c, d = columns[ci], np.shape(columns[ci].first)[-1]
            st = self._topic_states.get(c.topic)
            st = states[ci] = st if st and (st.kind, st.dim) == (c.kind, d) else \
                self._new_topic(c.topic, c.kind, d)  # fmt: skip
            first = self._first_steps.setdefault(c.topic, StepCounts())
            a, b = present_runs(keep[:, ci])
            twice = st.seen.add_ranges(k0 + a, k0 + b)
            if twice is not None:
                raise ValueError(f"{c.topic}: step {twice} written twice for runs from 0")
            first.add_ranges(k0 + a, k0 + b)
        self._first_times.extend(k0, t)
        self._trim()
        self._hstep = -1  # the one-message path's cached head is not these instants'
        logs = [None if st is None else st.log for st in states]
        for i in range(0, w, _WINDOW):
            j = min(w, i + _WINDOW)
            buf, bounds = encode_run_steps(k0 + i, t[i:j], [c.rows(i, j) for c in columns])
            k = keep[i:j].ravel()  # the messages at the instants present
            x, y = bounds[:-1][k].tolist(), bounds[1:][k].tolist()
            msgs = [buf[a:b] for a, b in zip(x, y, strict=True)]
            ns = compress(log_times(self._origin, t[i:j], C), k.tolist())
            calls = compress(logs * (j - i), k.tolist())
            deque(map(operator.call, calls, msgs, ns), maxlen=0)
            self._messages += len(msgs)
            if self._sink.alert:  # a write failed or a signal came during these messages
                self._fail()
