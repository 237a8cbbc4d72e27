"""What a long one-run log holds does not grow with its length (issue 34).

The per-interval F, Q of a model on irregular instants (`System.on_times`, `Fs`, `Qs`) are
formed a stretch at a time when asked for, not for the whole log; a sensors file opened for
reading holds its times (8 bytes per instant) and one bit per instant per sparse topic, not the
layout record's text. Memory is checked with tracemalloc (it sees numpy's buffers) on a log of
K and of 4K instants: what the longer log adds is bounded by what it must hold, whatever the
block of time.
"""

from __future__ import annotations

import dataclasses
import tracemalloc

import numpy as np
import pytest
from mcap_helpers import mcap_writer

from fusionlog.core.model import ajgl2009
from fusionlog.core.timing import constant_velocity_continuous
from fusionlog.io.mcap import VALUES, McapFile
from fusionlog.io.mcap.layout import LISTED
from fusionlog.io.mcap.run_steps import RunColumn

Q_DENSITY = 0.5


def _irregular(K: int, seed: int = 34) -> np.ndarray:
    """K+1 instants 5 ms +- 40 % apart, in whole nanoseconds (a recorded replay's clock)."""
    rng = np.random.default_rng(seed)
    ns = np.cumsum(np.round(5e6 * (1 + 0.4 * rng.uniform(-1, 1, K))))
    return np.r_[0.0, ns / 1e9]


def _system():
    """The paper's two-state constant-velocity model, continuous (A, Qc) for any interval."""
    A, Qc = constant_velocity_continuous(1, Q_DENSITY)
    return dataclasses.replace(ajgl2009(), continuous=(A, Qc))


def test_transitions_by_blocks_are_the_whole_log_s_and_the_closed_form() -> None:
    """F, Q formed for blocks of intervals, one interval at a time or by index arrays are those
    formed for the whole log at once, to the bit; and F = [[1, d], [0, 1]], Q = q [[d^3/3,
    d^2/2], [d^2/2, d]] (eq. 42 in continuous time) to rounding."""
    t = _irregular(3000)
    sy = _system().on_times(t)
    K = len(t) - 1
    F, Q = sy.transitions(0, K)
    for block in (1, 7, 257, 4096):
        parts = [sy.transitions(a, min(a + block, K)) for a in range(0, K, block)]
        assert np.concatenate([p[0] for p in parts]).tobytes() == F.tobytes()
        assert np.concatenate([p[1] for p in parts]).tobytes() == Q.tobytes()
    for k in (1, 2, 1500, K):
        assert sy.F_at(k).tobytes() == F[k - 1].tobytes()
        assert sy.GQG_at(k).tobytes() == Q[k - 1].tobytes()
    picks = np.array([5, 0, 2999, 5])
    assert sy.Qs[picks].tobytes() == Q[picks].tobytes()
    d = np.diff(t)
    one, zero = np.ones_like(d), np.zeros_like(d)
    want_F = np.stack([np.stack([one, d], -1), np.stack([zero, one], -1)], -2)
    want_Q = Q_DENSITY * np.stack(
        [np.stack([d**3 / 3, d**2 / 2], -1), np.stack([d**2 / 2, d], -1)], -2
    )
    np.testing.assert_allclose(F, want_F, rtol=1e-13, atol=0)
    np.testing.assert_allclose(Q, want_Q, rtol=1e-12, atol=0)


def _transitions_peak(K: int, block: int) -> int:
    """tracemalloc's peak while the system is put on K+1 irregular instants and every block
    of intervals' F, Q is formed in turn (a blocked estimate's use), instant 1's F asked too."""
    t = _irregular(K)
    system = _system()
    tracemalloc.start()
    try:
        sy = system.on_times(t)
        for a in range(0, K, block):
            F, Q = sy.transitions(a, min(a + block, K))
            del F, Q
        sy.F_at(1)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


@pytest.mark.memory
@pytest.mark.parametrize("block", [500, 2000])
def test_the_per_interval_transitions_do_not_grow_with_the_log(block: int) -> None:
    """Putting the model on 4K instants instead of K, and walking them block by block, adds
    less than a byte per added instant at the peak (forming them whole held 2 n^2 doubles per
    interval, 64 bytes with two states, and ~4 times that while forming them)."""
    K = 40_000
    _transitions_peak(K, block)  # first call: imports and caches
    short, long = _transitions_peak(K, block), _transitions_peak(4 * K, block)
    assert long - short < 3 * K, (short, long)


def _sparse_log(path, K: int) -> None:
    """A one-run sensors file of K instants on an irregular clock: the truth at every instant,
    sensor a at ~95 % of them, b at every third (the layout record lists their steps and the
    times)."""
    rng = np.random.default_rng(K)
    t = _irregular(K - 1)
    present = np.stack([np.ones(K, bool), rng.random(K) < 0.95, np.arange(K) % 3 == 0], -1)
    cols = [
        RunColumn("/truth", VALUES, rng.normal(size=(K, 2))),
        RunColumn("/sensors/a", VALUES, rng.normal(size=(K, 1))),
        RunColumn("/sensors/b", VALUES, rng.normal(size=(K, 1))),
    ]
    with mcap_writer(path) as w:
        for a in range(0, K, 8192):
            b = min(a + 8192, K)
            w.write_run_steps(a, t[a:b], [c.rows(a, b) for c in cols], present[a:b])


def _held_after_opening(path) -> tuple[int, McapFile]:
    """What an opened sensors file holds once its structure is read (tracemalloc's current
    size, the file object alive)."""
    tracemalloc.start()
    try:
        f = McapFile(path)
        f.times(), f.topic_steps("/sensors/b")
        return tracemalloc.get_traced_memory()[0], f
    finally:
        tracemalloc.stop()


@pytest.mark.memory
@pytest.mark.parametrize("base, K", [(0, 15_000), (LISTED, 30_000)])
def test_an_opened_long_sparse_log_holds_its_times_not_the_layout_record_s_text(tmp_path, base, K):
    """An opened file of 4K instants holds at most its times (8 bytes per instant) and a bit
    per instant for each sparse topic more than one of K: the layout record's lists of steps
    and times (~35 bytes per instant of text) are not kept once parsed; the file reads the
    same (its times, the sparse topics' steps). Past `LISTED` instants the record does not list
    them and the file is scanned: both sizes on each side of it, so that one way of reading
    is compared with itself."""
    held = []
    for size in (base + K, base + 4 * K):
        path = tmp_path / f"s{size}.mcap"
        _sparse_log(path, size)
        got, f = _held_after_opening(path)
        held.append(got)
        assert f.times().tobytes() == _irregular(size - 1).tobytes()
        rng = np.random.default_rng(size)
        a = rng.random(size) < 0.95
        np.testing.assert_array_equal(f.topic_steps("/sensors/a"), a)
        np.testing.assert_array_equal(f.topic_steps("/sensors/b"), np.arange(size) % 3 == 0)
        del f
    # slack: tracemalloc also sees what other threads allocate meanwhile (the whole suite
    # leaves some running); main's growth (~2.9 MB) is still 3x the bound
    assert held[1] - held[0] <= 3 * K * (8 + 2 / 8) + (256 << 10), held
