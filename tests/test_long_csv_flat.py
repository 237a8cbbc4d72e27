"""The evaluation of a long irregular CSV replay holds, while its blocks of time are evaluated,
no more of the log than the instants' times (issue 34: the 10^6-row irregular replay's `run`
peak grew by ~60 bytes an instant to 4*10^6 rows, set by the evaluate stage).

What it held besides a block, per instant, before: the instants' times twice (the sensors and
the estimates file each their own, 8 bytes each), the estimates' measurement mask as its
provenance text (3m + 2 bytes: 8 here) and parsed (m bytes), and each sensor's scheduled
instants (1 byte each): 30.5 bytes an instant of two sensors between 1.5*10^5 and 10^6
instants; now one array of times, the parsed mask and a bit per sensor, 12.4. Measured here
with tracemalloc (Python and numpy allocations) while the blocks come: the traced memory when
each block of estimates is handed over (`McapFile.iter_time_blocks`), its median over the
blocks, at two lengths of the same log, the smaller within the layout record's lists (65 536
instants), the larger past them (times from the scan, which over-allocates as it grows). Its
growth per added instant: 37.3 bytes on main (`2afb56b`), 19.2 now; bound 28, between the two.
The log: 5 ms +- 40 % intervals, each sensor's reading missing at 5 % of the rows, the truth
of the position only, CKF and FBS (its backward pass spooled), in blocks of 1024 instants;
both lengths past the recording's decimation (30 000 instants), so its series are a fixed
number of buckets. ~50 s of CPU.
"""

import statistics
import tracemalloc

import pytest
from long_helpers import csv_replay_toml, irregular_csv_replay

from fusionlog.io.mcap import McapFile
from fusionlog.stages.evaluate import run_evaluate
from fusionlog.stages.run import run_pipeline

BLOCK = 1024

_REPLAY = csv_replay_toml("long_csv_flat", '[estimate]\narchitectures = ["CKF", "FBS"]\n')


def _replay(folder, rows: int):
    return irregular_csv_replay(folder, rows, _REPLAY)


def _held_while_blocks(folder, monkeypatch) -> float:
    """The median over the blocks of tracemalloc's traced memory as each block of the
    estimates is handed to the evaluation, over what was traced before it started."""
    seen: list[int] = []
    read = McapFile.iter_time_blocks

    def spied(self, *args, **kwargs):
        for item in read(self, *args, **kwargs):
            if self.path.name == "estimates.mcap":
                seen.append(tracemalloc.get_traced_memory()[0])
            yield item

    monkeypatch.setattr(McapFile, "iter_time_blocks", spied)
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        run_evaluate(folder / "sensors.mcap", folder / "estimates.mcap", folder / "e.rrd",
                     summary_path=folder / "s.json", force=True)  # fmt: skip
    finally:
        tracemalloc.stop()
        monkeypatch.setattr(McapFile, "iter_time_blocks", read)
    return statistics.median(seen) - base


@pytest.mark.memory
def test_what_a_long_replay_s_evaluation_holds_does_not_grow_with_its_instants(
    tmp_path, monkeypatch
):
    monkeypatch.setenv("FUSIONLOG_TIME_BLOCK", str(BLOCK))
    small, large = 32 * BLOCK, 96 * BLOCK
    held = {}
    for rows in (small, large):
        folder = tmp_path / str(rows)
        folder.mkdir()
        sc = _replay(folder, rows)
        res = run_pipeline(sc, folder, archs=list(sc.architectures), force=True)
        assert res.summary["architectures"]["FBS"]["expected"] is not None  # exact, in blocks
        if rows == small:  # modules and caches loaded before measuring
            _held_while_blocks(folder, monkeypatch)
        held[rows] = _held_while_blocks(folder, monkeypatch)
    K_small = McapFile(tmp_path / str(small) / "sensors.mcap").steps()
    K_large = McapFile(tmp_path / str(large) / "sensors.mcap").steps()
    per_instant = (held[large] - held[small]) / (K_large - K_small)
    assert per_instant < 28, f"{per_instant:.1f} bytes held per added instant ({held})"
