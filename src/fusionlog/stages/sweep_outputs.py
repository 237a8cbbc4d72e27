"""What a sweep writes (DESIGN.md, "sweep.parquet"; docs/tutorials/sweeps.md): its
summary.json (the grid, every point as ``fusionlog run`` would summarise it, each
architecture's lowest MSE), the rows of sweep.parquet and their bytes. Pure functions of the
points' results; :mod:`.sweep` runs the tasks and commits the files."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from .grid import GridPoint, Vary
from .montecarlo import Job

__all__ = ["METRIC_COLUMNS", "parquet_bytes", "sweep_summary", "sweep_table"]

#: The parquet columns after the varied keys (DESIGN.md, "sweep.parquet").
METRIC_COLUMNS = (
    "mse",
    "anees",
    "dm",
    "nees_fraction_inside",
    "expected_mse",
    "expected_anees",
    "bound_worst",
)


#: More columns where a point has them: the trajectory metrics' RMSE (DESIGN.md "Trajectory
#: metrics", scenarios with position states).
TRAJECTORY_COLUMNS = ("ape_rmse", "rpe_rmse")


def _point_summary(
    job: Job,
    expected: dict[str, Any],
    sums: dict[str, Any],
    exact_only: bool,
    trajectory: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """A point's architectures as ``fusionlog run``'s summary.json has them (Monte Carlo
    metrics from the merged sums, `expected` from the exact analysis, which has DM too)."""
    out = {}
    for a in job.archs:
        ex = expected.get(a)
        exp = dict(ex) if ex is not None else {"mse": None, "anees": None, "dm": None}
        bound = exp.pop("bound", None)  # its own entry, as in `fusionlog run`'s summary
        if exact_only:
            out[a] = {"expected": exp} | ({"bound": bound} if bound else {})
            continue
        entry = sums[a].finalize(job.scenario.confidence).summary()
        entry["expected"] = exp
        if bound:
            entry["bound"] = bound
        if trajectory and a in trajectory:
            ape, rpe = trajectory[a].summary()
            entry |= {"ape": ape, "rpe": rpe}
        out[a] = entry
    return out


def _bound(scenario: Any) -> dict[str, Any]:
    """A nonlinear point's PCRB ({"pcrb": ...}, `montecarlo.scenario_bound`), else nothing."""
    from .montecarlo import scenario_bound

    bound = scenario_bound(scenario)
    return {} if bound is None else {"pcrb": bound}


def _lowest(points: list[dict[str, Any]]) -> dict[str, Any]:
    """Each architecture's grid point of lowest MSE: the exact value where every point has
    one, else the Monte Carlo one."""
    best: dict[str, Any] = {}
    archs = dict.fromkeys(a for p in points for a in p["architectures"])
    for a in archs:
        have = [p for p in points if a in p["architectures"]]
        exact = all(p["architectures"][a]["expected"]["mse"] is not None for p in have)

        def value(p: dict[str, Any], exact: bool = exact, a: str = a) -> float:
            e = p["architectures"][a]
            v = e["expected"]["mse"] if exact else e.get("mse")
            return float("inf") if v is None or v != v else float(v)

        p = min(have, key=value)
        if value(p) == float("inf"):
            continue
        e = p["architectures"][a]
        best[a] = {
            "by": "expected" if exact else "monte-carlo",
            "point": p["index"],
            "values": p["values"],
            "expected_mse": e["expected"]["mse"],
            "mse": e.get("mse"),
        }
    return best


def sweep_summary(
    varies: Sequence[Vary],
    points: Sequence[GridPoint],
    jobs: Sequence[Job],
    expected: Sequence[dict[str, Any]],
    sums: Sequence[dict[str, Any]],
    exact_only: bool,
    trajectory: Sequence[dict[str, Any]] | None = None,
) -> dict[str, Any]:
    """summary.json of a sweep (docs/reference/summary-json.md, "Sweeps"): the grid, every point as
    ``fusionlog run`` would summarise it, and each architecture's lowest MSE."""
    first = points[0].scenario
    per_point = [
        {
            "index": p.index,
            "values": p.values,
            "seed": p.scenario.seed,
            "runs": 0 if exact_only else p.scenario.runs,
            "steps": p.scenario.instants - 1,
            "architectures": _point_summary(job, e, s, exact_only, tr),
        }
        | _bound(p.scenario)
        for p, job, e, s, tr in zip(
            points, jobs, expected, sums, trajectory or [None] * len(points), strict=True
        )
    ]
    return {
        "kind": "sweep",
        "scenario": first.name,
        "seed": points[0].file_seed,
        "runs": 0 if exact_only else first.runs,
        "steps": first.instants - 1,
        "state_names": list(first.state_names),
        "confidence": first.confidence,
        "exact_only": exact_only,
        "grid": [
            {"key": v.key, "values": list(v.values), "log": v.log, "numeric": v.numeric}
            for v in varies
        ],
        "points": per_point,
        "lowest_mse": _lowest(per_point),
    }


def sweep_table(summary: dict[str, Any]) -> list[dict[str, Any]]:
    """The rows of sweep.parquet (DESIGN.md): the varied keys' values, the architecture, the
    runs, the Monte Carlo metrics and the expected ones (None where there are none)."""
    keys = [g["key"] for g in summary["grid"]]
    rows = []
    for p in summary["points"]:
        for a, e in p["architectures"].items():
            row: dict[str, Any] = {k: p["values"][k] for k in keys}
            row["architecture"] = a
            row["runs"] = p["runs"]
            for m in ("mse", "anees", "dm", "nees_fraction_inside"):
                row[m] = e.get(m)
            row["expected_mse"] = e["expected"]["mse"]
            row["expected_anees"] = e["expected"]["anees"]
            row["bound_worst"] = (e.get("bound") or {}).get("worst")
            if "ape" in e:
                row["ape_rmse"], row["rpe_rmse"] = e["ape"]["rmse"], e["rpe"]["rmse"]
            rows.append(row)
    return rows


def parquet_bytes(
    rows: list[dict[str, Any]], varies: Sequence[Vary], meta: dict[str, str]
) -> bytes:
    """sweep.parquet as bytes: a key column of numbers (int64 when every value is an integer),
    booleans or strings as the values are, else the values as written (TOML text)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    columns: dict[str, Any] = {}
    for v in varies:
        vals = [r[v.key] for r in rows]
        if all(isinstance(x, bool) for x in v.values):
            columns[v.key] = pa.array(vals, pa.bool_())
        elif v.numeric and all(isinstance(x, int) for x in v.values):
            columns[v.key] = pa.array(vals, pa.int64())
        elif v.numeric:
            columns[v.key] = pa.array([float(x) for x in vals], pa.float64())
        elif all(isinstance(x, str) for x in v.values):
            columns[v.key] = pa.array(vals, pa.string())
        else:
            text = dict(zip(map(repr, v.values), v.texts, strict=True))
            columns[v.key] = pa.array([text[repr(x)] for x in vals], pa.string())
    columns["architecture"] = pa.array([r["architecture"] for r in rows], pa.string())
    columns["runs"] = pa.array([r["runs"] for r in rows], pa.int64())
    more = [m for m in TRAJECTORY_COLUMNS if any(m in r for r in rows)]
    for m in (*METRIC_COLUMNS, *more):
        # NaN (no defined step) and None (not computed) are both null: no value
        vals = [r.get(m) if r.get(m) is not None and r[m] == r[m] else None for r in rows]
        columns[m] = pa.array(vals, pa.float64())
    table = pa.table(columns).replace_schema_metadata(meta)
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink)
    return sink.getvalue().to_pybytes()
