"""The parameters of ``fusionlog identify``: the scenario's values named by dotted keys, their
unconstrained coordinates for the optimiser, and the identified values written back into the
file's text.

A key is the sweep's (``sensors.s1.R``, ``model.n0``, ``correlations.0.cov``, ``prior.cov``;
:func:`fusionlog.stages.grid.key_path`). Its value in the file decides its form:

* a number (``n0 = 0.16``, ``R = 1.0``) stays positive: theta = log v;
* a list of numbers (``q = [qx, qy]``) keeps each entry positive: theta_i = log v_i;
* a matrix (list of lists) is estimated whole, symmetric positive definite, through its lower
  Cholesky factor L (V = L L'): theta = the log of L's diagonal and L's entries below it (the
  log-Cholesky parametrisation, Pinheiro and Bates 1996) -- except a cross-covariance
  (``correlations.*.cov``), which may be any matrix: theta = its entries.

The standard errors of the values follow from those of theta by the delta method (`jacobian`).
"""

from __future__ import annotations

import copy
import os
import re
from dataclasses import dataclass
from typing import Any

import numpy as np

from fusionlog.errors import FusionlogError
from fusionlog.scenario import toml

from .grid import assign, key_path

__all__ = ["Param", "params_of", "to_theta", "from_theta", "jacobian", "scales", "written_back"]


@dataclass(frozen=True)
class Param:
    """One ``--param``: the key as given, its path in the document, its form ("scalar",
    "vector", "matrix" or "free": a cross-covariance) and the file's value (as an array)."""

    key: str
    path: tuple[str | int, ...]
    form: str
    given: np.ndarray

    @property
    def size(self) -> int:
        """How many coordinates theta has for it."""
        if self.form == "matrix":
            d = self.given.shape[0]
            return d * (d + 1) // 2
        return self.given.size

    def value(self, v: np.ndarray) -> Any:
        """`v` in the file's form: a float, a list, a list of lists."""
        return float(v) if self.form == "scalar" else np.asarray(v, dtype=float).tolist()


def _bad(key: str, reason: str) -> FusionlogError:
    return FusionlogError(f"--param {key}: {reason}")


def params_of(doc: dict[str, Any], keys: list[str], file: str) -> list[Param]:
    """Each key's parameter, checked: present in the file, a number, a list of numbers or a
    square matrix, positive (definite) where its form requires it, and not given twice."""
    if not keys:
        raise FusionlogError(f"{file}: give at least one --param KEY (e.g. sensors.s1.R)")
    out: list[Param] = []
    for key in keys:
        path = tuple(key_path(doc, key, "--param"))
        node: Any = doc
        for p in path:
            node = node.get(p) if isinstance(node, dict) else node[p]
            if node is None:
                raise _bad(key, f"{file} has no {key} (identify estimates values the file has)")
        if any(q.path == path for q in out):
            raise _bad(key, "the parameter is given twice")
        for q in out:
            short, long = sorted((q.path, path), key=len)
            if long[: len(short)] == short:
                raise _bad(key, f"overlaps --param {q.key}")
        out.append(_param(key, path, node))
    return out


def _param(key: str, path: tuple[str | int, ...], v: Any) -> Param:
    free = path[0] == "correlations"
    if toml.is_number(v):
        a = np.array(float(v))
        form = "free" if free else "scalar"
    elif isinstance(v, list) and v and all(toml.is_number(e) for e in v):
        a, form = np.array(v, dtype=float), "free" if free else "vector"
    elif (
        isinstance(v, list)
        and v
        and all(isinstance(r, list) and len(r) == len(v) for r in v)
        and all(toml.is_number(e) for r in v for e in r)
    ):
        a, form = np.array(v, dtype=float), "free" if free else "matrix"
    else:
        raise _bad(key, f"{toml.show(v)} is not a number or a square matrix of numbers")
    if not np.isfinite(a).all():
        raise _bad(key, "the file's value is not finite")
    if form in ("scalar", "vector") and not (a > 0).all():
        raise _bad(key, f"the file's value {toml.show(v)} is not positive (a noise intensity)")
    if form == "matrix":
        try:
            np.linalg.cholesky(a)
        except np.linalg.LinAlgError:
            raise _bad(key, "the file's matrix is not positive definite") from None
        if not np.allclose(a, a.T, rtol=1e-12, atol=0):
            raise _bad(key, "the file's matrix is not symmetric")
    return Param(key, path, form, a)


def _tril(d: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns of the entries below the diagonal, in a fixed order."""
    return np.tril_indices(d, -1)


def to_theta(params: list[Param], values: list[np.ndarray]) -> np.ndarray:
    """The unconstrained coordinates of the values (see the module docstring)."""
    parts = []
    for p, v in zip(params, values, strict=True):
        if p.form == "matrix":
            L = np.linalg.cholesky(v)
            i, j = _tril(v.shape[0])
            parts.append(np.concatenate([np.log(np.diag(L)), L[i, j]]))
        elif p.form == "free":
            parts.append(np.ravel(v))
        else:
            parts.append(np.log(np.ravel(v)))
    return np.concatenate(parts)


def from_theta(params: list[Param], theta: np.ndarray) -> list[np.ndarray]:
    """The values of the coordinates theta (inverse of `to_theta`)."""
    out, at = [], 0
    for p in params:
        t = theta[at : at + p.size]
        at += p.size
        if p.form == "matrix":
            d = p.given.shape[0]
            L = np.diag(np.exp(t[:d]))
            i, j = _tril(d)
            L[i, j] = t[d:]
            out.append(L @ L.T)
        elif p.form == "free":
            out.append(t.reshape(p.given.shape).copy())
        else:
            out.append(np.exp(t).reshape(p.given.shape))
    return out


def scales(params: list[Param], theta: np.ndarray) -> np.ndarray:
    """Each coordinate's natural scale, for finite-difference steps: 1 for a log; for an
    entry L_ij below a Cholesky factor's diagonal, the scale of row i, sqrt(V_ii) (a fixed
    step would be 25 % of the entries of a matrix of 4e-4); for a cross-covariance's entry,
    max(1, |entry|)."""
    out, at = [], 0
    for p, v in zip(params, from_theta(params, theta), strict=True):
        t = theta[at : at + p.size]
        at += p.size
        if p.form == "matrix":
            d = v.shape[0]
            i, _ = _tril(d)
            out.append(np.concatenate([np.ones(d), np.sqrt(np.diag(v))[i]]))
        elif p.form == "free":
            out.append(np.maximum(1.0, np.abs(t)))
        else:
            out.append(np.ones(p.size))
    return np.concatenate(out)


def jacobian(params: list[Param], theta: np.ndarray) -> np.ndarray:
    """d(values' entries)/d theta (entries of every value, row-major, in order; theta's
    length): exact for exp and the free entries, the product rule for L L'."""
    values = from_theta(params, theta)
    J = np.zeros((sum(v.size for v in values), len(theta)))
    row = col = 0
    for p, v in zip(params, values, strict=True):
        t = theta[col : col + p.size]
        if p.form == "matrix":
            d = v.shape[0]
            L = np.diag(np.exp(t[:d]))
            i, j = _tril(d)
            L[i, j] = t[d:]
            # dV = dL L' + L dL' for each coordinate's dL
            for c in range(p.size):
                dL = np.zeros((d, d))
                if c < d:
                    dL[c, c] = L[c, c]
                else:
                    dL[i[c - d], j[c - d]] = 1.0
                J[row : row + d * d, col + c] = (dL @ L.T + L @ dL.T).ravel()
        elif p.form == "free":
            J[row : row + v.size, col : col + p.size] = np.eye(v.size)
        else:
            J[row : row + v.size, col : col + p.size] = np.diag(np.ravel(v))
        row += v.size
        col += p.size
    return J


def edited(doc: dict[str, Any], params: list[Param], values: list[np.ndarray]) -> dict[str, Any]:
    """A copy of the document with the values in place."""
    out = copy.deepcopy(doc)
    for p, v in zip(params, values, strict=True):
        assign(out, list(p.path), p.value(v))
    return out


# -- writing the values back into the file's text --------------------------------------------

_HEADER = re.compile(r"^\s*(\[\[?)\s*([A-Za-z0-9_.\-]+)\s*\]\]?\s*(#.*)?$")


def _number(x: float) -> str:
    """A TOML float that reads back as the same double."""
    text = repr(float(x))
    return text if any(c in text for c in ".en") else text + ".0"


def toml_value(v: Any) -> str:
    """A value as TOML text (numbers, lists, lists of lists, strings)."""
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(e) for e in v) + "]"
    return _number(v)


def _table_span(lines: list[str], table: str, index: int | None) -> tuple[int, int] | None:
    """Lines [start, end) of the body of [table] (index None) or of the index-th [[table]]."""
    seen, start = -1, None
    for i, line in enumerate(lines):
        m = _HEADER.match(line)
        if not m:
            continue
        if start is not None:
            return start, i
        if m.group(2) == table and (m.group(1) == "[[") == (index is not None):
            seen += 1
            if index is None or seen == index:
                start = i + 1
    return (start, len(lines)) if start is not None else None


def _value_end(text: str, i: int) -> int:
    """The end of the TOML value starting at text[i] (brackets and strings followed)."""
    depth, quote = 0, ""
    while i < len(text):
        c = text[i]
        if quote:
            if c == quote:
                quote = ""
        elif c in "\"'":
            quote = c
        elif c == "#" and depth > 0:
            i = text.find("\n", i)
            if i < 0:
                return len(text)
            continue
        elif c == "[":
            depth += 1
        elif c == "]":
            depth -= 1
            if depth == 0:
                return i + 1
        elif c in "#\n" and depth == 0:
            return i
        i += 1
    return i


def _replace(text: str, path: tuple[str | int, ...], value: Any) -> str | None:
    """`text` with the value at `path` replaced (None: not written as a plain key = value in
    its table's section, e.g. an inline table)."""
    if len(path) == 3 and isinstance(path[1], int):
        span_of = (str(path[0]), path[1])
    elif len(path) == 2 and isinstance(path[0], str):
        span_of = (path[0], None)
    else:
        return None
    key = str(path[-1])
    lines = text.splitlines(keepends=True)
    span = _table_span(lines, *span_of)
    if span is None:
        return None
    offsets = np.cumsum([0] + [len(line) for line in lines])
    pattern = re.compile(rf"^\s*(\"?){re.escape(key)}\1\s*=\s*")
    for i in range(*span):
        m = pattern.match(lines[i])
        if m:
            start = int(offsets[i]) + m.end()
            end = _value_end(text, start)
            tail = text[start:end]
            pad = tail[len(tail.rstrip()) :]
            return text[:start] + toml_value(value) + pad + text[end:]
    return None


def written_back(
    text: str, doc: dict[str, Any], params: list[Param], values: list[np.ndarray], file: str,
    sources_from: str | None = None, sources_to: str | None = None,
) -> str:  # fmt: skip
    """The file's text with the values in place of the given ones, everything else as it was
    (comments too); checked by parsing it back. A replay's `source` paths (relative to the
    file) are rewritten relative to the folder of the output (`sources_from` the input's
    folder, `sources_to` the output's), so that the tuned file reads the same recordings."""
    out = text
    want = edited(doc, params, values)
    for p in params:
        # the key's whole value (an entry of a matrix, sensors.s1.R.0.0, rewrites the matrix)
        at = p.path[:3] if len(p.path) > 1 and isinstance(p.path[1], int) else p.path[:2]
        node: Any = want
        for q in at:
            node = node[q]
        new = _replace(out, at, node)
        if new is None:
            raise FusionlogError(
                f"{file}: cannot write {p.key} back (it is not written as `key = value` under "
                "its own [table] header); write the file's tables out in full"
            )
        out = new
    if sources_from is not None and sources_to is not None:
        out = _moved_sources(out, want, sources_from, sources_to)
    check = toml.parse_toml(out, file)
    if check != want:
        raise FusionlogError(f"{file}: the identified values could not be written into its text")
    return out


def _moved_sources(text: str, want: dict[str, Any], src: str, dst: str) -> str:
    """Every relative `source` of [[sensors]] and [truth] made relative to `dst`."""
    if os.path.abspath(src) == os.path.abspath(dst):
        return text

    def moved(p: str) -> str:
        if os.path.isabs(p):
            return p
        return os.path.relpath(os.path.join(src, p), dst)

    for i, s in enumerate(want.get("sensors", [])):
        if isinstance(s, dict) and isinstance(s.get("source"), str):
            s["source"] = moved(s["source"])
            text = _replace(text, ("sensors", i, "source"), s["source"]) or text
    truth = want.get("truth")
    if isinstance(truth, dict) and isinstance(truth.get("source"), str):
        truth["source"] = moved(truth["source"])
        text = _replace(text, ("truth", "source"), truth["source"]) or text
    return text
