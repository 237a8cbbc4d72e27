"""The MCAP writer's memory per message on a long one-run log (DESIGN.md, "Bounded memory"):
what it remembers of each message (steps per topic, each step's time) is packed integers and
doubles, not Python objects. Before, a 10^6-instant log of four topics held ~0.5 GB of them
while it was written (`fusionlog simulate --runs 1 --steps 400000`: 355 MB peak, now 142 MB),
its estimates with seven architectures ~0.8 GB. The file is the same either way."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from fusionlog.io.mcap import McapFile, McapWriter

TOPICS = ["/truth", "/sensors/a", "/sensors/b", "/sensors/c"]


def _held_per_message(path, steps: int) -> float:
    """Bytes of Python memory the open writer holds per message once `steps` instants of one
    run are written (before close, which drops the bookkeeping)."""
    values = np.ones((1, 2))
    with open(path, "wb") as f:
        w = McapWriter(f)
        tracemalloc.start()
        try:
            for k in range(steps):
                t = 0.1 * k
                for topic in TOPICS:
                    w.write_values(topic, k, t, 0, values)
            held = tracemalloc.get_traced_memory()[0]
        finally:
            tracemalloc.stop()
        w.close()
    return held / (steps * len(TOPICS))


@pytest.mark.memory
def test_a_long_log_costs_the_writer_a_few_bytes_per_message(tmp_path) -> None:
    # Nothing per message now: a topic's steps are one range, and the instants' times k dt
    # their count and dt (~0.04 byte per message, the writer's fixed state, at 2*10^5
    # messages). It was ~120 bytes, then ~8 (4 per step per topic, 8 per instant for its time).
    assert _held_per_message(tmp_path / "long.mcap", 50_000) < 1


def test_irregular_times_are_kept_in_the_layout(tmp_path) -> None:
    """Times that stop being k dt part-way (and a first time that is not 0) are each kept:
    the file reads back with every instant's time."""
    for times in ([0.0, 0.1, 0.2, 0.30000000000000004, 0.5, 0.6], [0.5, 0.6, 0.7]):
        path = tmp_path / f"{len(times)}.mcap"
        with open(path, "wb") as f, McapWriter(f) as w:
            for k, t in enumerate(times):
                w.write_values("/truth", k, t, 0, np.zeros((1, 1)))
        assert McapFile(path).times().tolist() == times


@pytest.mark.parametrize("order", ["increasing", "decreasing", "shuffled"])
def test_steps_in_any_order_keep_the_layout_and_refuse_repeats(tmp_path, order) -> None:
    """The packed bookkeeping holds steps that come out of order too: the file reads back with
    every instant's time, a sparse topic's steps, and a step written twice is refused."""
    steps = np.arange(40)
    if order == "decreasing":
        steps = steps[::-1]
    elif order == "shuffled":
        steps = np.random.default_rng(3).permutation(40)
    path = tmp_path / f"{order}.mcap"
    with open(path, "wb") as f, McapWriter(f) as w:
        for k in steps.tolist():
            w.write_values("/truth", k, 0.5 * k, 0, np.full((2, 1), k, float))
            if k % 3 == 0:
                w.write_values("/sensors/s", k, 0.5 * k, 0, np.full((2, 1), -k, float))
        with pytest.raises(ValueError, match="written twice"):
            w.write_values("/truth", int(steps[7]), 0.5 * int(steps[7]), 0, np.zeros((2, 1)))
    mf = McapFile(path)
    np.testing.assert_array_equal(mf.times(), 0.5 * np.arange(40))
    assert mf.runs() == 2 and mf.steps() == 40
    got = dict(mf.iter_run_blocks(["/truth", "/sensors/s"], 2).__next__()[2])
    np.testing.assert_array_equal(got["/truth"][0, :, 0], np.arange(40))
    s = got["/sensors/s"][1, :, 0]
    np.testing.assert_array_equal(s[::3], -np.arange(0, 40, 3))
    assert np.isnan(np.delete(s, np.arange(0, 40, 3))).all()
