"""The output's cone of influence: which states can influence y = h(x) through the dependency graph of f.

State x_j influences x_i when f_i reads x_j (x_j appears in f_i); y is influenced by the states h reads and, through
the graph, by every state from which a path leads to them.  A state outside the cone evolves without ever acting on
y: its modes (a position that integrates a speed, a state with x' = 0) need not contract for the output to be
tracked, but the first stage certifies every state of the spec, so such a state is better left out of it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import sympy as sp

from ashc_cli.problem.model import Model, build_model
from ashc_cli.problem.spec import Spec

__all__ = ["output_cone", "on_the_cone", "cone_model", "Beside"]


def output_cone(model: Model) -> tuple[list[int], list[int]]:
    """The states that influence y and those that cannot (indices into ``model.x``, increasing).

    Parameters
    ----------
    model : Model
        The spec's systems (f, h).

    Returns
    -------
    inside, outside : list of int
        The states from which a path of the dependency graph of f (and of a disturbance's e) leads to a state h reads
        (h's states included), and the rest.
    """
    index = {s: k for k, s in enumerate(model.x)}
    # row i of f, and of e (a disturbance's input matrix acts on x_i' too): what x_i' reads
    rows = [model.f[i].free_symbols | (set().union(*(e.free_symbols for e in model.e.row(i))) if model.e is not None else set())
            for i in range(model.n)]
    reads = [sorted(index[s] for s in r if s in index) for r in rows]
    inside = {index[s] for e in model.h for s in e.free_symbols if s in index}
    todo = list(inside)
    while todo:
        i = todo.pop()
        for j in reads[i]:
            if j not in inside:
                inside.add(j)
                todo.append(j)
    return sorted(inside), [k for k in range(model.n) if k not in inside]


@dataclass(frozen=True)
class Beside:
    """The states left out of the design (outside the output's cone): driven by the plant, integrated beside the
    closed loop by ``simulate``, never acting on y.

    Attributes
    ----------
    names : tuple of str
        The states left out, in the spec's order.
    index, kept : tuple of int
        Their indices into the spec's states, and those of the states designed on.
    f : sympy Matrix
        Their right-hand sides, in the full plant's symbols.
    x, u : sympy Matrix
        The full plant's states and inputs.
    x0 : ndarray
        Their start: the spec's tracking ``x0`` where it lists every state, else the centre of ``state_box`` (0
        without one).
    values : dict
        The spec's parameters.
    e : sympy Matrix or None
        Their rows of e(x), for a run with a constant disturbance.
    """

    names: tuple[str, ...]
    index: tuple[int, ...]
    kept: tuple[int, ...]
    f: sp.Matrix
    x: sp.Matrix
    u: sp.Matrix
    x0: np.ndarray
    values: dict
    #: Their rows of the disturbance's input matrix e(x) (k x d), or None.
    e: sp.Matrix | None = None

    def line(self) -> str:
        """The design line's note: which states were left out, and why."""
        return f"left out {', '.join(self.names)} (no path of f leads from them to y: simulate integrates them beside the loop)"


def _rows(seq, keep):
    return None if seq is None else [seq[k] for k in keep]


def _restrict(section: dict, keys, keep) -> None:
    """The per-state lists of a spec section restricted to the kept states, where the spec gives them."""
    for key in keys:
        if isinstance(section.get(key), list):
            section[key] = _rows(section[key], keep)


def on_the_cone(spec: Spec, model: Model) -> tuple[Spec, Beside | None]:
    """The spec restricted to the output's cone (:func:`output_cone`), and the states left out; the spec itself and
    None when every state influences y (or none does: an output that reads no state is refused by the stages), or when the abstraction has more states than y has outputs (its extra
    directions are the user's choice of what to plan on, and may be states y cannot see) or a given ``abstract.m``
    reads a state outside the cone.

    Every per-state entry of the spec is restricted to the kept states: concrete (states, f_bar, g, f, state_box, e),
    stabilisability (M, K, linearise_at.x), abstract (manifold_guess, p) and the starts (tracking and task x0,
    m_relation x0).  The kept states' f never reads a left-out state (that would be a path to y), so the
    restricted plant is the plant seen from y.

    Parameters
    ----------
    spec : Spec
    model : Model
        The spec's model (its f and h give the cone).

    Returns
    -------
    Spec, Beside or None
    """
    keep, out = output_cone(model)
    outside = {model.x[k] for k in out}
    if not out or not keep or model.n_hat > model.p or (model.m_given is not None and model.m_given.free_symbols & outside):
        # with more abstract states than outputs the abstraction itself has directions y does not see, which may
        # live in the states outside the cone (a bilinear plant's x2 in m = ((x1 + x3) / (1 + 2 x2), x2)); a given
        # m that reads such a state means it too: keep them
        return spec, None
    # exclude_unset: the restricted spec sets what the spec set, so defaults read from model_fields_set stay defaults
    d = spec.model_dump(mode="python", exclude_unset=True)
    _restrict(d.get("concrete", {}), ("states", "f_bar", "g", "f", "state_box", "e"), keep)
    _restrict(d.get("abstract", {}), ("manifold_guess", "p"), keep)
    s = d.get("stabilisability", {})
    if isinstance(s.get("M"), list):
        s["M"] = [[row[j] for j in keep] for row in _rows(s["M"], keep)]
    if isinstance(s.get("K"), list):
        s["K"] = [[row[j] for j in keep] for row in s["K"]]
    if isinstance(s.get("linearise_at"), dict) and "x" in s["linearise_at"]:
        s["linearise_at"]["x"] = _rows(s["linearise_at"]["x"], keep)
    sim = d.get("simulate", {})
    tracking = sim.get("tracking") or {}
    full_x0 = tracking.get("x0") if isinstance(tracking.get("x0"), list) else None
    for where in (tracking, sim.get("m_relation") or {}, d.get("task") or {}):
        if isinstance(where.get("x0"), list) and len(where["x0"]) == model.n:
            where["x0"] = _rows(where["x0"], keep)
    reduced = type(spec).model_validate(d)
    box = model.state_box
    x0 = (np.asarray(full_x0, dtype=float)[out] if full_x0 is not None else
          (np.mean(np.asarray(box, dtype=float)[out], axis=1) if box is not None else np.zeros(len(out))))
    beside = Beside(tuple(str(model.x[k]) for k in out), tuple(out), tuple(keep), sp.Matrix([model.f[k] for k in out]),
                    sp.Matrix(model.x), sp.Matrix(model.u), x0, dict(model.values),
                    None if model.e is None else sp.Matrix([list(model.e.row(k)) for k in out]))
    return reduced, beside


def cone_model(spec: Spec) -> Model:
    """The model the design works on: the spec's, or the one of its output's cone with the states left out in
    ``beside`` (:func:`on_the_cone`).

    Parameters
    ----------
    spec : Spec

    Returns
    -------
    Model
    """
    full = build_model(spec)
    reduced, beside = on_the_cone(spec, full)
    if beside is None:
        return full
    return dataclasses.replace(build_model(reduced), beside=beside)
