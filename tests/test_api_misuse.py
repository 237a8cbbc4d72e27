"""Issue 28 part 1: the Python API fails like the CLI. Every misuse a newcomer met is one
`fl.FusionlogError` (here `fl.ValidationError`) whose message names the argument in the API's
words (`runs`, `filter`, `sim.measurements['s1']`, `estimates['CKF'].cov`, never `--runs`),
not a numpy error from deep inside, a silent result, or gigabytes allocated first. Also the
one covariance convention, (M, K+1, n, n), for linear and nonlinear scenarios, and `sim.z`
as data."""

from __future__ import annotations

import dataclasses
import tracemalloc
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

import fusionlog as fl

ROOT = Path(__file__).resolve().parent.parent
SMALL = ROOT / "tests/golden/small.toml"  # three position sensors s1..s3, n = 2


@pytest.fixture(scope="module")
def small():
    sc = fl.load(SMALL)
    sim = fl.simulate(sc, runs=4, seed=1, steps=3)
    return sc, sim, fl.estimate(sc, sim, ["CKF", "MSC"])


def _refused(call: Callable[[], object], *names: str) -> str:
    """The call raises a fl.FusionlogError naming each of `names` on one line, in the API's
    words (no CLI flag); returns the message."""
    with pytest.raises(fl.FusionlogError) as info:
        call()
    msg = str(info.value)
    for name in names:
        assert name in msg, msg
    assert "--" not in msg and "\n" not in msg, msg
    return msg


def _with(sim, **changes):
    return dataclasses.replace(sim, **changes)


def _changed(sim, sensor: str, z) -> object:
    return _with(sim, measurements={**sim.measurements, sensor: z})


# --------------------------------------------------------------------------- the simulation
BAD_SIMULATIONS = {
    # measurements one instant short of sim.times
    "one instant short": (lambda s: _changed(s, "s1", s.measurements["s1"][:, :-1]),
                          ["sim.measurements['s1']", "3 instants", "sim.times has 4"]),
    # an extra column: the sensor measures one value (m = 1)
    "extra column": (lambda s: _changed(s, "s2", np.concatenate([s.measurements["s2"]] * 2, -1)),
                     ["sim.measurements['s2']", "(4, any, 1)", "(4, 4, 2)"]),
    "2-D array": (lambda s: _changed(s, "s1", s.measurements["s1"][0]),
                  ["sim.measurements['s1']", "(4, 1)"]),
    "nested list": (lambda s: _changed(s, "s3", s.measurements["s3"].tolist()),
                    ["sim.measurements['s3']", "numpy array", "list"]),
    "complex values": (lambda s: _changed(s, "s1", s.measurements["s1"] + 0j),
                       ["sim.measurements['s1']", "complex"]),
    "times shortened": (lambda s: _with(s, times=s.times[:-1]), ["sim.times has 3"]),
    "times a list": (lambda s: _with(s, times=list(s.times)), ["sim.times", "numpy array"]),
    "a sensor missing": (lambda s: _with(s, measurements={"s1": s.measurements["s1"]}),
                         ["sim.measurements", "'s2'"]),
    "truth of other runs": (lambda s: _with(s, truth=s.truth[:2]), ["sim.truth", "(2, 4, 2)"]),
}  # fmt: skip


@pytest.mark.parametrize("case", BAD_SIMULATIONS)
@pytest.mark.parametrize("call", ["estimate", "evaluate"])
def test_a_damaged_simulation_is_named(small, case: str, call: str) -> None:
    sc, sim, est = small
    bad = BAD_SIMULATIONS[case][0](sim)
    run = (
        (lambda: fl.estimate(sc, bad))
        if call == "estimate"
        else (lambda: fl.evaluate(sc, bad, est))
    )
    _refused(run, *BAD_SIMULATIONS[case][1])


def test_no_simulation_and_no_scenario_are_named(small) -> None:
    sc, sim, est = small
    _refused(lambda: fl.estimate(sc, None), "sim: expected a Simulation", "NoneType")
    _refused(lambda: fl.evaluate(sc, (sim.truth, sim.measurements), est), "sim:", "tuple")
    _refused(lambda: fl.estimate(None, sim), "scenario: expected a scenario")


# --------------------------------------------------------------------------- the arguments
def test_architectures_must_be_names_and_not_empty(small) -> None:
    sc, sim, _ = small
    _refused(lambda: fl.estimate(sc, sim, [1]), "architectures:", "1 (int)")
    _refused(lambda: fl.estimate(sc, sim, ["CKF", None]), "architectures:", "NoneType")
    # an empty list silently ran the scenario's seven architectures
    for empty in ([], ()):
        _refused(lambda e=empty: fl.estimate(sc, sim, e), "architectures: empty")
    _refused(lambda: fl.estimate(sc, sim, 7), "architectures:", "7 (int)")
    with pytest.raises(fl.FusionlogError, match="^architectures: unknown architecture 'XKF'"):
        fl.estimate(sc, sim, "XKF")


def test_filter_runs_seed_steps_are_named_as_arguments(small) -> None:
    sc, sim, _ = small
    for bad in ("PF", 3):
        with pytest.raises(fl.FusionlogError) as info:
            fl.estimate(sc, sim, ["CKF"], filter=bad)
        assert str(info.value).startswith("filter: unknown filter"), info.value
    _refused(lambda: fl.simulate(sc, runs=1.5), " runs: expected an integer")
    _refused(lambda: fl.simulate(sc, runs=0), " runs: must be >= 1")
    _refused(lambda: fl.simulate(sc, steps=-1), " steps: must be >= 0")
    _refused(lambda: fl.simulate(sc, seed="3"), " seed: expected an integer")


@pytest.mark.memory
def test_runs_beyond_memory_are_refused_before_allocating() -> None:
    """runs=10**8 grew to 3.7 GB and ended in MemoryError: refused by the count, as the CLI
    refuses instants that do not fit, with next to nothing allocated."""
    sc = fl.load(ROOT / "pipeline/ajgl2009.toml")
    tracemalloc.start()
    try:
        msg = _refused(lambda: fl.simulate(sc, runs=10**8), " runs: 100000000 runs", "GiB")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 20 * 2**20, peak  # numpy's allocations are traced: a few MB at most
    assert "fewer runs" in msg


# --------------------------------------------------------------------------- the estimates
def test_evaluate_wants_estimates_not_tuples(small) -> None:
    sc, sim, est = small
    tuples = {a: (e.mean, e.cov) for a, e in est.items()}
    _refused(
        lambda: fl.evaluate(sc, sim, tuples), "estimates['CKF']", "tuple", "fusionlog.estimate"
    )
    _refused(lambda: fl.evaluate(sc, sim, [est["CKF"]]), "estimates:", "list")
    _refused(lambda: fl.evaluate(sc, sim, {"XKF": est["CKF"]}), "estimates:", "'XKF'")
    mean = est["CKF"].mean
    _refused(lambda: fl.evaluate(sc, sim, {"CKF": fl.Estimate(mean[..., :1], est["CKF"].cov)}),
             "estimates['CKF'].mean", "(4, 4, 2)")  # fmt: skip


def _one(est, mean=None, cov=None) -> dict:
    e = est["CKF"]
    return {"CKF": fl.Estimate(e.mean.copy() if mean is None else mean,
                               e.cov[0].copy() if cov is None else cov)}  # fmt: skip


@pytest.mark.parametrize("value", [np.inf, -np.inf])
def test_an_infinite_estimate_is_refused_not_dropped(small, value: float) -> None:
    """+inf in a mean was left out of the MSE as if there were no estimate."""
    sc, sim, est = small
    mean = est["CKF"].mean.copy()
    mean[2, 3, 1] = value
    _refused(lambda: fl.evaluate(sc, sim, _one(est, mean=mean)),
             "estimates['CKF'].mean", "infinite", "run 2, instant 3")  # fmt: skip
    cov = np.array(est["CKF"].cov)  # per run
    cov[1, 2, 0, 0] = np.inf
    _refused(lambda: fl.evaluate(sc, sim, _one(est, cov=cov)),
             "estimates['CKF'].cov", "infinite", "run 1, instant 2")  # fmt: skip


def test_nan_where_an_estimate_must_be_is_refused(small) -> None:
    """NaN marks no estimate in both the mean and the covariance (the filters before a
    prior); NaN in one of them only is neither."""
    sc, sim, est = small
    mean = est["CKF"].mean.copy()
    mean[0, 1, 0] = np.nan
    _refused(lambda: fl.evaluate(sc, sim, _one(est, mean=mean)),
             "estimates['CKF']", "NaN in the mean", "run 0, instant 1")  # fmt: skip
    cov = est["CKF"].cov[0].copy()
    cov[2, 0, 1] = np.nan
    _refused(lambda: fl.evaluate(sc, sim, _one(est, cov=cov)),
             "estimates['CKF']", "NaN in the cov", "instant 2")  # fmt: skip
    mean[:, 1], cov = np.nan, np.array(est["CKF"].cov)
    cov[:, 1] = np.nan  # no estimate at instant 1 in any run: accepted, and left out
    ev = fl.evaluate(sc, sim, _one(est, mean=mean, cov=cov))
    assert ev.summary["architectures"]["CKF"]["excluded"] == 4


def test_a_covariance_that_is_not_positive_semidefinite_is_refused(small) -> None:
    """A negative-definite covariance gave ANEES 1.82 without a word; an indefinite one with
    positive variances ([[1, 2], [2, 1]]: correlation 2) is no covariance either."""
    sc, sim, est = small
    _refused(lambda: fl.evaluate(sc, sim, _one(est, cov=-est["CKF"].cov[0])),
             "estimates['CKF'].cov", "not positive semidefinite", "instant 0")  # fmt: skip
    cov = np.array(est["CKF"].cov)
    cov[3, 2] = [[1.0, 2.0], [2.0, 1.0]]
    _refused(lambda: fl.evaluate(sc, sim, _one(est, cov=cov)),
             "estimates['CKF'].cov", "not positive semidefinite", "run 3, instant 2")  # fmt: skip
    # the test does not depend on the units: 1e-6 m^2 beside 1e6 (m/s)^2, correlation 0.5
    ok = np.array([[1e-6, 0.5], [0.5, 1e6]])
    assert np.linalg.eigvalsh(ok)[0] > 0
    fl.evaluate(sc, sim, _one(est, cov=np.broadcast_to(ok, est["CKF"].cov[0].shape).copy()))


# --------------------------------------------------------------------------- conventions
def test_one_covariance_shape_for_linear_and_nonlinear_scenarios(small) -> None:
    """`.cov` is (M, K+1, n, n) whether the runs share it (linear: one read-only view, no
    memory per run) or not (dropouts, nonlinear): a plot of run 0's variance needs no branch."""
    _, _, est = small
    turn = fl.load(ROOT / "pipeline/coordinated_turn.toml")
    tsim = fl.simulate(turn, runs=3, seed=2, steps=4)
    drop = fl.load(ROOT / "pipeline/ajgl2009_dropout.toml")
    dsim = fl.simulate(drop, runs=3, seed=2, steps=4)
    cases = [(est["CKF"], 4, 4, 2, True), (fl.estimate(turn, tsim, "CKF")["CKF"], 3, 5, 5, False),
             (fl.estimate(drop, dsim, "CKF")["CKF"], 3, 5, 2, False)]  # fmt: skip
    for e, M, K1, n, shared in cases:
        assert e.mean.shape == (M, K1, n) and e.cov.shape == (M, K1, n, n)
        assert e.shared_cov is shared and e.cov.flags.writeable is not shared
        if shared:  # one (K+1, n, n) array seen from every run
            assert e.cov.strides[0] == 0 and all(np.array_equal(c, e.cov[0]) for c in e.cov)
        std = np.sqrt(e.cov[0, :, 0, 0])  # the same code for all three
        assert std.shape == (K1,) and np.isfinite(std).all()
    with pytest.raises(ValueError, match="read-only"):
        est["CKF"].cov[0, 0, 0, 0] = 1.0  # a view shared by every run cannot be written


def test_sim_z_is_data(small) -> None:
    """`sim.z` looked like data but was a method: it is the stacked measurements of eq. (30),
    the scenario's sensors side by side in its order."""
    sc, sim, _ = small
    assert isinstance(type(sim).z, property)
    by_hand = np.concatenate([sim.measurements[s] for s in ("s1", "s2", "s3")], axis=-1)
    np.testing.assert_array_equal(sim.z, by_hand)
    assert sim.z.shape == (4, 4, 3)
