"""The recording stream every fusionlog recording is written through (state and identity).

What all recordings share: application id ``fusionlog``; a recording id derived from the
scenario name and the seed (identical inputs give identical data); the recording name; the
recording properties ``scenario`` (name, seed, and the scenario text if given), ``summary``
(field ``json``: the summary table as JSON) and any further ``properties``; the default
blueprint in the same file; timelines ``step`` (sequence) and ``time`` (duration, seconds); and
series sent with ``send_columns`` (:class:`SeriesWriter`), never point by point.

**How the bytes reach the disk.** Rerun's file sink (``RecordingStream.save``) only *logs* a
failed write ("No space left on device"), leaves a truncated file and can hang in
``disconnect()`` on a full disk. So a recording is never given a path on a disk: Rerun's file
sink writes into a named pipe in a private temporary folder, and a thread (:class:`_Pump`)
copies what comes out of it with Python file I/O into the file object the caller gives (a
:class:`fusionlog.io.atomic.CheckedFile`), where the first failed write raises
:class:`fusionlog.errors.OutputError` (the pump keeps draining the pipe, so Rerun never blocks,
and the error is raised when the recording ends). The encoded recording is never held whole:
an in-memory ``binary_stream()`` held it twice at the end (Rerun's buffer and the ``bytes``
of its ``read``; a long log's 200 MB recording: about 0.1 GiB more peak memory), and reading
that stream in parts gives complete RRD streams that do not concatenate into one recording
(rerun-sdk 0.41: "More than one RRD manifest", a CRC error).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import threading
import uuid
from collections.abc import Iterator, Mapping, Sequence
from typing import IO, Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from fusionlog.errors import FusionlogError, OutputError
from fusionlog.jsonout import dumps

__all__ = [
    "APPLICATION_ID",
    "SeriesWriter",
    "entity_path",
    "output_name",
    "recording_error",
    "recording_id_for",
    "recording_stream",
    "write_all",
]

APPLICATION_ID = "fusionlog"

#: Bytes handed to one ``write`` call: a failing disk is reported after at most this much more.
_PIECE = 1 << 20


def entity_path(*parts: str | int) -> str:
    """Entity path (no leading slash) from unescaped parts, as keys of `read_recording` series."""
    return "/".join(rr.escape_entity_path_part(str(p)) for p in parts)


def recording_id_for(scenario_name: str, seed: int) -> str:
    """Deterministic recording id from the scenario name and the seed."""
    return str(uuid.uuid5(uuid.NAMESPACE_URL, f"fusionlog:{scenario_name}:{seed}"))


def output_name(file: IO[bytes]) -> str:
    """How errors name the output: the target of a CheckedFile, else the file's name."""
    name = getattr(file, "target", None) or getattr(file, "name", None)
    return str(name) if name is not None else "recording"


def recording_error(file: IO[bytes], msg: str) -> FusionlogError:
    """The error for data that cannot make a recording (raised before anything is written)."""
    return FusionlogError(f"{output_name(file)}: cannot write recording: {msg}")


def check_axes(
    file: IO[bytes], times: np.ndarray, names: Sequence[str], *, least: int, what: str
) -> tuple[int, int]:
    """The recording's axes: `times` a non-empty 1-D array, `names` (states or classes) unique
    and at least `least`. Returns (steps, names)."""
    if times.ndim != 1 or times.shape[0] < 1:
        raise recording_error(file, f"times must be a non-empty 1-D array, got shape {times.shape}")
    if len(set(names)) != len(names) or len(names) < least:
        raise recording_error(file, f"{what} must be unique, at least {least}, got {list(names)}")
    return times.shape[0], len(names)


def write_all(file: IO[bytes], data: bytes | bytearray | memoryview) -> None:
    """Write every byte of `data` to `file` and flush it; any failure is an OutputError."""
    view = memoryview(data)
    try:
        while view:
            n = file.write(view[:_PIECE])
            if not n:  # a raw file that took nothing: no progress is a failure, not a loop
                raise OutputError(f"{output_name(file)}: cannot write: nothing was written")
            view = view[n:]
        file.flush()
    except OSError as e:  # a plain file; a CheckedFile raises OutputError itself
        raise OutputError(f"{output_name(file)}: cannot write: {e.strerror or e}") from None


def _property_value(v: Any) -> str:
    """Every property field is a string: Rerun types a field name once for all properties, so
    `seed` as an int in one property and a string in another would be dropped with a warning."""
    if isinstance(v, str):
        return v
    return dumps(v, sort_keys=True, default=str)


def _send_properties(
    rec: rr.RecordingStream,
    scenario_name: str,
    seed: int,
    summary: Mapping[str, Any],
    properties: Mapping[str, Any] | None,
) -> None:
    props: dict[str, dict[str, Any]] = {"scenario": {"name": scenario_name, "seed": str(seed)}}
    for key, value in (properties or {}).items():
        fields = (
            {str(k): _property_value(v) for k, v in value.items()}
            if isinstance(value, Mapping)
            else {"text": _property_value(value)}
        )
        props.setdefault(str(key), {}).update(fields)
    props["summary"] = {"json": dumps(summary)}  # strict JSON; keeps the arch order
    for key in sorted(props):
        rec.send_property(key, rr.AnyValues(**props[key]))


@contextlib.contextmanager
def recording_stream(
    file: IO[bytes],
    blueprint: rrb.Blueprint,
    scenario_name: str,
    seed: int,
    times: np.ndarray,
    summary: Mapping[str, Any],
    properties: Mapping[str, Any] | None = None,
    recording_id: str | None = None,
    axes: Mapping[str, tuple[str, np.ndarray]] | None = None,
) -> Iterator[SeriesWriter]:
    """A recording (application id, recording id, name, default blueprint, properties) whose
    series the block sends through the yielded :class:`SeriesWriter`; when the block completes
    the recording is complete in `file` (written as it is encoded). If the block raises,
    `file` holds an incomplete recording, which its owner discards (`Outputs` commits nothing).
    `axes` replaces the timelines ``step`` and ``time`` (see :class:`SeriesWriter`).

    The default blueprint goes into the same file, as ``save(default_blueprint=...)`` puts it:
    a blueprint store followed by the activation command "make default, not active".
    """
    rec = rr.RecordingStream(
        APPLICATION_ID,
        recording_id=recording_id or recording_id_for(scenario_name, seed),
        send_properties=False,  # no wall-clock start_time: identical inputs give identical data
    )
    with (
        tempfile.TemporaryDirectory(prefix="fusionlog-rrd-") as folder,
        _Pump(folder, file) as pipe,
    ):
        rec.save(pipe)  # Rerun's file sink, into the pipe: nothing of Rerun's touches a disk
        try:
            rec.send_blueprint(blueprint, make_active=False, make_default=True)
            rec.send_recording_name(scenario_name)
            _send_properties(rec, scenario_name, seed, summary, properties)
            yield SeriesWriter(rec, times, axes)
            rec.flush()
        finally:
            rec.disconnect()  # closes the pipe's writing end: the pump sees its end


def _whole_ns(kind: str, values: np.ndarray) -> np.ndarray:
    """A duration timeline's seconds as the nearest whole nanoseconds: Rerun truncates the
    seconds it is given (4.1625 s became 4.162499999 s, a nanosecond before the instant the
    estimates' `time` and log_time stamp). Other timelines, and seconds a 64-bit count of
    nanoseconds cannot hold, as they are."""
    v = np.asarray(values)
    if kind != "duration" or v.dtype.kind != "f" or not (np.abs(v) < 9e9).all():
        return v
    return np.round(v * 1e9).astype(np.int64).astype("timedelta64[ns]")


class _Pump:
    """A named pipe whose bytes a thread copies into `file` (see the module's docstring).

    The pipe is opened at both ends here before Rerun opens it, so that neither Rerun's open
    nor the pump's reads wait on the other: the pump sees the end of the data when every
    writer has closed it (Rerun's sink at ``disconnect``, this object's own end at exit). The
    first failed write is kept and raised at exit; the pipe is drained to its end regardless.
    """

    def __init__(self, folder: str, file: IO[bytes]) -> None:
        self.path = os.path.join(folder, "recording.rrd")
        self.file = file
        self.error: BaseException | None = None

    def __enter__(self) -> str:
        os.mkfifo(self.path, 0o600)
        self._read = os.open(self.path, os.O_RDONLY | os.O_NONBLOCK)
        os.set_blocking(self._read, True)
        self._hold = os.open(self.path, os.O_WRONLY)  # no end of data before Rerun's writes
        self._thread = threading.Thread(target=self._run, name="fusionlog-rrd", daemon=True)
        self._thread.start()
        return self.path

    def _run(self) -> None:
        with open(self._read, "rb", buffering=0) as pipe:
            while chunk := pipe.read(_PIECE):
                if self.error is None:
                    try:
                        write_all(self.file, chunk)
                    except BaseException as e:  # raised at exit, in the caller's thread
                        self.error = e

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        os.close(self._hold)
        self._thread.join()
        if exc_type is None and self.error is not None:
            raise self.error


class SeriesWriter:
    """Sends styled time series of one recording, one ``send_columns`` call each."""

    def __init__(
        self,
        rec: rr.RecordingStream,
        times: np.ndarray,
        axes: Mapping[str, tuple[str, np.ndarray]] | None = None,
    ) -> None:
        self.rec = rec
        self.times = np.asarray(times, dtype=float)
        self.steps = np.arange(self.times.shape[0], dtype=np.int64)
        # The timelines every series is indexed by: {name: ("sequence" | "duration", values)},
        # one value per entry of `times`; by default step (k) and time (t_k, seconds).
        self.axes = {
            name: (kind, _whole_ns(kind, values))
            for name, (kind, values) in (
                axes or {"step": ("sequence", self.steps), "time": ("duration", self.times)}
            ).items()
        }
        # Many entities share a style (an architecture's colour and name across states) and
        # most series are defined at every step: build those column batches once.
        self._styles: dict[tuple, Any] = {}
        self._full_index = self.index(np.ones(self.times.shape[0], dtype=bool))

    def index(self, keep: np.ndarray) -> list[rr.TimeColumn]:
        """The timeline columns (``step`` and ``time`` unless `axes` said otherwise) of the
        entries where `keep` is true."""
        return [
            rr.TimeColumn(name, **{kind: np.asarray(values)[keep]})
            for name, (kind, values) in self.axes.items()
        ]

    # Styling goes out with send_columns and no index (= static), so that it lands in the file
    # right before its series instead of being batched; one unbatched chunk each, in order.
    def style_lines(self, path: str, name: str, color: Sequence[int], width: float) -> None:
        key = ("lines", name, tuple(color), width)
        if key not in self._styles:
            self._styles[key] = rr.SeriesLines.columns(
                names=[name], colors=[list(color)], widths=[width]
            )
        self.rec.send_columns(path, indexes=[], columns=self._styles[key], strict=True)

    def style_points(self, path: str, name: str, color: Sequence[int]) -> None:
        key = ("points", name, tuple(color))
        if key not in self._styles:
            self._styles[key] = rr.SeriesPoints.columns(
                names=[name], colors=[list(color)], markers=["circle"], marker_sizes=[2.5]
            )
        self.rec.send_columns(path, indexes=[], columns=self._styles[key], strict=True)

    def send(self, path: str, values: np.ndarray) -> None:
        """One scalar series; steps where it is not finite are not logged."""
        values = np.asarray(values, dtype=float)
        keep = np.isfinite(values)
        if keep.all():
            indexes = self._full_index
        elif keep.any():
            indexes, values = self.index(keep), values[keep]
        else:
            return
        self.rec.send_columns(
            path, indexes=indexes, columns=rr.Scalars.columns(scalars=values), strict=True
        )

    def line(self, path: str, values: np.ndarray, name: str, color: Sequence[int], width: float):
        """A series drawn as a line (``SeriesLines``); with a single instant (``steps = 0``, a
        sweep of one point) a line joins nothing and the viewer draws nothing, so the value is
        a marker (``SeriesPoints``) of the same name and colour."""
        if self.times.shape[0] == 1:
            self.points(path, values, name, color)
            return
        self.style_lines(path, name, color, width)
        self.send(path, values)

    def points(self, path: str, values: np.ndarray, name: str, color: Sequence[int]) -> None:
        """A series drawn as markers (``SeriesPoints``)."""
        self.style_points(path, name, color)
        self.send(path, values)
