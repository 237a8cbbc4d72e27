"""`fusionlog import` holds what a block needs, not the log (issue 34): its peak does not grow
with the rows of a long CSV replay.

The import keeps each stream's messages in an unnamed temporary file (`io/replay/rows.py`) and
writes the sensors file a window of merged instants at a time (`stages/import_windows.py`).
What it holds is a parsed block of the table (8 MB of text and its requested columns), each
stream's buffer of up to 65 536 records and a window of instants (at most two such blocks a
stream) with its messages' columns: none of it grows with the rows. What does grow is the
writer's check that no step is written twice (`io/mcap/bookkeeping.StepSet`, 12 bytes for each
run of consecutive steps of a topic; here each sensor starts a run after each of its missing
readings, ~0.05 a row each: ~1.2 bytes per row); the layout record lists nothing past 65 536
instants (`io/mcap/layout.LISTED`). Bound: 4 bytes per added row. Before: every reading was
held until written, 90.5 bytes per row (62 by the importer's design), and at 133 before that.
The rows are wide (a 130-character column not read: 8 MB of text hold ~50 000 rows), so that
both sizes span several blocks of every kind (4 of text and 3 of records at the smaller) and
the check does not depend on where the blocks end. Measured with tracemalloc (Python and
numpy allocations; pyarrow's pool is not traced, and is a block's) as the peak's growth
between the two sizes, so the constant costs (a block, imports) cancel.
"""

import tracemalloc

import pytest
from long_helpers import csv_replay_toml, irregular_csv_replay

from fusionlog.stages.import_data import run_import

_REPLAY = csv_replay_toml("long_csv")


_PAD = "x" * 130  # a column not read: the rows' width fills the blocks of text


def _replay(folder, rows: int):
    """An irregular log (5 ms +- 40 %), each sensor's reading missing at 5 % of the rows."""
    return irregular_csv_replay(folder, rows, _REPLAY, pad=_PAD)


def _peak(scenario, out) -> int:
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        run_import(scenario, out, force=True)
        return tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()


@pytest.mark.memory
def test_the_import_peak_does_not_grow_with_the_rows(tmp_path):
    small, large = 200_000, 400_000
    peaks = []
    for rows in (small, large):
        folder = tmp_path / str(rows)
        folder.mkdir()
        sc = _replay(folder, rows)
        run_import(sc, folder / "warm.mcap")  # modules and caches loaded before measuring
        peaks.append(_peak(sc, folder / "s.mcap"))
    per_row = (peaks[1] - peaks[0]) / (large - small)
    assert per_row < 4, f"{per_row:.1f} bytes per added row"
