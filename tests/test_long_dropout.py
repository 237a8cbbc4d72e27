"""Issue 34, the dropout log at 10^6 instants: what of it grows with the instants.

A log with dropouts shares one measurement pattern over its one run, which the estimates'
provenance states as JSON (`measurement_pattern`, DESIGN.md "MCAP files") and the evaluation
reads back for its exact analysis. The text is ~11 bytes per instant of three sensors; writing
it through Python lists and reading it through whole-text temporaries took 49 and 33 bytes
per instant of Python allocations (tracemalloc), the largest thing of the log's length in the
estimate and evaluate stages of a 4*10^6-instant log. Here: the text is json.dumps's (the
reference: the json module on the mask's rows), it reads back to the mask whatever its
spacing, and its writing and reading take at most 2.5 and 1.5 times the text's own size.
"""

from __future__ import annotations

import json
import tracemalloc

import numpy as np
import pytest

from fusionlog.driver import pattern_record
from fusionlog.driver.plans import pattern_mask


def _record(mask: np.ndarray) -> str:
    return pattern_record([np.packbits(mask).tobytes()], mask.shape)["measurement_pattern"]


@pytest.mark.parametrize("shape", [(1, 1), (1, 3), (2, 2), (9, 3), (70_001, 3), (5, 4)])
def test_the_pattern_is_json_of_the_mask_and_reads_back(shape) -> None:
    rng = np.random.default_rng(sum(shape))
    mask = rng.random(shape) < 0.9
    mask[0, 0] = False  # not complete
    text = _record(mask)
    assert text == json.dumps(mask.astype(int).tolist())
    assert np.array_equal(pattern_mask(text), mask)
    # another writer's spacing (one row per line, no spaces): the same mask
    for other in (json.dumps(mask.astype(int).tolist(), indent=1),
                  json.dumps(mask.astype(int).tolist(), separators=(",", ":"))):  # fmt: skip
        assert np.array_equal(pattern_mask(other), mask)


def test_a_complete_pattern_is_named_so() -> None:
    mask = np.ones((5, 3), dtype=bool)
    assert _record(mask) == "complete"


@pytest.mark.memory
def test_writing_and_reading_the_pattern_take_a_few_times_its_text() -> None:
    """tracemalloc's peak of `pattern_record` and of `pattern_mask` on 3*10^5 instants of three
    sensors, against the text's length: the mask (3 bytes an instant), the text and one copy
    (11 each) are what they need; Python lists per row or whole-text temporaries are not."""
    rng = np.random.default_rng(34)
    mask = rng.random((300_001, 3)) < 0.9
    packed = np.packbits(mask).tobytes()
    tracemalloc.start()
    try:
        text = pattern_record([packed], mask.shape)["measurement_pattern"]
        write = tracemalloc.get_traced_memory()[1]
        tracemalloc.reset_peak()
        base = tracemalloc.get_traced_memory()[0]
        got = pattern_mask(text)
        read = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    assert np.array_equal(got, mask)
    assert write <= 2.5 * len(text), (write, len(text))
    assert read <= 1.5 * len(text), (read, len(text))
