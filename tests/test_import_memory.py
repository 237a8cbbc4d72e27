"""`fusionlog import` holds a bounded number of bytes per row of a long CSV replay (issue 34).

Under the importer's design the whole log's readings are held while the instants are formed and
written (each sensor's readings and their instant index, the truth on the instants, the instants'
times), never a copy of each at once: for this log (two 1-value sensors at ~95 % of the rows, a
1-value truth on a 2-state model) that is 8 (instants) + 2 x 0.95 x 16 (index, value) + 24 (the
truth's index and 2 states) ~ 62 bytes per row, plus one transient array of the readings' times to
sort (16) and the writer's own times (8): below 100 bytes per added row. Before this bound the
import held the readings' times, the sorted union, the association's temporaries and the
readings through the writer's layout record at once: 133 bytes per row (2·10^5 to 8·10^5 rows).
Measured with tracemalloc (Python and numpy allocations; pyarrow's pool is not traced, and is a
block's) as the peak's growth between two sizes, so the constant costs (a parsed block, imports)
cancel.
"""

import tracemalloc

import numpy as np

from fusionlog.scenario import load_scenario
from fusionlog.stages.import_data import run_import

_REPLAY = (
    """[scenario]
name = "long_csv"
state_names = ["p", "v"]
[model]
kind = "constant-velocity"
n0 = 0.5
[prior]
mean = [1.0, 0.0]
cov = [[1.0, 0.0], [0.0, 1.0]]
"""
    + "".join(
        f'[[sensors]]\nname = "{x}"\nsource = "log.csv"\nvalues = ["{x}"]\ntime_unit = "ns"\n'
        "H = [[1.0, 0.0]]\nR = 1.0\n"
        for x in "ab"
    )
    + """[truth]
source = "log.csv"
values = ["p"]
states = ["p"]
time_unit = "ns"
match = "exact"
"""
)


def _replay(folder, rows: int):
    """An irregular log (5 ms +- 40 %), each sensor's reading missing at 5 % of the rows."""
    rng = np.random.default_rng(34)
    t = np.cumsum(np.round(5_000_000 * (1 + 0.4 * rng.uniform(-1, 1, rows)))).astype(np.int64)
    p = 1.0 + np.cumsum(0.01 * np.cumsum(rng.normal(size=rows))) * 0.005
    a, b = p + rng.normal(size=rows), p + rng.normal(size=rows)
    a[rng.random(rows) < 0.05] = np.nan
    b[rng.random(rows) < 0.05] = np.nan
    with open(folder / "log.csv", "w") as f:
        f.write("time,a,b,p\n")
        f.writelines(
            f"{u},{x:.6f},{y:.6f},{z:.9f}\n".replace("nan", "")
            for u, x, y, z in zip(t, a, b, p, strict=True)
        )
    (folder / "replay.toml").write_text(_REPLAY)
    return load_scenario(folder / "replay.toml")


def _peak(scenario, out) -> int:
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        run_import(scenario, out, force=True)
        return tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()


def test_the_import_peak_grows_by_a_bounded_number_of_bytes_per_row(tmp_path):
    small, large = 150_000, 450_000
    peaks = []
    for rows in (small, large):
        folder = tmp_path / str(rows)
        folder.mkdir()
        sc = _replay(folder, rows)
        run_import(sc, folder / "warm.mcap")  # modules and caches loaded before measuring
        peaks.append(_peak(sc, folder / "s.mcap"))
    per_row = (peaks[1] - peaks[0]) / (large - small)
    assert per_row < 100, f"{per_row:.1f} bytes per added row"
