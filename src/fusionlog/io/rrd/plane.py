"""The state-plane view of a 2-D state (the Gustafsson-Hendeby slides' plot of the fusion
formula): truth, sample estimates and covariance ellipses, one frame a step.

=============================================  ============================================
``plane/truth``                                 the true state (labelled "truth")
``plane/estimates/<ARCH>``                      sample estimates of the first runs
``plane/ellipses/<label>``                      the ellipse {x : (x - x_true)^T P^-1 (x -
                                                x_true) = c^2} of a covariance P (an input's
                                                ``input <sensor>`` or an architecture's)
``plane/ellipses/<label>/name``                 one point on that ellipse carrying the label,
                                                so that coinciding or crossing ellipses can
                                                be told apart
=============================================  ============================================

The scale c is given by the caller: for a two-dimensional Gaussian error the ellipse holds the
error with probability `confidence` when c^2 = chi2.ppf(confidence, 2) (2 degrees of freedom).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import IO, Any

import numpy as np
import rerun as rr

from .stream import SeriesWriter, entity_path, recording_error
from .style import INPUT_COLOR, TRUTH_COLOR, arch_color

__all__ = ["check_plane", "ellipse_points", "label_angles", "write_plane"]

#: Vertices of an ellipse polygon (the first and the last coincide: a closed strip).
_VERTICES = 97


def check_plane(file: IO[bytes], steps: int, plane: Mapping[str, Any]) -> None:
    """Refuse plane data of the wrong shapes (before anything is written)."""
    if np.shape(plane.get("truth")) not in ((steps, 2), (steps, 1, 2)):
        raise recording_error(file, f"plane truth must have shape {(steps, 2)}")
    for arch, pts in plane.get("estimates", {}).items():
        sh = np.shape(pts)
        if len(sh) != 3 or sh[0] != steps or sh[2] != 2:
            raise recording_error(file, f"plane estimates of {arch} must be ({steps}, P, 2)")
    for label, covs in plane.get("ellipses", {}).items():
        if np.shape(covs) != (steps, 2, 2):
            raise recording_error(file, f"plane ellipse {label} must be ({steps}, 2, 2)")


def ellipse_points(centres: np.ndarray, covs: np.ndarray, scale: float, angles: np.ndarray):
    """Points x = centre + scale L (cos a, sin a) with L L^T = P, for each step (K, 2) and
    (K, 2, 2) and each angle a: on the ellipse (x - centre)^T P^-1 (x - centre) = scale^2.
    Returns (K, len(angles), 2)."""
    w, V = np.linalg.eigh(covs)
    L = V * np.sqrt(np.clip(w, 0.0, None))[:, None, :]
    u = np.stack([np.cos(angles), np.sin(angles)], axis=-1) * scale
    return centres[:, None, :] + np.einsum("kij,pj->kpi", L, u)


def write_plane(w: SeriesWriter, plane: Mapping[str, Any]) -> None:
    """plane: {"truth": (K+1, 2), "estimates": {ARCH: (K+1, P, 2) sample estimates},
    "ellipses": {label: (K+1, 2, 2) covariances, drawn centred on the truth}, "scale": ellipse
    radius c in standard deviations (default 2)}. A label ``input <sensor>`` is drawn grey."""
    K1 = w.steps.shape[0]
    rec, every = w.rec, w.index(np.ones(K1, dtype=bool))
    truth = np.asarray(plane["truth"], dtype=float).reshape(K1, 2)
    path = entity_path("plane", "truth")
    style = rr.Points2D.columns(colors=[TRUTH_COLOR], radii=[0.012], labels=["truth"])
    rec.send_columns(path, indexes=[], columns=style)
    rec.send_columns(
        path, indexes=every, columns=rr.Points2D.columns(positions=truth).partition([1] * K1)
    )
    for arch, pts in plane.get("estimates", {}).items():
        pts = np.asarray(pts, dtype=float)
        path = entity_path("plane", "estimates", arch)
        style = rr.Points2D.columns(colors=[arch_color(arch)], radii=[0.004])
        rec.send_columns(path, indexes=[], columns=style)
        keep = np.isfinite(pts).all(axis=-1)
        rec.send_columns(
            path,
            indexes=every,
            columns=rr.Points2D.columns(positions=pts[keep]).partition(keep.sum(axis=1)),
        )
    scale = float(plane.get("scale", 2.0))
    circle = np.linspace(0.0, 2.0 * np.pi, _VERTICES)
    ellipses = {
        label: np.asarray(covs, dtype=float).reshape(K1, 2, 2)
        for label, covs in plane.get("ellipses", {}).items()
    }
    ellipses = {k: c for k, c in ellipses.items() if np.isfinite(c).all(axis=(1, 2)).any()}
    angles = label_angles(truth, ellipses, scale)
    for label, covs in ellipses.items():
        ok = np.isfinite(covs).all(axis=(1, 2))
        strips = ellipse_points(truth[ok], covs[ok], scale, circle)
        arch = label.removeprefix("input ")
        color = arch_color(arch) if label == arch else INPUT_COLOR
        path = entity_path("plane", "ellipses", label)
        style = rr.LineStrips2D.columns(
            colors=[color], radii=[0.003], labels=[label], show_labels=[False]
        )
        rec.send_columns(path, indexes=[], columns=style)
        rec.send_columns(
            path, indexes=w.index(ok), columns=rr.LineStrips2D.columns(strips=list(strips))
        )
        at = ellipse_points(truth[ok], covs[ok], scale, np.array([angles[label]]))[:, 0]
        name = entity_path("plane", "ellipses", label, "name")
        style = rr.Points2D.columns(
            colors=[color], radii=[0.006], labels=[label], show_labels=[True]
        )
        rec.send_columns(name, indexes=[], columns=style)
        rec.send_columns(
            name,
            indexes=w.index(ok),
            columns=rr.Points2D.columns(positions=at).partition([1] * int(ok.sum())),
        )


def label_angles(
    truth: np.ndarray, ellipses: Mapping[str, np.ndarray], scale: float
) -> dict[str, float]:
    """For each ellipse, the angle a of the point centre + scale L (cos a, sin a) that carries
    its label: the candidate farthest from the other ellipses (those that do not coincide with
    it), from the labels placed before (ellipses that coincide, e.g. an input and the SKF on
    it, show both names apart), from the truth's label and from the edge of the picture (the
    view fits the ellipses, a label there would be cut). One angle for all steps, chosen on
    the last step where every ellipse is defined (the steady state of a converging filter)."""
    if not ellipses:
        return {}
    covs = np.stack(list(ellipses.values()))  # (E, K+1, 2, 2)
    ok = np.flatnonzero(np.isfinite(covs).all(axis=(0, 2, 3)))
    k = int(ok[-1]) if ok.size else -1
    if k < 0:  # no step where all are defined: each on its own last defined step
        ks = [int(np.flatnonzero(np.isfinite(c).all(axis=(1, 2)))[-1]) for c in covs]
    else:
        ks = [k] * len(covs)
    P = np.stack([c[kk] for c, kk in zip(covs, ks, strict=True)])  # (E, 2, 2)
    centres = np.stack([truth[kk] for kk in ks])
    curves = ellipse_points(centres, P, scale, np.linspace(0.0, 2.0 * np.pi, _VERTICES))
    cand = np.linspace(0.0, 2.0 * np.pi, 72, endpoint=False)
    spots = ellipse_points(centres, P, scale, cand)  # (E, C, 2)
    lo, hi = curves.reshape(-1, 2).min(axis=0), curves.reshape(-1, 2).max(axis=0)
    size = float(np.max(hi - lo)) or 1.0
    placed = [truth[ks[0]]]
    out: dict[str, float] = {}
    for e, label in enumerate(ellipses):
        same = np.isclose(P, P[e], rtol=1e-9, atol=1e-12 * size**2).all(axis=(1, 2))
        others = curves[~same].reshape(-1, 2)
        pts = spots[e]
        d_edge = np.minimum(pts - lo, hi - pts).min(axis=1) * 2.0  # half the room to spare
        d = [d_edge]
        if others.size:
            d.append(np.linalg.norm(pts[:, None] - others[None], axis=-1).min(axis=1))
        d.append(np.linalg.norm(pts[:, None] - np.array(placed)[None], axis=-1).min(axis=1))
        best = int(np.argmax(np.min(d, axis=0)))
        out[label] = float(cand[best])
        placed.append(pts[best])
    return out
