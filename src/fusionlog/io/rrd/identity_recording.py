"""The evaluation recording (.rrd) of an identity scenario (BAYES and DS identity fusion).

Same conventions as every fusionlog recording (:mod:`.stream`): application id ``fusionlog``,
recording id from the scenario name and seed, timelines ``step`` (sequence) and ``time``
(duration), every series sent with ``send_columns``, recording properties ``scenario``,
``summary`` (field ``json``) and any further ``properties``.
:func:`fusionlog.io.rrd.read_recording` reads it back.

=================================================  ===========================================
``identity/probability/<class>/BAYES``             mean BAYES posterior of <class> over the runs
                                                   whose true class is <class>
``identity/belief/<class>/DS``                     the same for the DS belief Bel({<class>})
``identity/plausibility/<class>/DS``               ... and the DS plausibility Pl({<class>})
``metrics/accuracy/<ARCH>``                        share of runs classified correctly
``metrics/p_true/<ARCH>``                          mean probability of the true class (DS: the
                                                   normalised plausibility)
``metrics/log_loss/<ARCH>``                        mean -log of that probability
``metrics/belief_true/DS``, ``.../plausibility_true/DS``  mean Bel and Pl of the true class
``metrics/conflict/DS``                            mean conflict K of each step's combination
``metrics/accumulated_conflict/DS``                mean accumulated conflict
``metrics/disagreement``                           share of runs where BAYES and DS decide
                                                   differently
``runs/<m>/probability/<class>/BAYES``             sample run m: BAYES posterior of each class
``runs/<m>/belief/<class>/DS``, ``.../plausibility/<class>/DS``  and its DS Bel and Pl
=================================================  ===========================================

Steps where a value is not finite (no run with that class, DS in total conflict) are not logged.
The default blueprint opens on one view per class (BAYES probability, DS belief and
plausibility over time) beside the accuracy, log-loss, probability-of-the-truth, conflict and
disagreement views; a second tab shows the sample runs.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from functools import partial
from typing import IO, Any

import numpy as np
import rerun.blueprint as rrb

from .stream import check_axes, entity_path, recording_error, recording_stream
from .style import arch_color, class_color, lighter
from .views import query, tabbed_blueprint, time_series_view

__all__ = ["write_identity_recording"]

#: Per-architecture series of one value per step.
_SCALARS = {
    "BAYES": ("accuracy", "p_true", "log_loss"),
    "DS": (
        "accuracy",
        "p_true",
        "log_loss",
        "belief_true",
        "plausibility_true",
        "conflict",
        "accumulated_conflict",
    ),
}
#: Per-architecture series of one value per step and class.
_PER_CLASS = {"BAYES": ("probability",), "DS": ("belief", "plausibility")}
_LABEL = {"probability": "P", "belief": "Bel", "plausibility": "Pl"}
#: Legend names of the per-step series (default: the architecture).
_SCALAR_NAMES = {
    "p_true": "{arch} p(true)",
    "belief_true": "{arch} Bel(true)",
    "plausibility_true": "{arch} Pl(true)",
    "conflict": "{arch} conflict K",
    "accumulated_conflict": "{arch} accumulated conflict",
}


def _style(arch: str, kind: str) -> tuple[tuple[int, int, int], float]:
    """Colour and width: plausibility is drawn thinner and lighter than belief."""
    col = arch_color(arch)
    if kind in ("plausibility", "plausibility_true", "accumulated_conflict"):
        return lighter(col), 1.5
    if kind in ("belief_true",):
        return col, 1.5
    return col, 2.5


def _check(
    file: IO[bytes],
    times: np.ndarray,
    classes: list[str],
    series: Mapping[str, Mapping[str, np.ndarray]],
    disagreement: np.ndarray | None,
    sample_runs: Mapping[int, tuple[int, Mapping[str, Mapping[str, np.ndarray]]]],
) -> None:
    s, n = check_axes(file, times, classes, least=2, what="classes")
    bad = partial(recording_error, file)
    for arch, d in series.items():
        if arch not in _SCALARS:
            raise bad(f"unknown identity architecture {arch!r}")
        for key in _SCALARS[arch] + _PER_CLASS[arch]:
            if key not in d:
                raise bad(f"architecture {arch}: missing series {key!r}")
        for key, arr in d.items():
            want = (s,) if key in _SCALARS[arch] else (s, n) if key in _PER_CLASS[arch] else None
            if want is None:
                raise bad(f"architecture {arch}: unknown series {key!r}")
            if np.shape(arr) != want:
                raise bad(f"architecture {arch}: {key} has shape {np.shape(arr)}, want {want}")
    if disagreement is not None and np.shape(disagreement) != (s,):
        raise bad(f"disagreement has shape {np.shape(disagreement)}, want {(s,)}")
    for m, (truth, est) in sample_runs.items():
        if not 0 <= int(truth) < n:
            raise bad(f"sample run {m}: true class {truth} is not an index 0..{n - 1}")
        for arch, d in est.items():
            for key, arr in d.items():
                if key not in _PER_CLASS.get(arch, ()) or np.shape(arr) != (s, n):
                    raise bad(
                        f"sample run {m}, {arch}: {key} must be one of "
                        f"{_PER_CLASS.get(arch, ())} with shape {(s, n)}"
                    )


def write_identity_recording(
    file: IO[bytes],
    *,
    classes: Sequence[str],
    series: Mapping[str, Mapping[str, np.ndarray]],
    summary: Mapping[str, Any],
    times: np.ndarray,
    scenario_name: str,
    seed: int,
    disagreement: np.ndarray | None = None,
    sample_runs: Mapping[int, tuple[int, Mapping[str, Mapping[str, np.ndarray]]]] | None = None,
    properties: Mapping[str, Any] | None = None,
    recording_id: str | None = None,
) -> None:
    """Write the identity evaluation recording into the binary file object `file`.

    times: (K+1,) seconds. classes: the frame, in index order. series: {ARCH: {name: array}}
    with ARCH in BAYES, DS; per step (K+1,): ``accuracy``, ``p_true``, ``log_loss`` and for DS
    also ``belief_true``, ``plausibility_true``, ``conflict``, ``accumulated_conflict``; per
    step and class (K+1, N): BAYES ``probability``, DS ``belief`` and ``plausibility`` (means
    over the runs whose truth is that class). disagreement: (K+1,) or None.
    sample_runs: {run: (true class index, {ARCH: {"probability" | "belief" | "plausibility":
    (K+1, N)}})}. summary, properties, recording_id: as
    :func:`fusionlog.io.rrd.write_recording`. Raises FusionlogError if the data are
    inconsistent (before anything is written) and OutputError if writing `file` fails.
    """
    times = np.asarray(times, dtype=float)
    classes = [str(c) for c in classes]
    samples = sample_runs or {}
    _check(file, times, classes, series, disagreement, samples)
    blueprint = _blueprint(classes, list(series), {m: classes[t] for m, (t, _) in samples.items()})
    args = (scenario_name, seed, times, summary, properties, recording_id)
    with recording_stream(file, blueprint, *args) as w:
        for arch, d in series.items():
            for kind in _PER_CLASS[arch]:
                col, width = _style(arch, kind)
                values = np.asarray(d[kind], dtype=float)
                for i, c in enumerate(classes):
                    p = entity_path("identity", kind, c, arch)
                    w.line(p, values[:, i], f"{arch} {_LABEL[kind]}", col, width)
            for kind in _SCALARS[arch]:
                col, width = _style(arch, kind)
                name = _SCALAR_NAMES.get(kind, "{arch}").format(arch=arch)
                w.line(entity_path("metrics", kind, arch), d[kind], name, col, width)
        if disagreement is not None:
            w.line(
                entity_path("metrics", "disagreement"),
                disagreement,
                "BAYES ≠ DS",
                (90, 90, 90),
                2.0,
            )
        for m in sorted(samples):
            _, est = samples[m]
            for arch, d in est.items():
                for kind, arr in d.items():
                    arr = np.asarray(arr, dtype=float)
                    width = 1.25 if kind == "plausibility" else 2.5
                    for i, c in enumerate(classes):
                        col = class_color(i)
                        if kind == "plausibility":
                            col = lighter(col, 0.4)
                        p = entity_path("runs", m, kind, c, arch)
                        w.line(p, arr[:, i], f"{_LABEL[kind]}({c})", col, width)


def _blueprint(classes: list[str], archs: list[str], runs: Mapping[int, str]) -> rrb.Blueprint:
    what = []
    if "BAYES" in archs:
        what.append("BAYES P")
    if "DS" in archs:
        what.append("DS Bel (thick), Pl (thin)")
    per_class = [
        time_series_view(
            f"truth {c}: {', '.join(what)} of {c}, run mean",
            [
                query("identity", kind, c) + "/**"
                for kind in ("probability", "belief", "plausibility")
            ],
            legend=i == 0,
        )
        for i, c in enumerate(classes)
    ]
    accuracy = time_series_view(
        "Accuracy: share of runs classified correctly", [query("metrics", "accuracy") + "/**"]
    )
    log_loss = time_series_view(
        "Log-loss: −log p(true class), run mean",
        [query("metrics", "log_loss") + "/**"],
        legend=False,
    )
    p_true = time_series_view(
        "Probability of the true class (DS: normalised Pl; Bel and Pl thin)",
        [query("metrics", k) + "/**" for k in ("p_true", "belief_true", "plausibility_true")],
    )
    conflict = time_series_view(
        "DS conflict (per step; accumulated light) and BAYES ≠ DS",
        [
            query("metrics", "conflict") + "/**",
            query("metrics", "accumulated_conflict") + "/**",
            query("metrics", "disagreement"),
        ],
    )
    overview = rrb.Horizontal(
        rrb.Vertical(*per_class, name="Classes"),
        rrb.Vertical(accuracy, log_loss, name="Decisions"),
        rrb.Vertical(p_true, conflict, name="Truth and conflict"),
        name="Overview",
    )
    tabs: list[rrb.Container | rrb.View] = [overview]
    if runs:
        views = []
        for j, m in enumerate(sorted(runs)):
            if "BAYES" in archs:
                views.append(
                    time_series_view(
                        f"run {m} (truth {runs[m]}): BAYES posterior",
                        [query("runs", m, "probability") + "/**"],
                        legend=j == 0,
                    )
                )
            if "DS" in archs:
                views.append(
                    time_series_view(
                        f"run {m} (truth {runs[m]}): DS Bel (thick), Pl (thin)",
                        [
                            query("runs", m, "belief") + "/**",
                            query("runs", m, "plausibility") + "/**",
                        ],
                        legend=j == 0,
                    )
                )
        tabs.append(rrb.Grid(*views, grid_columns=len(archs), name="Sample runs"))
    return tabbed_blueprint(tabs)
