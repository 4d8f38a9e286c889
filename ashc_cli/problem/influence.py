"""The output's cone of influence: which states can influence y = h(x) through the dependency graph of f.

State x_j influences x_i when f_i reads x_j (x_j appears in f_i); y is influenced by the states h reads and, through
the graph, by every state from which a path leads to them.  A state outside the cone evolves without ever acting on
y: its modes (a position that integrates a speed, a state with x' = 0) need not contract for the output to be
tracked, but the first stage certifies every state of the spec, so such a state is better left out of it.
"""

from __future__ import annotations

from ashc_cli.problem.model import Model

__all__ = ["output_cone"]


def output_cone(model: Model) -> tuple[list[int], list[int]]:
    """The states that influence y and those that cannot (indices into ``model.x``, increasing).

    Parameters
    ----------
    model : Model
        The spec's systems (f, h).

    Returns
    -------
    inside, outside : list of int
        The states from which a path of the dependency graph of f leads to a state h reads (h's states included), and
        the rest.
    """
    index = {s: k for k, s in enumerate(model.x)}
    reads = [sorted(index[s] for s in e.free_symbols if s in index) for e in model.f]
    inside = {index[s] for e in model.h for s in e.free_symbols if s in index}
    todo = list(inside)
    while todo:
        i = todo.pop()
        for j in reads[i]:
            if j not in inside:
                inside.add(j)
                todo.append(j)
    return sorted(inside), [k for k in range(model.n) if k not in inside]
