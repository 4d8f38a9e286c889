"""Reading designs back: the ``ashc summary`` object and ``ashc eval`` of a stored function at a point.

Both work from an artefact folder alone (no spec): formulas are rebuilt from their stored ``srepr`` and
evaluated with the parameter values the artefacts recorded.
"""

from __future__ import annotations

import math

import json

import numpy as np
import sympy as sp

from ashc_cli.design.artefacts import Artefact
from ashc_cli.errors import ArtefactError, DesignError, SpecError
from ashc_cli.design.pipeline import PRODUCTS, STAGES
from ashc_cli.design.upstream import certified_set, format_box, outside_certified_set
from ashc_cli.outputs.numbers import PEOPLE_DIGITS, no_negative_zero, number_text, readable  # noqa: F401 (re-exported)

__all__ = ["summary", "EVALUABLE", "parse_point", "evaluate", "no_negative_zero", "number_text", "readable", "PEOPLE_DIGITS"]

#: Functions built from m: evaluated only at states x whose output h(x) lies where m is certified
#: (``inverse.m_domain``).
BUILT_FROM_M = ("m", "b", "c")

#: Functions of xi solved on V only: evaluated only at points of V (a fitted p extrapolates beyond it).
ON_V = ("p", "kappa")

#: Names ``ashc eval`` knows, with the stage and stored expression each comes from.
EVALUABLE = {
    "p": ("manifold", "p"),
    "kappa": ("kappa", "kappa"),
    "m": ("inverse", "m"),
    "delta": ("delta", "delta"),
    "b": ("delta", "b"),
    "c": ("delta", "c"),
    "theta": ("bound", None),
}


def summary(arts: dict[str, Artefact]) -> dict:
    """One JSON-able object: a key per stage with its headline numbers, formulas and checks.

    Parameters
    ----------
    arts : dict of str to Artefact
        The artefacts present (see :func:`ashc_cli.design.pipeline.load_all`).

    Returns
    -------
    dict
    """
    out = {}
    for name, art in arts.items():
        module = STAGES.get(name) or PRODUCTS.get(name)
        if module is None:          # a product this process has not loaded (the CLI loads them all)
            continue
        entry = module.summarise(art)
        entry["checks"] = {k: {"value": _num(c.value), "passed": c.passed, "description": c.description, "evidence": c.evidence}
                           for k, c in art.checks.items()}
        entry["provenance"] = {k: art.provenance.get(k) for k in ("spec_sha256", "created", "ashc_version", "sha256")}
        out[name] = no_negative_zero(entry)
    return out


def _num(x: float):
    return x + 0.0 if math.isfinite(x) else str(x)


def parse_point(text: str) -> dict[str, float]:
    """Parse ``--at a=1,b=2`` into a mapping.

    Parameters
    ----------
    text : str
        Comma-separated ``name=number`` items (spaces around them are ignored, as are empty items).

    Returns
    -------
    dict of str to float
        Name -> value, in the order given (a repeated name keeps its last value); -0 read as 0.

    Raises
    ------
    SpecError
        Naming the malformed item (no ``=``, no name, a value that is not a finite number), or when no item is given.
    """
    point: dict[str, float] = {}
    for item in filter(None, (s.strip() for s in text.split(","))):
        name, sep, value = item.partition("=")
        name = name.strip()
        if not sep or not name:
            raise SpecError("--at", f"item '{item}' is not name=value", "a list like xi=0.6156 or x1=1,x2=2")
        try:
            number = float(value)
        except ValueError:
            raise SpecError("--at", f"value of {name} is '{value.strip()}', not a number", "name=number") from None
        if not math.isfinite(number):
            raise SpecError("--at", f"value of {name} is not finite", "a finite number")
        point[name] = number + 0.0  # -0 is 0
    if not point:
        raise SpecError("--at", "no values given", "a list like xi=0.6156")
    return point


def _values(expr_matrix: sp.Matrix, point: dict[str, float], params: dict[str, float], name: str) -> np.ndarray:
    symbols = set().union(*(e.free_symbols for e in expr_matrix)) if expr_matrix else set()
    subs = {}
    missing = []
    for s in symbols:
        if s.name in point:
            subs[s] = sp.Float(point[s.name])
        elif s.name in params:
            subs[s] = sp.Float(params[s.name])
        else:
            missing.append(s.name)
    if missing:
        raise SpecError("--at", f"{name} needs a value for {', '.join(sorted(missing))}", f"--at with {', '.join(sorted(missing))}")
    out = []
    for e in expr_matrix:
        z = complex(e.xreplace(subs).evalf())
        out.append(z.real if abs(z.imag) <= 1e-12 * max(1.0, abs(z.real)) else math.nan)
    return np.array(out, dtype=float)


def _known_names(arts: dict[str, Artefact]) -> set[str]:
    """Every name the spec declared (stored with the artefacts) and every name a stored formula uses."""
    names: set[str] = set()
    for art in arts.values():
        for declared in art.provenance.get("names", {}).values():
            names |= set(declared)
        for matrix in art.exprs.values():
            for e in matrix:
                names |= {s.name for s in e.free_symbols}
    return names


def evaluate(arts: dict[str, Artefact], name: str, point: dict[str, float]) -> list[float]:
    """Evaluate a stored function (p, kappa, m, delta, b, c, theta) at a point.

    Parameters
    ----------
    arts : dict of str to Artefact
        The artefacts of a design.
    name : str
        One of :data:`EVALUABLE`.
    point : dict of str to float
        Values of the spec's own variable names (e.g. ``xi`` or ``x1..x4``); parameters come from the
        artefacts.

    Returns
    -------
    list of float
        The value, flattened row by row (a scalar is a one-element list).

    Raises
    ------
    SpecError
        If the name is unknown, a needed variable is missing, or a given name is not a design variable; or,
        for m and the b, c built from it, if y = h(x) at the point lies outside the set where m is certified
        (``inverse.m_domain``): m is a left inverse there only, and a Chebyshev interpolant extrapolates; for p and
        kappa, if xi lies outside V.
    ArtefactError
        If the stage holding the function has not been run (for m, b, c: also the inverse stage), or the
        inverse artefact does not record where m is certified.
    DesignError
        If the function is not real at the point.
    """
    if name not in EVALUABLE:
        raise SpecError("NAME", f"'{name}' cannot be evaluated", f"one of {', '.join(EVALUABLE)}")
    stage, key = EVALUABLE[name]
    if stage not in arts:
        raise ArtefactError(stage, f"no {stage}.h5 artefact in this folder", f"run `ashc {stage} SPEC --out DIR` first")
    art = arts[stage]
    params = art.provenance.get("parameters", {})
    unknown = set(point) - _known_names(arts) - set(params)
    if unknown:
        raise SpecError("--at", f"unknown variable(s) {', '.join(sorted(unknown))}", "names the spec declares (states, inputs, abstract states and inputs)")
    if name in BUILT_FROM_M:
        _require_certified(arts, name, point)
    if name in ON_V:
        _require_in_V(arts, name, point)
    if key is not None:
        values = _values(art.expr(key), point, params, name)
    else:
        values = _theta(art, point, params)
    if np.any(np.isnan(values)):
        raise DesignError(name, f"{name} is not real at {point}", "a point where it is defined (see `ashc summary`)")
    return no_negative_zero(values.tolist())


def _require_in_V(arts: dict[str, Artefact], name: str, point: dict[str, float]) -> None:
    """Refuse to evaluate p or kappa at an abstract state outside V (``manifold.V``), where eq. (14a) was not solved."""
    man = arts.get("manifold")
    if man is None or "V" not in man.values:
        return
    V = np.asarray(man.values["V"], dtype=float).reshape(-1, 2)
    names = (man.provenance.get("names") or {}).get("abstract_states", [])
    if len(names) != len(V) or not all(n in point for n in names):
        return   # a missing abstract state is refused where the expression is evaluated
    xi = np.array([point[n] for n in names], dtype=float)
    if outside_certified_set(V, xi):
        shown = ", ".join(f"{n}={v:.6g}" for n, v in zip(names, xi))
        raise SpecError(f"eval {name}", f"{shown} is outside V = {format_box(V)}, where p solves eq. (14a) (beyond it a fitted p extrapolates)",
                        f"a point of V = {format_box(V)}")


def _require_certified(arts: dict[str, Artefact], name: str, point: dict[str, float]) -> None:
    """Refuse to evaluate m (or b, c, built from it) at a state whose output h(x) is outside ``inverse.m_domain``."""
    if "inverse" not in arts:
        raise ArtefactError("inverse", f"no inverse.h5 artefact in this folder (it records where m, and so {name}, is certified)",
                            "run `ashc inverse SPEC --out DIR` first")
    inv = arts["inverse"]
    box, set_name, _ = certified_set(inv)
    h = inv.expr("h")
    y = _values(h, point, inv.provenance.get("parameters", {}), name)
    if outside_certified_set(box, y):
        shown = f"{y[0]:.6g}" if y.size == 1 else "[" + ", ".join(f"{v:.6g}" for v in y) + "]"
        built = "" if name == "m" else f" ({name} is built from m)"
        raise SpecError(f"eval {name}", f"y = h(x) = {shown} is outside the set where m is certified{built}, y in {set_name} = {format_box(box)}",
                        f"a state x with h(x) in {format_box(box)} (inverse.m_domain)")


def _theta(art: Artefact, point: dict[str, float], params: dict[str, float]) -> np.ndarray:
    """theta(xi, x) = sqrt(M) (dp/dxi delta - g(x) q(xi, x)) (eq. (37)) with the design's q."""
    dpd = _values(art.expr("dp_delta"), point, params, "theta").reshape(art.expr("dp_delta").shape)
    g = _values(art.expr("g"), point, params, "theta").reshape(art.expr("g").shape)
    L = np.asarray(art.value("L"))
    A, B = L.T @ dpd, L.T @ g
    if art.meta.get("interface_q") == "least_squares":
        A = A - B @ (np.linalg.pinv(B) @ A)
    return A.ravel()
