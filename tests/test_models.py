"""Model components (`fusionlog.core.models`): the protocol a sensor and a motion model give the
estimators, the registries, and the one place a linear-only computation refuses a nonlinear one."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import pytest

from fusionlog.core.architectures import build_plan
from fusionlog.core.model import System, ajgl2009, constant_velocity
from fusionlog.core.models import (
    MOTION_KINDS,
    SENSOR_KINDS,
    LinearMotion,
    LinearSensor,
    NotLinear,
    SensorModel,
)
from fusionlog.core.simulate import simulate
from fusionlog.core.timing import SensorTiming, van_loan
from fusionlog.errors import FusionlogError
from fusionlog.scenario import load_scenario


@dataclass(frozen=True)
class _Range(SensorModel):
    """A range sensor at the origin of a [p, v] state (not registered: a test double)."""

    kind = "test-range"
    name: str
    R: np.ndarray
    timing: SensorTiming = SensorTiming()

    def h(self, x: np.ndarray) -> np.ndarray:
        return np.abs(x[..., :1])

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        J = np.zeros(x.shape[:-1] + (1, x.shape[-1]))
        J[..., 0, 0] = np.sign(x[..., 0])
        return J


def test_linear_kinds_are_registered() -> None:
    assert SENSOR_KINDS["linear"] is LinearSensor
    assert MOTION_KINDS["linear"] is LinearMotion


def test_linear_sensor_protocol() -> None:
    rng = np.random.default_rng(1)
    H = rng.standard_normal((2, 3))
    s = LinearSensor("a", H, np.eye(2))
    x = rng.standard_normal((4, 5, 3))
    # a 3-term dot product: rounding within 3 eps of sum |H_ij x_j|
    bound = 3 * np.finfo(float).eps * np.einsum("ij,mkj->mki", np.abs(H), np.abs(x))
    assert (np.abs(s.h(x) - np.einsum("ij,mkj->mki", H, x)) <= bound).all()
    assert s.jacobian(x).shape == (4, 5, 2, 3)
    np.testing.assert_array_equal(s.jacobian(x)[1, 2], H)
    assert s.linear and s.dim == 2


def test_linear_motion_discretises_its_continuous_model() -> None:
    dt, n0 = 0.5, 0.3
    F, Q = constant_velocity(dt, n0)
    A = np.array([[0.0, 1.0], [0.0, 0.0]])
    Qc = np.array([[0.0, 0.0], [0.0, n0]])
    mo = LinearMotion(F, Q, dt, (A, Qc))
    assert mo.F(dt) is F and mo.Q(dt) is Q  # its own interval: the matrices as given
    F2, Q2 = constant_velocity(1.25, n0)  # the closed form, an independent reference
    np.testing.assert_allclose(mo.F(1.25), F2, rtol=1e-13)
    np.testing.assert_allclose(mo.Q(1.25), Q2, rtol=1e-12)
    Fv, _ = van_loan(A, Qc, np.array([1.25]))
    x = np.array([[1.0, 2.0]])
    np.testing.assert_allclose(mo.f(x, 1.25), x @ Fv[0].T, rtol=1e-14)
    with pytest.raises(ValueError, match="no transition"):
        LinearMotion(F, Q, dt).F(1.0)


def test_system_asks_its_models() -> None:
    system = ajgl2009()
    assert system.linear
    np.testing.assert_array_equal(system.linear_measurement(), [[1.0, 0.0]] * 3)
    assert system.motion.F(system.dt) is system.F
    x = np.array([[3.0, 1.0], [-2.0, 0.5]])
    np.testing.assert_array_equal(system.h(x), np.repeat(x[:, :1], 3, axis=1))
    assert system.jacobian(x).shape == (2, 3, 2)


def test_a_nonlinear_sensor_is_simulated_and_refused_by_the_plans() -> None:
    base = ajgl2009()
    rng_sensor = _Range("r", np.array([[0.25]]))
    system: System = dataclasses.replace(base, sensors=(*base.sensors[:1], rng_sensor))
    assert not system.linear
    x, z = simulate(system, 4, seed=3, run_offset=0, runs=2)
    assert z.shape == (2, 5, 2) and np.isfinite(z).all()
    with pytest.raises(NotLinear, match=r"sensor r \(test-range\) is nonlinear"):
        build_plan(system, "CKF", 4)
    assert issubclass(NotLinear, FusionlogError)


@dataclass(frozen=True)
class _Bearing(_Range):
    """A bearing-like test double whose residual wraps to (-pi, pi]."""

    kind = "test-bearing"

    def residual(self, z: np.ndarray, z_hat: np.ndarray) -> np.ndarray:
        return np.pi - np.mod(np.pi - (z - z_hat), 2 * np.pi)


def test_the_system_asks_each_sensor_for_its_residual() -> None:
    base = ajgl2009()
    system = dataclasses.replace(base, sensors=(base.sensors[0], _Bearing("b", np.eye(1))))
    z = np.array([[1.0, np.pi - 0.1]])
    z_hat = np.array([[0.25, -np.pi + 0.1]])
    np.testing.assert_allclose(system.residual(z, z_hat), [[0.75, -0.2]], rtol=1e-12)
    np.testing.assert_array_equal(base.residual(z[:, :1], z_hat[:, :1]), [[0.75]])


def test_unknown_sensor_kind_is_one_line(tmp_path) -> None:
    src = tmp_path / "s.toml"
    src.write_text(
        '[scenario]\nname = "k"\nsteps = 2\nruns = 2\nseed = 1\ndt = 1.0\n'
        '[model]\nkind = "constant-velocity"\nn0 = 0.1\n'
        "[prior]\nmean = [0.0, 0.0]\ncov = [[1.0, 0.0], [0.0, 1.0]]\n"
        '[[sensors]]\nname = "a"\nkind = "sonar"\nH = [1.0, 0.0]\nR = 1.0\n'
    )
    with pytest.raises(FusionlogError, match=r"sensors\[0\]\.kind: unknown sensor kind 'sonar'"):
        load_scenario(src)
