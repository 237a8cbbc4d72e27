"""What the believed noise costs: the exact analysis (`core.exact`) with the identified values
as the truth, against the file's values (given) and the identified ones (tuned) as the
filters' model, per architecture; and the whiteness of the tuned filter's innovations.

The cost is conditional on the log's own pattern of readings (its instants, rates and lost
readings): each block of runs is analysed with the plans of its pattern (shared, or per run
on history nodes) and the run averages are those the Monte Carlo metrics would estimate
(`core.exact.ConditionalExpected`); the overall MSE (eq. 45) and ANEES are their means over
the instants (`montecarlo.expected_overall`), as in summary.json's `expected`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fusionlog.core.names import check_architectures
from fusionlog.core.nis import innovations, ljung_box
from fusionlog.driver import PlanCache, conditional_sums
from fusionlog.scenario import Scenario

from .montecarlo import expected_overall
from .simulation import Simulation, blocks_of, estimate_blocks

__all__ = ["cost_of", "format_identification", "whiteness_of"]


def cost_of(
    given: Scenario, tuned: Scenario, sim: Simulation
) -> dict[str, dict[str, float | None] | None]:
    """{arch: {"mse_given", "mse_tuned", "anees_given", "anees_tuned"}} for the scenario's
    architectures; None for each where no exact analysis exists (a nonlinear model)."""
    where = f"{given.path or given.name}: architectures"
    archs = check_architectures(list(given.architectures), given.system, where)
    truth = sim.on_instants(tuned.system)
    if not truth.linear:
        return dict.fromkeys(archs)
    K = len(sim.times) - 1
    models = {"given": sim.on_instants(given.system), "tuned": truth}
    z = sim.stacked(truth)
    sums: dict[str, dict[str, Any]] = {w: {} for w in models}
    for w, system in models.items():
        cache = PlanCache(system, K)
        for off, n in blocks_of(sim):
            plans, _ = cache.block_plans(archs, z[off : off + n])
            for a, acc in conditional_sums(plans, truth, n).items():
                if a in sums[w]:
                    sums[w][a].merge(acc)
                else:
                    sums[w][a] = acc
    out: dict[str, dict[str, float | None] | None] = {}
    for a in archs:
        g, t = (expected_overall(sums[w][a]) for w in ("given", "tuned"))
        out[a] = {
            "mse_given": g["mse"],
            "mse_tuned": t["mse"],
            "anees_given": g["anees"],
            "anees_tuned": t["anees"],
        }
    return out


def whiteness_of(tuned: Scenario, sim: Simulation) -> dict[str, dict[str, Any]]:
    """Per sensor, the Ljung-Box test (`core.nis.ljung_box`) of the tuned CKF's normalised
    innovations of that sensor's readings (empty for a nonlinear model)."""
    system = sim.on_instants(tuned.system)
    if not system.linear:
        return {}
    blocks = estimate_blocks(tuned.system, sim, ["CKF"])[0]["CKF"]
    z = sim.stacked(system)
    out = {}
    for s, sl in zip(system.sensors, system.sensor_slices, strict=True):
        rows = np.arange(system.m)[sl]
        normalised = [
            innovations(system, est.mean, est.cov, z[off : off + n], rows).normalised
            for (off, n), est in zip(blocks_of(sim), blocks, strict=True)
        ]
        out[s.name] = ljung_box(np.concatenate(normalised))
    return out


def _num(v: Any) -> str:
    if v is None:
        return "-"
    if isinstance(v, list):
        return "[" + ", ".join(_num(e) for e in v) + "]"
    return f"{v:.6g}"


def format_identification(ident: Any) -> str:
    """The printed summary: each parameter's value, standard error and the file's value, the
    log-likelihoods, the cost table and the whiteness of the tuned filter's innovations."""
    how = "exact (linear model)" if ident.exact else "the EKF's approximation (nonlinear model)"
    truth = " and the truth" if ident.with_truth else ""
    lines = [
        f"maximum likelihood of the readings{truth}: {how}, {ident.observations} values, "
        f"{ident.iterations} iterations",
        f"log-likelihood {ident.loglik:.6g} (file's values: {ident.loglik_given:.6g})",
        "",
    ]
    width = max(len(k) for k in ident.keys)
    for k in ident.keys:
        lines.append(
            f"  {k:<{width}}  {_num(ident.values[k])}  +- {_num(ident.stderr[k])}  "
            f"(given {_num(ident.given[k])})"
        )
    if ident.cost:
        lines += ["", "cost of the given values (exact analysis, the identified values as truth):"]
        lines.append(f"  {'arch':<10}{'MSE given':>12}{'MSE tuned':>12}"
                     f"{'ANEES given':>13}{'ANEES tuned':>13}")  # fmt: skip
        for a, c in ident.cost.items():
            if c is None:
                lines.append(f"  {a:<10}{'(no exact analysis: nonlinear model)':>50}")
                continue
            lines.append(
                f"  {a:<10}{_num(c['mse_given']):>12}{_num(c['mse_tuned']):>12}"
                f"{_num(c['anees_given']):>13}{_num(c['anees_tuned']):>13}"
            )
    if ident.whiteness:
        lines += ["", "whiteness of the tuned CKF's normalised innovations (Ljung-Box):"]
        for name, w in ident.whiteness.items():
            lines.append(
                f"  {name}: lag {w['lags']}, Q = {_num(w['q'])} on {w['dof']} dof, "
                f"p = {_num(w['p'])}" + ("  (not white)" if w["p"] < 0.01 else "")
            )
    return "\n".join(lines)
