"""Covariance intersection's weights omega for many problems at once (Gustafsson-Hendeby's
"safe fusion"): exact tests first (equal inputs, an input alone by its KKT conditions), closed
forms on the edges for two-state problems, then Newton's method on the simplex's faces
(`fusionlog.core.ci_newton`). The shared and the per-run paths call the same function.
"""

from __future__ import annotations

import math

import numpy as np

from .ci_newton import (
    CI_TOL,
    Criterion,
    Info2,
    InfoN,
    diagsum,
    finish,
    invertible2,
    representatives,
    split,
)
from .linalg import is_invertible

__all__ = ["Criterion", "ci_omegas"]


def ci_omegas(infos: np.ndarray, criterion: Criterion = "trace") -> np.ndarray:
    """Covariance-intersection weights for many independent problems at once, on the simplex.

    infos (..., N, n, n): the inputs' information matrices Y_i = P_i^-1, any leading shape and
    strides (n = 2 reads them in place); the weights come back as (..., N). Each problem minimises
    tr P or log det P, P = (sum_i w_i Y_i)^-1, over w >= 0, sum_i w_i = 1. Both costs are convex
    in w (tr X^-1 and -log det X are convex on positive definite X), with
    d tr P/d w_i = -tr(P Y_i P), d^2 tr P/d w_i d w_j = 2 tr(P Y_i P Y_j P) and
    d log det P/d w_i = -tr(P Y_i), d^2 log det P/d w_i d w_j = tr(P Y_i P Y_j). They are solved
    all together by an active-set Newton method (`newton_solve`: Newton steps on a face of the
    simplex, cut at its boundary, with Armijo backtracking and the KKT multipliers choosing the
    face), vectorised over the problems, from w = 1/N. For n = 2 (`_ci_omegas2`) exact tests
    at w = 1/N and at the end points, and closed forms on the edges, settle most problems
    without iterating, and the iteration itself needs no matrix algebra (`Info2`); every
    answer passes the same optimality test. Every problem is solved on its own:
    the same problem gives the same omega to the last bit alone or among any others, so the
    shared path (one problem per step) and the per-run path (one per run and step) agree.

    Each problem's informations are first scaled to unit mean trace (omega does not change).
    Inputs whose informations are bit-for-bit equal are merged and share their weight equally.
    A singular input (a local filter that cannot see the whole state yet) makes the cost
    infinite on part of the simplex, which the line search never enters; a problem whose
    inputs together are singular has no CI estimate (NaN). The answer keeps w = 1/N when the
    cost's gradient there is the same for all inputs up to rounding (`CI_TOL`; equal
    covariances: every omega gives the same P, and the interior answer also averages the
    estimates, where letting rounding pick an input would make the fused estimate jump from
    step to step); likewise an input alone (an end point) replaces the optimiser's answer only
    if better by more than rounding.
    """
    Ys = np.asarray(infos, dtype=float)
    lead, N, n = Ys.shape[:-3], Ys.shape[-3], Ys.shape[-1]
    if N == 1:
        return np.ones(lead + (1,))
    trace = criterion == "trace"
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        if n == 2:
            return _ci_omegas2(Ys, trace)
        Ys = Ys.reshape((-1, N, n, n))
        B = len(Ys)
        total = Ys[:, 0]
        for i in range(1, N):
            total = total + Ys[:, i]
        tr = diagsum(total) / (N * n)
        tr = np.where(tr > 0, tr, 1.0)
        out = np.full((B, N), np.nan)
        idx = np.flatnonzero(is_invertible(total / (N * tr)[:, None, None]))
        if idx.size:
            Ys = Ys[idx] / tr[idx, None, None, None]
            flat = Ys.reshape(len(idx), N, n * n)
            rep = representatives(lambda k, i: (flat[:, k] == flat[:, i]).all(axis=1), len(idx), N)
            out[idx] = finish(InfoN.of(Ys, trace), rep)
        return out.reshape(lead + (N,))


#: Problems per block of `_ci_omegas2`'s tests: the arrays of a block stay in the cache.
CI_BLOCK = 16384


def _ci_omegas2(Ys: np.ndarray, trace: bool) -> np.ndarray:
    """`ci_omegas` for n = 2, on the entries [[a_i, b_i], [b_i, c_i]] of the informations, each
    an array over the problems.

    Before any iteration, two exact optimality tests with the tolerances of `newton_solve`:
    * at the start w = 1/N, with Ybar = mean Y_i = [[a, b], [b, c]], q = det Ybar, the gradient
      g_i = -tr(P Y_i P) is, up to a constant, -tr(D_i adj(Ybar)^2)/q^2 (D_i = Y_i - Ybar;
      for log det, -tr(D_i adj(Ybar))/q): if it varies by at most CI_TOL times the cost,
      w = 1/N is the answer (equal inputs);
    * at an end point e_k (input k alone, P_k = Y_k^-1 = adj(Y_k)/q_k): the KKT multipliers
      mu_j = g_j - g_k = -tr((Y_j - Y_k) adj(Y_k)^2)/q_k^2 (for log det -tr((Y_j - Y_k)
      adj(Y_k))/q_k) are all >= -CI_TOL times the cost scale: then e_k is the optimum (a
      local filter whose information dominates the others', the usual case in a bank of
      filters that differ only in which measurements they had). Used when the inputs that
      pass are all equal (one group, which then shares the weight).
    The other problems are gathered and tried on the edges (`_ci_edges2`, closed forms); those
    left go to `newton_solve` with `Info2`.
    """
    lead, N = Ys.shape[:-3], Ys.shape[-3]
    if not lead:
        return _ci_omegas2(Ys[None], trace)[0]
    # The output in the input's memory order, and both seen with the leading axes from the
    # outermost in memory to the innermost: blocks along the first of them then cover
    # contiguous memory, whatever layout the informations come in.
    out = np.empty_like(Ys[..., 0, 0])
    perm = sorted(range(len(lead)), key=lambda ax: -abs(Ys.strides[ax]))
    Yt = Ys.transpose(perm + [-3, -2, -1])
    ot = out.transpose(perm + [-1])
    shape = Yt.shape[:-3]
    k = 0  # split the first axis whose inner part fits a block
    while k < len(shape) - 1 and math.prod(shape[k + 1 :]) > CI_BLOCK:
        k += 1
    chunk = max(1, CI_BLOCK // math.prod(shape[k + 1 :]))
    rest: list[tuple[tuple, tuple]] = []
    for at in np.ndindex(shape[:k]):
        for r0 in range(0, shape[k], chunk):
            block = at + (slice(r0, r0 + chunk),)
            ot[block], left = _ci_tests2(Yt[block], trace)
            if left is not None:
                rest.append((block, left))
    if rest:
        sub = np.concatenate([Yt[block][left] for block, left in rest])
        tr = diagsum(sub[:, 0])
        for i in range(1, N):
            tr = tr + diagsum(sub[:, i])
        tr = tr / (2 * N)
        sub = sub / np.where(tr > 0, tr, 1.0)[:, None, None, None]
        a, c = sub[:, :, 0, 0], sub[:, :, 1, 1]
        b = 0.5 * (sub[:, :, 0, 1] + sub[:, :, 1, 0])
        rep = representatives(lambda k, i: (sub[:, k] == sub[:, i]).all(axis=(1, 2)), len(sub), N)
        w = np.empty((len(sub), N))
        for r0 in range(0, len(sub), CI_BLOCK):  # blocks again, for the cache
            part = slice(r0, r0 + CI_BLOCK)
            w[part], done = _ci_edges2(a[part], b[part], c[part], rep[part], trace)
            if not done.all():
                todo = np.flatnonzero(~done)
                ev = Info2.of(a[part][todo], b[part][todo], c[part][todo], trace)
                w[r0 + todo] = finish(ev, rep[part][todo])
        r0 = 0
        for block, left in rest:
            view = ot[block]
            view[left] = w[r0 : r0 + len(left[0])]
            r0 += len(left[0])
    return out


def _ci_edges2(
    a: np.ndarray, b: np.ndarray, c: np.ndarray, rep: np.ndarray, trace: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Optima on an edge of the simplex (two inputs), for n = 2, in closed form and certified.

    On the edge w = (1 - x) e_i + x e_j, Y = Y_i + x E (E = Y_j - Y_i) has
    det Y = c0 + c1 x + c2 x^2 (c0 = det Y_i, c1 = tr(adj(Y_i) E), c2 = det E) and
    tr Y = t0 + t1 x. tr P = (t0 + t1 x)/det Y has derivative -p(x)/det^2 with
    p(x) = t1 c2 x^2 + 2 t0 c2 x + (t0 c1 - t1 c0); the cost is convex, so its minimum is the
    root where p falls, x = (-b - sqrt(b^2 - 4 a c))/(2 a) in p's coefficients a, b, c,
    evaluated as 2 c/(sqrt(..) - b) when b < 0 (no cancellation either way). log det P =
    -log det Y has its minimum at x = -c1/(2 c2) when c2 < 0. A root inside (0, 1) is the
    answer if it passes the KKT test of `newton_solve` at that point (with Y = Y(w) and
    Z = adj(Y)^2, or adj(Y) for log det: G_k = tr((Y_k - Y) Z) equal for i and j up to
    CI_TOL, and no other input's G_k above theirs by more; g_k = const - G_k/q^2, or /q), and
    no other edge passes. Returns the weights (split within groups of equal inputs; garbage
    where not found) and where one was found.
    """
    B, N = a.shape
    member = rep == np.arange(N)
    A, Bq, C = a.T.copy(), b.T.copy(), c.T.copy()
    am, bm, cm = sum(A[1:], A[0]) / N, sum(Bq[1:], Bq[0]) / N, sum(C[1:], C[0]) / N
    S = (am + cm) / (am * cm - bm * bm) if trace else 2.0
    found = np.zeros(B)
    w = np.zeros((B, N))
    for i in range(N):
        for j in range(i + 1, N):
            Ea, Eb, Ec = A[j] - A[i], Bq[j] - Bq[i], C[j] - C[i]
            c1 = C[i] * Ea + A[i] * Ec - 2.0 * Bq[i] * Eb
            c2 = Ea * Ec - Eb * Eb
            if trace:
                t0, t1 = A[i] + C[i], Ea + Ec
                pa, pb = t1 * c2, 2.0 * t0 * c2
                pc = t0 * c1 - t1 * (A[i] * C[i] - Bq[i] * Bq[i])
                root = np.sqrt(pb * pb - 4.0 * pa * pc)
                x = np.where(pb >= 0, (-pb - root) / (2.0 * pa), (2.0 * pc) / (root - pb))
            else:
                x = np.where(c2 < 0, -c1 / (2.0 * c2), np.nan)
            ya, yb, yc = A[i] + x * Ea, Bq[i] + x * Eb, C[i] + x * Ec
            q = ya * yc - yb * yb
            if trace:
                za, zb, zc = yc * yc + yb * yb, -yb * (ya + yc), ya * ya + yb * yb
                bound = CI_TOL * S * (q * q)
            else:
                za, zb, zc = yc, -yb, ya
                bound = 2.0 * CI_TOL * q
            G = [(A[k] - ya) * za + 2.0 * (Bq[k] - yb) * zb + (C[k] - yc) * zc for k in range(N)]
            ok = member[:, i] & member[:, j] & (x > 0) & (x < 1) & (q > 0)
            ok &= np.abs(G[i] - G[j]) <= bound
            mid = 0.5 * (G[i] + G[j])
            for k in range(N):
                if k != i and k != j:
                    ok &= G[k] - mid <= bound
            found += ok
            w[ok, i], w[ok, j] = 1.0 - x[ok], x[ok]
    return split(w, rep), found == 1


def _ci_tests2(Ys: np.ndarray, trace: bool) -> tuple[np.ndarray, tuple | None]:
    """The tests of `_ci_omegas2` on one block of problems (any leading shape): its weights
    (NaN where the inputs together are singular) and the index (np.nonzero) of the problems
    that need more (None if none; their weights are left unset)."""
    N = Ys.shape[-3]
    # Entry by entry, each an array over the problems (views: the first operation reads them).
    a = [Ys[..., i, 0, 0] for i in range(N)]
    b = [0.5 * (Ys[..., i, 0, 1] + Ys[..., i, 1, 0]) for i in range(N)]
    c = [Ys[..., i, 1, 1] for i in range(N)]
    tr = (sum(a[1:], a[0]) + sum(c[1:], c[0])) / (2 * N)
    tr[~(tr > 0)] = 1.0
    inv = 1.0 / tr
    a, b, c = [x * inv for x in a], [x * inv for x in b], [x * inv for x in c]
    am, bm, cm = sum(a[1:], a[0]) / N, sum(b[1:], b[0]) / N, sum(c[1:], c[0]) / N
    solvable = invertible2(am, bm, cm)
    # Gradient at w = 1/N, through the quadratic form of adj(Ybar)^2 (trace) or adj(Ybar).
    q0 = am * cm - bm * bm
    if trace:
        A, Bq, C = cm * cm + bm * bm, -bm * (am + cm), am * am + bm * bm
        bound = CI_TOL * (am + cm) * q0
    else:
        A, Bq, C = cm, -bm, am
        bound = 2.0 * CI_TOL * q0
    G = [(a[i] - am) * A + 2.0 * (b[i] - bm) * Bq + (c[i] - cm) * C for i in range(N)]
    Gmax, Gmin = G[0], G[0]
    for x in G[1:]:
        Gmax, Gmin = np.maximum(Gmax, x), np.minimum(Gmin, x)
    flat = Gmax - Gmin <= bound
    # End points: KKT at each input alone. Equal inputs give the same numbers, so they pass
    # or fail together; the answer is an end point when those that pass are all equal.
    S = (am + cm) / q0 if trace else 2.0
    diff = {(j, k): (a[j] - a[k], b[j] - b[k], c[j] - c[k]) for k in range(N) for j in range(k)}
    passed = []
    for k in range(N):
        qk = a[k] * c[k] - b[k] * b[k]
        if trace:
            A, Bq, C = c[k] * c[k] + b[k] * b[k], -b[k] * (a[k] + c[k]), a[k] * a[k] + b[k] * b[k]
            bound = CI_TOL * S * (qk * qk)
        else:
            A, Bq, C = c[k], -b[k], a[k]
            bound = 2.0 * CI_TOL * qk
        # A singular Y_k (q_k <= 0 or at rounding level) fails the test by itself unless every
        # input is blind along its null direction z (z^T (Y_j - Y_k) z = z^T Y_j z >= 0 must
        # be <= ~0), i.e. unless the problem has no answer at all (not solvable).
        ok = qk > 0
        for j in range(N):
            if j < k:
                da, db, dc = diff[j, k]
                ok &= da * A + 2.0 * db * Bq + dc * C <= bound
            elif j > k:  # D_jk = -D_kj
                da, db, dc = diff[k, j]
                ok &= da * A + 2.0 * db * Bq + dc * C >= -bound
        passed.append(ok)
    eq = {(j, k): (a[j] == a[k]) & (b[j] == b[k]) & (c[j] == c[k]) for (j, k) in diff}
    # One group: no two inputs that pass differ.
    one = passed[0].copy()
    for k in range(1, N):
        one |= passed[k]
    for (j, k), e in eq.items():
        one &= ~(passed[j] & passed[k]) | e
    npass = sum(p.astype(float) for p in passed)
    out = np.empty(Ys.shape[:-2])
    end = one & ~flat
    for i in range(N):
        out[..., i] = passed[i] / npass  # (garbage where not an end point)
    out[flat] = 1.0 / N
    out[~solvable] = np.nan
    left = np.nonzero(solvable & ~flat & ~end)
    return out, (left if left[0].size else None)
