"""Reading a fusionlog recording back offline (no viewer, no network): its properties, its
summary and every scalar series, for ``fusionlog summary`` and the tests."""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from fusionlog.errors import DamagedFile, FusionlogError
from fusionlog.inputs import check_input

__all__ = ["read_recording"]


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def read_recording(path: str | os.PathLike[str], *, series: bool = True) -> dict[str, Any]:
    """Read an evaluation recording.

    Returns {"application_id", "recording_id", "name", "properties": {property: {field: value}},
    "summary": dict, "steps": (S,) int array, "times": (S,) float seconds,
    "series": {entity path (see `entity_path`): (S,) float array, NaN where not logged}}
    with S the union of logged steps, sorted. Raises FusionlogError (one line) if the file is
    missing or unreadable, DamagedFile if it is damaged (truncated, changed bytes), and
    FusionlogError if it is not a fusionlog recording (no summary, or one that is not a JSON
    object).

    With ``series=False`` (``fusionlog summary``) every chunk is still decoded, so damage is
    found as above, but only the properties are kept: "steps", "times" and "series" are empty.
    Memory is then that of one chunk, not of the recording's series (a 10^6-instant log's
    recording holds ~0.5 GB of them, decoded several times over).
    """
    path = Path(path)
    check_input(path)  # a FIFO or a device: say what it is (it is no missing file)
    if path.is_dir():
        raise FusionlogError(f"{path}: is a directory, not a recording")
    if not path.is_file():
        raise FusionlogError(f"{path}: no such file")
    try:
        stores, chunks = _load(path, series)
    except OSError as exc:
        raise FusionlogError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except Exception as exc:  # the Rust reader raises assorted errors on damaged files
        raise DamagedFile(
            f"{path}: not a readable Rerun recording ({_first_line(exc)})", path, recoverable=False
        ) from None
    if not stores:
        raise FusionlogError(f"{path}: contains no recording")
    try:
        name, properties, raw = _collect(chunks)
    except Exception as exc:  # decodable framing but unexpected columns: damaged content
        raise DamagedFile(
            f"{path}: damaged recording ({_first_line(exc)})", path, recoverable=False
        ) from None
    summary = _summary(path, properties)
    steps, times, series = _align(raw)
    return {
        "application_id": stores[0].application_id,
        "recording_id": stores[0].recording_id,
        "name": name,
        "properties": properties,
        "summary": summary,
        "steps": steps,
        "times": times,
        "series": series,
    }


def _is_property(chunk: Any) -> bool:
    ent = str(chunk.entity_path)
    return ent == "/__properties" or ent.startswith("/__properties/")


def _load(path: Path, series: bool = True) -> tuple[list[Any], list[Any]]:
    from rerun.chunk import RrdReader

    with warnings.catch_warnings():
        # a damaged file first warns "no footer", then fails below: report only the failure
        warnings.simplefilter("ignore")
        reader = RrdReader(str(path))
        stores = [s for s in reader.recordings() if s.kind == "recording"]
        stream = reader.store().stream()
        if not series:  # each chunk decoded (a damaged one fails), then dropped unless a property
            stream = stream.flat_map(lambda ch: [ch] if _is_property(ch) else [])
        chunks = list(stream.to_chunks())
    return stores, chunks


def _collect(chunks: list[Any]) -> tuple[Any, dict[str, dict[str, Any]], dict[str, list]]:
    """(recording name, properties, {entity: [(steps, times, values) per chunk]})."""
    properties: dict[str, dict[str, Any]] = {}
    name = None
    raw: dict[str, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {}
    for ch in chunks:
        ent = str(ch.entity_path)
        rb = ch.to_record_batch()
        cols = {c: rb.column(c) for c in rb.schema.names if c != "rerun.controls.RowId"}
        if _is_property(ch):
            if ent == "/__properties":
                if "RecordingInfo:name" in cols:
                    name = cols["RecordingInfo:name"].to_pylist()[-1][0]
                continue
            prop = ent.removeprefix("/__properties/")
            fields = properties.setdefault(prop, {})
            for c, arr in cols.items():
                vals = arr.to_pylist()[-1]
                fields[c] = vals[0] if isinstance(vals, list) and len(vals) == 1 else vals
            continue
        if ch.is_static or "Scalars:scalars" not in cols or "step" not in cols:
            continue
        steps = cols["step"].to_numpy(zero_copy_only=False).astype(np.int64)
        if "time" in cols:
            t = cols["time"].cast("int64").to_numpy(zero_copy_only=False) / 1e9
        else:
            t = np.full(steps.shape, np.nan)
        vals = cols["Scalars:scalars"].flatten().to_numpy(zero_copy_only=False).astype(float)
        if vals.shape != steps.shape:
            continue  # not one scalar per row: not one of ours
        raw.setdefault(ent.lstrip("/"), []).append((steps, t, vals))
    return name, properties, raw


def _summary(path: Path, properties: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """The ``summary`` property's JSON, which must be an object (the summary table)."""
    text = properties.get("summary", {}).get("json")
    if text is None:
        raise FusionlogError(f"{path}: not a fusionlog recording (no summary property)")
    try:
        summary = json.loads(text)
    except (TypeError, ValueError, RecursionError) as exc:
        raise FusionlogError(f"{path}: corrupt summary property ({_first_line(exc)})") from None
    if not isinstance(summary, dict):
        raise FusionlogError(
            f"{path}: corrupt summary property (not a JSON object ({_json_type(summary)}))"
        )
    return summary


def _align(raw: dict[str, list]) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Every series on the union of the logged steps, NaN where a series was not logged."""
    all_steps = (
        np.unique(np.concatenate([s for parts in raw.values() for s, _, _ in parts]))
        if raw
        else np.zeros(0, dtype=np.int64)
    )
    times = np.full(all_steps.shape, np.nan)
    series: dict[str, np.ndarray] = {}
    for ent, parts in raw.items():
        out = np.full(all_steps.shape, np.nan)
        for steps, t, vals in parts:
            idx = np.searchsorted(all_steps, steps)
            out[idx] = vals
            times[idx] = t
        series[ent] = out
    return all_steps, times, dict(sorted(series.items()))


def _json_type(v: Any) -> str:
    """A parsed JSON value's type in JSON's words."""
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "boolean"
    if isinstance(v, list):
        return "list"
    if isinstance(v, str):
        return "str"
    return "number"
