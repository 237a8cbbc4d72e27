"""Reading a damaged MCAP file as far as it goes (``fusionlog inspect --recover``).

A seeking reader needs the footer, which a truncated file lacks, so the records are read
sequentially from the start up to the first damage, and what they say is summed up: topics and
messages read, the steps of the first block of runs, the runs whose block was read in full for
every fusionlog topic, and the last step every topic reached in the last block.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from mcap.records import Channel, Header, Message, Metadata, Schema

from fusionlog.inputs import check_input

from .chunks import one_line, open_error, records
from .wire import MessageFormat, decode, format_of_schema_record

__all__ = ["recover"]


def recover(path: str | os.PathLike[str]) -> dict[str, Any]:
    """What is still readable from a damaged (e.g. truncated) file, for ``inspect --recover``.

    Reads records sequentially up to the first damage (a seeking reader needs the footer, which
    a truncated file lacks). Returns a dict with ``error`` (why reading stopped, None if the
    file read to its end), ``library``, ``metadata``, ``schemas`` {topic: schema name},
    ``topics`` {topic: messages read}, ``messages``, ``steps`` (distinct steps of the first
    block of runs), ``complete_runs`` (runs whose block was read in full for every fusionlog
    topic), ``last_complete_step`` (last step k such that every fusionlog topic has steps 0..k
    in the last block read; -1 if none) and ``last_complete_time``.
    """
    p = Path(path)
    out: dict[str, Any] = {
        "path": str(p),
        "error": None,
        "library": None,
        "metadata": {},
        "schemas": {},
        "topics": {},
        "messages": 0,
        "steps": 0,
        "complete_runs": 0,
        "last_complete_step": -1,
        "last_complete_time": None,
    }
    schemas: dict[int, Schema] = {}
    channels: dict[int, tuple[str, MessageFormat | None]] = {}
    readable: set[str] = set()  # topics with a fusionlog schema
    # The block of runs being read: (run_offset, runs) and {topic: {step: time}}.
    block: tuple[int, int] | None = None
    seen: dict[str, dict[int, float]] = {}
    first_steps: set[int] | None = None

    def close_block() -> None:
        nonlocal first_steps
        if block is None:
            return
        if first_steps is None:
            first_steps = set().union(*(s.keys() for s in seen.values()))
        if all(first_steps <= seen.get(t, {}).keys() for t in readable):
            out["complete_runs"] += block[1]

    check_input(p)  # a FIFO or a device would block or never end
    try:
        with open(p, "rb") as f:
            for rec in records(f):
                if isinstance(rec, Message):
                    if rec.channel_id not in channels:
                        continue
                    topic, fmt = channels[rec.channel_id]
                    out["messages"] += 1
                    out["topics"][topic] += 1
                    if fmt is None:
                        continue
                    step, t, off, runs, _, _, _ = decode(rec.data, fmt)
                    if block is None or block[0] != off:
                        close_block()
                        block, seen = (off, runs), {}
                    seen.setdefault(topic, {})[step] = t
                elif isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    schema = schemas.get(rec.schema_id)
                    fmt = None
                    if schema is not None and rec.message_encoding == "protobuf":
                        fmt = format_of_schema_record(schema.encoding, schema.name, schema.data)
                    channels[rec.id] = (rec.topic, fmt)
                    out["schemas"][rec.topic] = schema.name if schema is not None else ""
                    out["topics"].setdefault(rec.topic, 0)
                    if fmt is not None:
                        readable.add(rec.topic)
                elif isinstance(rec, Metadata):
                    out["metadata"][rec.name] = dict(rec.metadata)
                elif isinstance(rec, Header):
                    out["library"] = rec.library
    except OSError as e:
        raise open_error(p, e) from e
    except Exception as e:  # whatever the damage looks like, report what came before it
        out["error"] = one_line(e)
    close_block()
    out["steps"] = len(first_steps or ())
    if block is not None:
        k = -1
        while readable and all(k + 1 in seen.get(t, {}) for t in readable):
            k += 1
        out["last_complete_step"] = k
        if k >= 0:
            out["last_complete_time"] = next(iter(seen.values()))[k]
    return out
