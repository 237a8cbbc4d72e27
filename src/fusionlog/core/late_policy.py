"""Late measurements, what the policies decide before any plan: which sensors are late, the
policies, what each architecture and model takes or refuses (one line, why), when each
measurement arrives, and neglect's rule of which measurements are taken (DESIGN.md "Late
measurements"). Apart from `core.latency`'s plans so that the EKF/UKF lanes, which never build
a plan, need nothing of the plans' package."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from .latency_corr import correlated_refusal
from .model import System

__all__ = [
    "BUILT_POLICIES",
    "DELAY_STREAM",
    "LATE_POLICIES",
    "SINGLE_FILTER",
    "accept_at",
    "accepted",
    "arrival_steps",
    "arrival_blocks",
    "draw_arrivals",
    "ekf_retrodict_refusal",
    "is_late",
    "late_refusal",
    "nonlinear_refusal",
    "random_delays",
    "system_refusal",
]

#: [estimate] late: the first is the default.
LATE_POLICIES = ("reprocess", "retrodict", "neglect")

#: Policies whose plans exist.
BUILT_POLICIES = ("reprocess", "neglect", "retrodict")


def is_late(system: System) -> bool:
    """Whether some sensor's measurements arrive after they are taken."""
    return any(s.timing.late for s in system.sensors)


def random_delays(system: System) -> bool:
    """Whether some sensor's delays are drawn per measurement (a latency range): the runs then
    differ in what arrives when, like dropouts in what is measured."""
    return any(s.timing.latency[0] != s.timing.latency[1] for s in system.sensors)


def system_refusal(system: System) -> tuple[str, str] | None:
    """(key, reason) why a system's late sensors cannot be estimated, or None."""
    if not is_late(system):
        return None
    if system.late not in BUILT_POLICIES:
        return ("estimate.late", f"{system.late!r} with late sensors is not available yet")
    if not system.linear:
        return nonlinear_refusal(system)
    if system.prior is None:
        return (
            "prior",
            "missing: reprocessing late measurements runs the filter on the state stacked "
            "over the latency window, which starts from [prior] (mean, cov)",
        )
    if system.late == "retrodict":
        Fs = [system.F] if system.Fs is None else list(system.Fs)
        if not all(abs(np.linalg.det(F)) >= 1e-300 for F in Fs):
            return (
                "estimate.late",
                "retrodict predicts backwards through F^-1, and F is singular",
            )
    return None


def nonlinear_refusal(system: System) -> tuple[str, str] | None:
    """(key, reason) why the EKF/UKF lanes cannot take a system's late sensors
    (`core.nonlinear.late`), or None."""
    if system.late == "retrodict" and system.filter == "UKF":
        return (
            "estimate.late",
            "retrodict needs the EKF: Al1 linearises the motion and the sensors at the "
            "retrodicted state, which the UKF never samples (its sigma points are drawn about "
            'the forward predictions); use reprocess or neglect, or filter = "EKF"',
        )
    return None


def late_refusal(system: System, locals_kind: str, arch: str) -> str | None:
    """Why architecture `arch` (its `Architecture.locals`) has no meaning or no plan with the
    system's late sensors, or None."""
    if not is_late(system):
        return None
    if locals_kind == "smoother":
        return (
            f"architecture {arch}: a fixed-interval smoother uses every measurement of the run "
            "whenever it arrives: a latency has no meaning there"
        )
    # The linear plans retrodict in every filter (`core.retrodict_fused`); the EKF lanes
    # (`core.nonlinear.retrodict`) in every filter too, but carry no joint covariance there.
    if system.late == "retrodict" and not system.linear and locals_kind == "per-sensor":
        # imported here: the registry's package imports the lanes, which import this module
        from .architectures.registry import definition

        return ekf_retrodict_refusal(arch, definition(arch).joint)
    return correlated_refusal(system, locals_kind, arch)


def ekf_retrodict_refusal(arch: str, joint: bool) -> str | None:
    """Why the EKF lanes' retrodicting locals cannot feed track-to-track rule `arch` (`joint`:
    it reads the locals' joint error covariance), or None."""
    if not joint:
        return None
    return (
        f"architecture {arch}: retrodict with EKF locals gives no joint error covariance for "
        "its rule (Al1 correlates each local with the process noise since its stored estimate, "
        "which the lanes do not carry); use reprocess or neglect, or MSC, CI, ICI or EI"
    )


#: The architectures that run one filter on their sensors.
SINGLE_FILTER = ("centralised", "single")


#: The delays' random stream (`core.simulate.chunked`): apart from the truth and readings'.
DELAY_STREAM = (30,)


def draw_arrivals(
    system: System, times: np.ndarray, seed: int, run_offset: int, runs: int
) -> np.ndarray | None:
    """When each measurement of runs [run_offset, +runs) arrives, (runs, K+1, S) seconds: t_i
    + latency, a delay uniform in [min, max] drawn from the seed where the sensor's latency
    is a range (runs independent of the caller's blocks); None when every sensor is on time."""
    if not is_late(system):
        return None
    from .simulate import chunked

    lat = np.array([s.timing.latency for s in system.sensors])  # (S, 2)
    K1 = len(times)
    out = np.repeat((times[:, None] + lat[None, :, 0])[None], runs, axis=0)
    rand = lat[:, 1] > lat[:, 0]
    if rand.any():

        def draw(rng: np.random.Generator, size: int) -> tuple[np.ndarray]:
            return (rng.random((size, K1, int(rand.sum()))),)

        (u,) = chunked(draw, K1 - 1, seed, run_offset, runs, stream=DELAY_STREAM)
        out[..., rand] += u * (lat[rand, 1] - lat[rand, 0])
    return out


def arrival_blocks(
    system: System, times: np.ndarray, seed: int, block: int
) -> Iterator[np.ndarray] | None:
    """`draw_arrivals` of run 0 in blocks of `block` instants, (w, S) s each, in order (issue
    34: a long log's delays never held whole); None where no delay is drawn. Run 0's uniforms
    are the first of its chunk's draw (C order), and a generator draws its doubles one after
    the other, so drawing them block by block from the same stream gives the same numbers."""
    lat = np.array([s.timing.latency for s in system.sensors])  # (S, 2)
    rand = lat[:, 1] > lat[:, 0]
    if not rand.any():
        return None
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(0, *DELAY_STREAM)))

    def blocks() -> Iterator[np.ndarray]:
        for k0 in range(0, len(times), block):
            out = times[k0 : k0 + block, None] + lat[None, :, 0]
            u = rng.random((len(out), int(rand.sum())))
            out[:, rand] += u * (lat[rand, 1] - lat[rand, 0])
            yield out

    return blocks()


def arrival_steps(times: np.ndarray, arrival: np.ndarray) -> np.ndarray:
    """The first instant index k with t_k >= arrival (seconds; compared in whole nanoseconds,
    the resolution of a log's time); len(times) where a measurement never arrives within the
    horizon (or NaN: none taken)."""
    tk = np.round(np.asarray(times, float) * 1e9)
    a = np.round(np.asarray(arrival, float) * 1e9)
    out = np.searchsorted(tk, np.where(np.isnan(a), np.inf, a), side="left")
    return out.astype(np.intp)


def accepted(took: np.ndarray, arrive: np.ndarray, W: int) -> np.ndarray:
    """Neglect's rule: which measurements (batch + (K+1, S)) the filter takes, in arrival
    order (measurement-time order within an arrival instant): those not older than the
    newest measurement time it has taken before."""
    K1 = took.shape[-2]
    out = np.zeros_like(took)
    newest = np.full(took.shape[:-2], -1, dtype=np.intp)
    for k in range(K1):
        lo = max(0, k - W)
        here = took[..., lo : k + 1, :] & (arrive[..., lo : k + 1, :] == k)
        ok, newest = accept_at(here, np.arange(lo, k + 1), newest)
        out[..., lo : k + 1, :] |= ok
    return out


def accept_at(here: np.ndarray, i: np.ndarray, newest: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Neglect's rule at one arrival instant (`accepted`'s step; the EKF/UKF lanes take it an
    instant at a time, `nonlinear.late_feed`): of the readings `here` (batch + (w, S)), taken
    at the instants i (w,), that arrive now, those not older than the newest measurement time
    the filter has taken (`newest`, batch); and that time after them."""
    ok = here & (i[:, None] >= newest[..., None, None])
    return ok, np.maximum(newest, np.where(ok.any(-1), i, -1).max(-1))
