"""Helpers shared by the MCAP layer's tests (test_mcap_*.py): data, writing, reading."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from fusionlog.io.atomic import Outputs
from fusionlog.io.mcap import McapFile, McapWriter


@contextmanager
def mcap_writer(path: Path, *, force: bool = False, **kw) -> Iterator[McapWriter]:
    """A McapWriter on ``path`` the way the stages use one: through Outputs, committed when
    the block ends without an exception."""
    with Outputs([path], force=force) as outs:
        with McapWriter(outs.open(path), **kw) as w:
            yield w
        outs.commit()


def make_data(seed: int, runs: int, steps: int, d: int = 2, n: int = 2, p_nan: float = 0.2):
    """Truth (runs, S, n), one sensor (runs, S, d) with NaN gaps, estimate means (runs, S, n)."""
    rng = np.random.default_rng(seed)
    truth = rng.normal(size=(runs, steps, n))
    sens = rng.normal(size=(runs, steps, d))
    sens[rng.random(size=sens.shape) < p_nan] = np.nan
    mean = rng.normal(size=(runs, steps, n))
    return truth, sens, mean


def write_file(path, truth, sens, mean, covs, write_block, times=None, **kw):
    """Write in the documented order; covs[b] is (S,n,n) shared or (r,S,n,n) per run (a step
    where every run has the same matrix is written shared)."""
    runs, steps = truth.shape[:2]
    times = np.arange(steps) * 0.5 if times is None else times
    with mcap_writer(path, **kw) as w:
        w.add_metadata("fusionlog.scenario", {"name": "t", "toml": "[scenario]\n"})
        w.add_metadata("fusionlog.provenance", {"seed": "1"})
        for b, o in enumerate(range(0, runs, write_block)):
            r = min(write_block, runs - o)
            for k in range(steps):
                w.write_values("/truth", k, times[k], o, truth[o : o + r, k])
                w.write_values("/sensors/a", k, times[k], o, sens[o : o + r, k])
                c = covs[b][k] if covs[b].ndim == 3 else covs[b][:, k]
                if c.ndim == 3 and (c == c[:1]).all():  # the same for every run: write it once
                    c = c[0]
                w.write_estimate("/estimates/CKF", k, times[k], o, mean[o : o + r, k], c)


def concat_blocks(f: McapFile, topics, block_runs):
    got = {t: [] for t in topics}
    offsets = []
    for off, r, data in f.iter_run_blocks(topics, block_runs):
        offsets.append((off, r))
        for t in topics:
            got[t].append(data[t])
    return offsets, got


def sample_file(path: Path, **kw) -> Path:
    """40 runs x 10 steps in blocks of 5, 4 kB chunks: many chunks and blocks."""
    truth, sens, mean = make_data(5, 40, 10)
    covs = [np.eye(2)[None].repeat(10, 0)] * 8
    write_file(path, truth, sens, mean, covs, 5, chunk_size=4096, **kw)
    return path
