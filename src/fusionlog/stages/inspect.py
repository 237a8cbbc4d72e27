"""`fusionlog inspect`: what an MCAP file holds, as lines of text.

For any MCAP: its topics, schemas and message counts (foreign topics with their encoding and
rate); for fusionlog's files also the scenario, who wrote it, runs and instants, and for each
sensor its instants, rate and the share of its readings lost. `describe_damaged` reads a
damaged file as far as it goes.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from fusionlog.io.mcap import McapFile
from fusionlog.io.mcap import recover as recover_file
from fusionlog.io.mcap.topics import SENSORS_PREFIX

__all__ = ["describe", "describe_damaged", "sensor_timing"]


def sensor_timing(mf: McapFile, topic: str) -> str:
    """A sensor's instants and rate (its instants per second of the log), and the share of its
    readings lost (NaN) over all runs."""
    at = mf.topic_steps(topic)
    times = mf.times()[at]
    span = float(times[-1] - times[0]) if len(times) > 1 else 0.0
    rate = f"{(len(times) - 1) / span:.4g} Hz" if span > 0 else "one instant"
    share = mf.lost_share(topic)
    return f"measures at {at.sum()} of {len(at)} instants ({rate}), {100 * share:.1f} % lost"


def describe(file: Path) -> Iterator[str]:
    """The lines `fusionlog inspect FILE` prints."""
    mf = McapFile(file)
    sc = mf.metadata.get("fusionlog.scenario", {})
    prov = mf.metadata.get("fusionlog.provenance", {})
    yield f"{file}"
    if sc:
        yield f"  scenario: {sc.get('name')} (seed {sc.get('seed')})"
    if prov:
        version = prov.get("fusionlog_version", "?")
        yield f"  written by: {prov.get('command', '?')} (fusionlog {version})"
    ours = [t for t in mf.topics if mf.kind_of(t) is not None]
    if ours:
        yield f"  runs: {mf.runs()}, instants: {mf.steps()} (k = 0..{mf.steps() - 1})"
    else:
        yield "  no fusionlog topics (no fusionlog.Block or fusionlog.EstimateBlock streams)"
    foreign = {}
    if len(ours) < len(mf.topics):  # any MCAP's topics: encoding and rate from its indexes
        from fusionlog.io.replay import list_topics

        foreign = {t: (enc, rate) for t, _, enc, _, rate in list_topics(file)}
    for t in sorted(mf.topics):
        if t in ours:
            kind = f"dim {mf.dim_of(t)}"
        else:
            enc, rate = foreign.get(t, ("?", None))
            hz = f", {rate:.4g} Hz" if rate else ""
            kind = f"not a fusionlog stream ({enc}{hz}; replay it with a replay file)"
        yield f"  {t:32s} {mf.topics[t]:8d} messages  {mf.schema_of(t)}  {kind}"
        if t.startswith(SENSORS_PREFIX) and t in ours:
            yield f"  {'':32s} {sensor_timing(mf, t)}"
    yield f"  metadata: {', '.join(sorted(mf.metadata)) or 'none'}"


def describe_damaged(file: Path) -> Iterator[str]:
    """The lines `fusionlog inspect --recover FILE` prints: what is readable."""
    info = recover_file(file)
    yield f"{file}: {'damaged: ' + str(info['error']) if info['error'] else 'intact'}"
    for t, c in sorted(info["topics"].items()):
        yield f"  {t:32s} {c:8d} messages readable"
    yield (
        f"  complete runs: {info['complete_runs']}, "
        f"last complete step: {info['last_complete_step']}"
    )
    yield f"  metadata: {', '.join(sorted(info['metadata'])) or 'none'}"
