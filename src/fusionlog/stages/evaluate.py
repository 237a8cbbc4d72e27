"""`fusionlog evaluate`: estimates against the truth into a Rerun recording and summary.json."""

from __future__ import annotations

import json
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fusionlog.core.architectures import build_plan
from fusionlog.core.exact import Expected, analyse
from fusionlog.core.metrics import MetricsAccumulator, chi2_quantile
from fusionlog.core.names import parse_arch
from fusionlog.errors import FusionlogError
from fusionlog.io.mcap import McapFile
from fusionlog.io.rrd import write_recording
from fusionlog.scenario import system_from_dict

from .common import (
    SCENARIO_META,
    block_runs,
    open_evaluation_inputs,
    progress,
    scenario_from_file,
)

#: Sample estimates per architecture drawn in the state-plane view.
PLANE_POINTS = 300


@dataclass
class EvaluateResult:
    recording: Path
    summary_path: Path | None
    summary: dict[str, Any]


def write_json_atomic(path: Path, data: Any, force: bool) -> None:
    if path.exists() and not force:
        raise FusionlogError(f"{path}: exists; use --force to overwrite")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give it the usual permissions
        with os.fdopen(fd, "w") as f:
            json.dump(data, f, indent=2)
            f.write("\n")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _analysable(prov: dict[str, str], filter_sys, truth_sys):
    """(truth model as the filter saw it, measurement mask) for the exact analysis, or None.

    The filter stacks its sensors in its own order, so the truth is re-ordered to match by
    sensor name (a `--model` may list them differently or use only some); sensors the truth
    does not have, or missing measurements that differ between runs, leave no exact analysis.
    """
    pattern = prov.get("measurement_pattern", "complete")
    if pattern == "per-run":
        return None
    names = [s.name for s in truth_sys.sensors]
    if any(s.name not in names for s in filter_sys.sensors):
        return None
    seen = truth_sys.subset([names.index(s.name) for s in filter_sys.sensors])
    if any(a.dim != b.dim for a, b in zip(seen.sensors, filter_sys.sensors, strict=True)):
        return None
    mask = None if pattern == "complete" else np.array(json.loads(pattern), dtype=bool)
    return seen, mask


def _known(arch: str, system) -> bool:
    try:
        parse_arch(arch, [s.name for s in system.sensors])
    except ValueError:
        return False
    return True


def _estimate_topics(est: McapFile) -> list[str]:
    topics = [t for t in est.topics if t.startswith("/estimates/")]
    if not topics:
        have = ", ".join(sorted(est.topics)) or "none"
        raise FusionlogError(f"{est.path}: no /estimates/<ARCH> topics (topics: {have})")
    return topics


def run_evaluate(
    sensors_path: Path,
    estimates_path: Path,
    out: Path,
    *,
    summary_path: Path | None = None,
    force: bool = False,
    block: int | None = None,
) -> EvaluateResult:
    """Metrics of every architecture in `estimates_path`, with exact expected values beside them.

    Metrics are sums over blocks of runs (core.metrics), so memory does not grow with M. The
    expected values come from the exact covariance analysis of each architecture built on the
    filter model it ran with, under the true model of the sensors file; they are left out when
    the data had missing measurements (the analysis assumes every measurement present).
    With `[evaluate] plane_view`, the recording also shows the state plane: truth, sample
    estimates and the ellipses (at the chi-square confidence) of every input and fused result.
    """
    outputs = [out] + ([summary_path] if summary_path else [])
    sens, est, prov = open_evaluation_inputs(sensors_path, estimates_path, outputs, force)
    sc = scenario_from_file(sens)
    if sc is None:
        raise FusionlogError(f"{sensors_path}: no {SCENARIO_META} metadata (not a simulation)")
    topics = _estimate_topics(est)
    archs = [t.removeprefix("/estimates/") for t in topics]
    truth_sys = sc.system
    filter_sys = system_from_dict(json.loads(prov["model"])) if "model" in prov else truth_sys
    if filter_sys.n != truth_sys.n:
        raise FusionlogError(
            f"{estimates_path}: estimates of {filter_sys.n} states, the truth has {truth_sys.n}"
        )
    K, M, n = sens.steps() - 1, sens.runs(), truth_sys.n
    analysable = _analysable(prov, filter_sys, truth_sys)
    times = sens.times()
    B = block_runs(K, M, block)
    accs = {a: MetricsAccumulator(K + 1, n) for a in archs}
    n_samples = min(sc.sample_runs, M)
    samples: dict[int, tuple[np.ndarray, dict[str, tuple[np.ndarray, np.ndarray]]]] = {}
    plane_pts: dict[str, np.ndarray] = {}
    plane_truth: np.ndarray | None = None
    plane_cov: dict[str, np.ndarray] = {}
    blocks = zip(sens.iter_run_blocks(["/truth"], B), est.iter_run_blocks(topics, B), strict=True)
    for (off, runs, tdata), (_, _, edata) in progress(blocks, -(-M // B), "evaluate"):
        x = tdata["/truth"]
        for a, t in zip(archs, topics, strict=True):
            mean, cov = edata[t]
            accs[a].add(x, mean, cov)
            if sc.plane_view and off == 0:
                plane_truth = x[0]
                plane_pts[a] = np.moveaxis(mean[:PLANE_POINTS], 0, 1)  # (K+1, P, 2)
                plane_cov[a] = cov if cov.ndim == 3 else cov[0]
            for r in range(off, min(off + runs, n_samples)):
                c = cov if cov.ndim == 3 else cov[r - off]
                std = np.sqrt(np.clip(np.diagonal(c, axis1=-2, axis2=-1), 0, None))
                samples.setdefault(r, (x[r - off], {}))[1][a] = (mean[r - off], std)
    series, arch_summary = {}, {}
    bounds = None
    for a in archs:
        res = accs[a].finalize(sc.confidence)
        ex: Expected | None = None
        if analysable is not None and _known(a, filter_sys):
            truth_seen, mask = analysable
            ex = analyse(build_plan(filter_sys, a, K, mask), truth_seen)
        kw = (
            {"expected_mse": ex.mse_per_state, "expected_nees": ex.nees, "expected_dm": ex.dm}
            if ex is not None
            else {}
        )
        series[a] = res.series(**kw)
        arch_summary[a] = res.summary(**kw)
        if bounds is None:
            bounds = (res.nees_lower, res.nees_upper)
    summary = {
        "scenario": sc.name,
        "seed": sc.seed,
        "runs": M,
        "steps": K,
        "state_names": list(sc.state_names),
        "confidence": sc.confidence,
        "architectures": arch_summary,
    }
    plane = None
    if sc.plane_view and plane_truth is not None:
        inputs = {
            f"input {s.name}": build_plan(filter_sys, f"SKF:{s.name}", K).reported_cov
            for s in filter_sys.sensors
        }
        plane = {
            "truth": plane_truth,
            "estimates": plane_pts,
            "ellipses": {**inputs, **plane_cov},
            "scale": float(np.sqrt(chi2_quantile(sc.confidence, 2))),
        }
    write_recording(
        out,
        scenario_name=sc.name,
        seed=sc.seed,
        times=times,
        state_names=sc.state_names,
        series=series,
        summary=summary,
        nees_bounds=bounds,
        confidence=sc.confidence,
        sample_runs=samples,
        properties={"scenario": sc.source, "provenance": prov},
        plane=plane,
        force=force,
    )
    if summary_path is not None:
        write_json_atomic(summary_path, summary, force)
    return EvaluateResult(out, summary_path, summary)
