"""Extreme but accepted numbers: every architecture either stays finite or raises NumericalError.

Scenarios are built through the public loader (`scenario_from_text`), so what is tested is what a
user can write. For each, every architecture is compiled (shared plan, and per run with gaps),
applied to simulated measurements and analysed exactly. The contract (issue 12): finite numbers
wherever an estimate is defined, or `fusionlog.errors.NumericalError` with one line naming the
architecture -- never numpy's LinAlgError, an OverflowError or a FloatingPointError.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from fusionlog.core.architectures import STATE_ARCHITECTURES, build_plan, run_plan
from fusionlog.core.exact import analyse
from fusionlog.core.simulate import simulate
from fusionlog.errors import NumericalError, ValidationError
from fusionlog.scenario import scenario_from_text

K, M = 10, 4
CV = 'kind = "constant-velocity"\nn0 = {n0}'


def scenario(
    R: tuple[str, ...] = ("1.0", "1.0", "1.0"),
    *,
    n0: str = "0.16",
    model: str | None = None,
    prior: bool = True,
    cov: str = "[[1.0, 0.0], [0.0, 1.0]]",
    mean: str = "[100.0, -1.0]",
    H: str = "[[1.0, 0.0]]",
    extra: str = "",
) -> str:
    """The paper's example (constant velocity, position sensors) with some numbers changed."""
    start = "[prior]\nmean = {m}\ncov = {c}\n" if prior else "[truth]\ninitial_mean = {m}\n"
    start = start.format(m=mean, c=cov) + ("" if prior else f"initial_cov = {cov}\n")
    sensors = "".join(f'[[sensors]]\nname = "s{j}"\nH = {H}\nR = {r}\n\n' for j, r in enumerate(R))
    return (
        f'[scenario]\nname = "extreme"\nsteps = {K}\nruns = {M}\nseed = 1\ndt = 1.0\n\n'
        f"[model]\n{model or CV.format(n0=n0)}\n\n{start}\n{sensors}{extra}"
    )


EXPLICIT = "F = {F}\nQ = {Q}"
Q01 = "[[0.1, 0.0], [0.0, 0.1]]"
#: Cases whose filters are expected to stay finite (a tolerance question, not an overflow).
FINITE = {
    "R=1e-16": scenario(("1e-16",) * 3),
    "R=1e-300": scenario(("1e-300",) * 3),
    "R=1e-300 beside 1 and 1e8": scenario(("1e-300", "1.0", "1e8")),
    "n0=1e200": scenario(n0="1e200"),
    "R=1e-16 without a prior": scenario(("1e-16",) * 3, prior=False),
    "correlated R=1e-16": scenario(
        ("1e-16", "1e-16", "1.0"), extra='[[correlations]]\nsensors = ["s0", "s1"]\ncov = 0.9e-16\n'
    ),
}
#: Cases that may end in NumericalError (numbers beyond the float range somewhere).
ANY = {
    "Q=1e308": scenario(model=EXPLICIT.format(F="[[1, 1], [0, 1]]", Q="[[1e308, 0], [0, 1e308]]")),
    "F=1e308": scenario(model=EXPLICIT.format(F="[[1e308, 1.0], [0.0, 1.0]]", Q=Q01)),
    "F=1e154": scenario(model=EXPLICIT.format(F="[[1e154, 1.0], [0.0, 1.0]]", Q=Q01)),
    "F=1e100": scenario(model=EXPLICIT.format(F="[[1e100, 1.0], [0.0, 1.0]]", Q=Q01)),
    "prior cov=1e308": scenario(cov="[[1e308, 0.0], [0.0, 1e308]]"),
    "prior cov=1e300": scenario(cov="[[1e300, 0.0], [0.0, 1e300]]"),
    "prior cov=1e300 without a prior": scenario(cov="[[1e300, 0.0], [0.0, 1e300]]", prior=False),
    "R=1e-308": scenario(("1e-308",) * 3),
    "R=5e-324": scenario(("5e-324", "1.0", "1.0")),
    "R=1e-300 without a prior": scenario(("1e-300",) * 3, prior=False),
    "n0=1e300": scenario(n0="1e300"),
    "mean=1e300": scenario(mean="[1e300, -1e300]"),
    "H=1e150": scenario(H="[[1e150, 0.0]]"),
    "H=1e-150 without a prior": scenario(H="[[1e-150, 0.0]]", prior=False),
}  # fmt: skip


def _measurements(system) -> np.ndarray:
    """Simulated measurements, or zeros where the simulation itself overflows (which it must
    report as NumericalError): the filters are tested on data either way."""
    try:
        _, z = simulate(system, K, 1, 0, M)
    except NumericalError as e:
        assert "\n" not in str(e) and "simulation" in str(e)
        return np.zeros((M, K + 1, system.m))
    assert np.isfinite(z).all()
    return z


def _outcomes(text: str, name: str) -> dict[tuple[str, str], str]:
    """For every architecture and path: "finite", or the NumericalError's message."""
    try:
        sc = scenario_from_text(text, name)
    except ValidationError:
        pytest.skip("refused when loaded: nothing reaches the filters")
    system = sc.system
    z = _measurements(system)
    gaps = z.copy()
    gaps[1, 2, 0] = np.nan
    gaps[2, 3:5, 1] = np.nan
    out = {}
    for arch in STATE_ARCHITECTURES:
        for path, data in (("shared", z), ("per run", gaps)):
            present = None if path == "shared" else ~np.isnan(data)
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("error")  # no overflow warnings on the way either
                    plan = build_plan(system, arch, K, present)
                    est = run_plan(plan, data)
                    cov = np.broadcast_to(est.cov, (M, K + 1, 2, 2))
                    defined = np.isfinite(cov).all(axis=(-2, -1))
                    assert np.isfinite(est.mean[defined]).all(), (arch, path)
                    assert defined[:, 2:].all(), (arch, path, "no estimate where one exists")
                    if path == "shared":
                        ex = analyse(plan, system)
                        for a in (ex.mse, ex.nees, ex.dm):
                            assert np.isfinite(a[defined[0]]).all(), (arch, "exact analysis")
                        # Jensen: E sqrt(q) <= sqrt(E q), whatever the scale of P
                        dm, nees = ex.dm[defined[0]], ex.nees[defined[0]]
                        assert np.all(dm <= np.sqrt(nees) * (1 + 1e-6)), (arch, dm, nees)
                out[arch, path] = "finite"
            except NumericalError as e:
                msg = str(e)
                assert "\n" not in msg and msg.startswith(f"architecture {arch}"), msg
                out[arch, path] = msg
    return out


@pytest.mark.parametrize("name", list(FINITE))
def test_badly_scaled_models_stay_finite(name: str) -> None:
    """Tiny measurement noise against the process noise (the LinAlgError of issue 12 in CKF and
    FBS), huge process noise: singular solves fall back to the pseudo-inverse, badly scaled
    inverses go through their Jacobi scaling, and every architecture gives finite numbers."""
    bad = {k: v for k, v in _outcomes(FINITE[name], name).items() if v != "finite"}
    assert not bad


@pytest.mark.parametrize("name", list(ANY))
def test_overflowing_models_are_finite_or_one_numerical_error(name: str) -> None:
    _outcomes(ANY[name], name)  # the assertions are inside: finite, or NumericalError


def test_overflow_names_the_architecture_the_step_and_the_matrix() -> None:
    """F = 1e100 on a state whose first component is not measured: its variance is 1e200 after
    one prediction and beyond the float range after the second."""
    model = EXPLICIT.format(F="[[1e100, 1], [0, 1]]", Q=Q01)
    sc = scenario_from_text(scenario(model=model, H="[[0.0, 1.0]]"), "f")
    for arch in ("CKF", "HKF", "MSC-GMF", "FBS"):
        with pytest.raises(NumericalError) as e:
            build_plan(sc.system, arch, K)
        assert str(e.value).startswith(f"architecture {arch}, step 2: the "), str(e.value)
        assert "covariance" in str(e.value) and "overflows" in str(e.value)
    with pytest.raises(NumericalError, match="simulation: the true state overflows at step 4"):
        simulate(sc.system, K, 1, 0, M)


def test_r_1e16_gives_the_noise_free_limit() -> None:
    """Three identical sensors with R = 1e-16: the innovation covariance is singular to working
    precision, and the pseudo-inverse gain is the noise-free limit: the position is the average
    of the three measurements, its variance R / 3."""
    sc = scenario_from_text(scenario(("1e-16",) * 3), "r.toml")
    _, z = simulate(sc.system, K, 1, 0, M)
    for arch in ("CKF", "FBS", "MSC-GMF"):
        est = run_plan(build_plan(sc.system, arch, K), z)
        np.testing.assert_allclose(est.mean[:, :, 0], z.mean(axis=2), rtol=0, atol=1e-6)
        assert np.all(est.cov[:, 0, 0] < 1e-15)
