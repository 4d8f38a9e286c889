"""The design as code (issue 15): a finished design exported as one C99 file (with its header) or one numpy module.

``ashc export`` turns the stored expressions of a design into source code a controller can run without ashc:

``ashc_p(xi)``, ``ashc_kappa(xi)``
    The manifold map p (manifold stage) and the abstract output map kappa (kappa stage).
``ashc_m(x)``
    The left inverse m (inverse stage), evaluated only where it is certified: the output y = h(x) must lie in
    ``inverse.m_domain`` (widened by ``DOMAIN_RTOL``, as ``ashc eval`` and ``simulate`` test it).  It returns a
    status: ``0`` (ok), ``1`` (outside the certified set; the result is NaN) or ``2`` (m is not real there).
``ashc_interface(xi, x, v)``
    The interface u_w = SAT(l(xi) + K (x - p(xi)) + q(xi, x) v) of the set-point law (tests/oracle.py ``tracking_law``)
    (eqs. (15), (42), (44)): the feedback K (x - p) when the design synthesised a gain
    (``feedback: linear_gain``); q = pinv(L^T g(x)) L^T dp/dxi delta(xi) (eq. (43), with M = L L^T) or q = 0
    as the spec's ``interface.q`` says; SAT as ``interface.saturate`` says (clip per channel, scale the correction,
    or none).  Its arithmetic is the compiled loops' own (:mod:`ashc_cli.closedloop.interface`), printed by
    :mod:`ashc_cli.outputs.translate`.
``ashc_controller(xi, xi_ref)``
    The set-point abstract controller of the tracking scenario, v = clip(delta^+ (gain (xi_ref - xi) -
    phi_bar(xi)), -v_max, v_max), with gain and v_max from ``simulate.tracking.abstract_controller`` when the
    spec gives one, else as two more arguments; with ``abstract_controller.kind: registered`` the registered
    controller's own law (:mod:`ashc_cli.closedloop.controllers`, printed when it keeps to the subset
    :mod:`ashc_cli.outputs.translate` reads) with the spec's parameters.
``ashc_abstract_rhs(xi, v)``
    The abstract system's right-hand side phi_bar(xi) + delta(xi) v, to integrate xi on the controller.
``ashc_plan_reference(t)``, ``ashc_plan_controller(t, xi)`` (with a task)
    The task's plan (``ashc synthesize``; synthesize.h5 when it belongs to the design, else planned again): from
    ``switches[k]`` on, the set-point law with the plan's gain and v_max aims at ``references[k]``.  Integrated with
    ``ashc_abstract_rhs`` it replays the plan's xi; ``ashc eval DIR plan --at t=..[,xi=..]`` checks it.

The formulas are printed by sympy (``C99CodePrinter`` for C, ``NumPyPrinter`` for Python) after common
subexpressions are eliminated (``sympy.cse``, one pass per generated function); the spec's parameters stay
named constants (``#define PRM_<name>`` in C, ``PRM_<name> = ...`` in Python), the numbers of the design (U, V,
the certified set of m, K, L, gain, v_max) are constant arrays.  The C file allocates nothing and needs only
``math.h``; the Python module needs only numpy.

Pseudo-inverses (delta^+ for the controller, pinv(L^T g) for the least-squares q): a single column (or, in C,
a single row) in closed form, a^T / |a|^2 (zero for a zero vector), as :func:`ashc_cli.numerics.linalg.pinv`; any other shape by
numpy's ``pinv`` in Python and, in C, by a fixed-size one-sided Jacobi SVD whose cut-off is numpy's (singular
values at most 1e-15 times the largest are taken as zero), so rank-deficient matrices are handled as numpy does.

The functions here are pure (spec and artefacts in, source text out), except :func:`write_export`, which
writes the files; :func:`interface_value` evaluates the interface law with the tool's own numerics for
``ashc eval DIR u_w``.
"""


from __future__ import annotations

import re
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import sympy as sp

from ashc_cli.closedloop import controllers
from ashc_cli.closedloop.interface import interface_codes, interface_u
from ashc_cli.design.artefacts import Artefact
from ashc_cli.errors import DesignError, SpecError
from ashc_cli.problem.influence import cone_model
from ashc_cli.problem.model import lambdify
from ashc_cli.problem.spec import Spec

from ashc_cli.outputs.export_design import Design, TaskPlanExport, gather, require_current
from ashc_cli.outputs.printers import c_sources, python_source

__all__ = ["LANGUAGES", "export_sources", "check_target", "write_export", "interface_value", "interface_point"]

#: The languages ``ashc export --lang`` writes.
LANGUAGES = ("c", "python")


# --- the API the CLI calls ------------------------------------------------------------------------------


def _check_lang(lang: str) -> str:
    lang = str(lang).lower()
    if lang not in LANGUAGES:
        raise SpecError("--lang", f"'{lang}' is not a language ashc exports", " or ".join(LANGUAGES))
    return lang


def check_target(lang: str, output: str | Path) -> tuple[str, Path]:
    """Validate ``--lang`` and ``--output`` before any work (the CLI calls it before designing).

    Parameters
    ----------
    lang : str
        ``--lang`` (any case).
    output : str or Path
        ``--output``.

    Returns
    -------
    lang : str
        ``c`` or ``python``.
    output : Path

    Raises
    ------
    SpecError
        For another language, or an output name of the wrong kind: a C output must end in .c (its header
        goes beside it, .h), a Python one in .py with an importable module name.
    """
    lang = _check_lang(lang)
    output = Path(output)
    suffix = ".c" if lang == "c" else ".py"
    if output.suffix != suffix:
        raise SpecError("--output", f"'{output}' does not end in {suffix}", f"a file name ending in {suffix} for --lang {lang}")
    if lang == "python" and not output.stem.isidentifier():
        raise SpecError("--output", f"'{output.name}' is not an importable module name", "a name like cuk_design.py")
    if lang == "c" and not re.fullmatch(r"[A-Za-z0-9_.+-]+", output.stem):
        raise SpecError("--output", f"'{output.name}' cannot be named in an #include line", "a file name of letters, digits, '_', '-', '.'")
    return lang, output


def export_sources(spec: Spec, arts: Mapping[str, Artefact], lang: str, stem: str = "ashc_design", plan: TaskPlanExport | None = None) -> dict[str, str]:
    """The source text(s) of a design in one language, by file name.

    Parameters
    ----------
    spec : Spec
        The design's spec.
    arts : mapping of str to Artefact
        Its artefacts (stages :data:`NEEDED`); they are not checked against the spec here (see
        :func:`require_current`).
    lang : {"c", "python"}
        ``c``: ``<stem>.c`` and ``<stem>.h``; ``python``: ``<stem>.py``.
    stem : str
        The file names' stem.
    plan : TaskPlanExport, optional
        The task's plan (:func:`task_plan_export`), printed with the design.

    Returns
    -------
    dict of str to str
        File name to text.

    Raises
    ------
    SpecError
        For another language.
    DesignError
        If an expression cannot be written in the language.
    """
    lang = _check_lang(lang)
    design = gather(spec, arts, plan)
    controller = _registered(spec)
    if lang == "c":
        source, header = c_sources(design, f"{stem}.h", controller)
        return {f"{stem}.c": source, f"{stem}.h": header}
    return {f"{stem}.py": python_source(design, controller)}


def _registered(spec: Spec) -> tuple | None:
    """(Controller, its parameters) when the spec's tracking controller is ``kind: registered``, else None (the
    set-point law is printed)."""
    tr = spec.simulate.tracking
    if tr is None or tr.abstract_controller.kind != "registered":
        return None
    law = controllers.law_of(tr.abstract_controller)
    c = controllers.controller(law.kind)
    return c, np.asarray(c.prm(law), dtype=float)


def write_export(spec: Spec, arts: Mapping[str, Artefact], lang: str, output: str | Path, plan: TaskPlanExport | None = None) -> list[Path]:
    """Write the exported design: ``FILE.c`` and ``FILE.h`` beside it (C), or ``FILE.py`` (Python).

    Parameters
    ----------
    spec : Spec
        The design's spec; the artefacts must have been made from it (:func:`require_current`).
    arts : mapping of str to Artefact
        The design's artefacts.
    lang : {"c", "python"}
    output : str or Path
        The file to write (its folder is created if needed).
    plan : TaskPlanExport, optional
        The task's plan, exported with the design.

    Returns
    -------
    list of Path
        The files written.

    Raises
    ------
    SpecError
        For another language, or an output name of the wrong kind (a C output must end in .c, a Python one
        in .py).
    ArtefactError
        If an artefact is missing or was made from another spec.
    """
    lang, output = check_target(lang, output)
    require_current(spec, arts)
    texts = export_sources(spec, arts, lang, output.stem, plan)
    output.parent.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, text in texts.items():
        path = output.with_name(name)
        path.write_text(text, encoding="utf-8")
        paths.append(path)
    return paths


# --- ashc eval DIR u_w ----------------------------------------------------------------------------------


def interface_point(design: Design, point: Mapping[str, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split ``--at`` values into (xi, x, v) by the spec's names.

    Parameters
    ----------
    design : Design
        From :func:`gather`.
    point : mapping of str to float
        A value for every abstract state, state and abstract input, by name.

    Returns
    -------
    xi, x, v : ndarray
        In the spec's order.

    Raises
    ------
    SpecError
        If a name is not an abstract state, state or abstract input of the spec, or one is missing.
    """
    wanted = [*design.abstract_states, *design.states, *design.abstract_inputs]
    unknown = sorted(set(point) - set(wanted))
    if unknown:
        raise SpecError("--at", f"unknown variable(s) {', '.join(unknown)} for u_w", f"the names {', '.join(wanted)}")
    missing = [name for name in wanted if name not in point]
    if missing:
        raise SpecError("--at", f"u_w needs a value for {', '.join(missing)}", f"--at with {', '.join(wanted)}")
    pick = lambda names: np.array([float(point[k]) for k in names], dtype=float)  # noqa: E731
    return pick(design.abstract_states), pick(design.states), pick(design.abstract_inputs)


def interface_value(spec: Spec, arts: Mapping[str, Artefact], point: Mapping[str, float]) -> list[float]:
    """The interface law u_w(xi, x, v) at a point, with the tool's own numerics (for ``ashc eval DIR u_w``).

    The same law as the set-point law (tests/oracle.py ``tracking_law``)'s u: SAT(l(xi) + K (x - p(xi)) + q(xi, x) v),
    the terms lambdified from the spec and the artefacts, the law by :func:`ashc_cli.closedloop.interface.interface_u`
    (the compiled loops' functions).

    Parameters
    ----------
    spec : Spec
        The design's spec (l, g, U and the interface are in no artefact).
    arts : mapping of str to Artefact
        The design's artefacts, made from ``spec``.
    point : mapping of str to float
        Every abstract state, state and abstract input, by the spec's names (``--at xi=..,x1=..,v=..``).

    Returns
    -------
    list of float
        u_w, one value per input.

    Raises
    ------
    SpecError
        For a missing or unknown name.
    ArtefactError
        If an artefact is missing or was made from another spec.
    DesignError
        If u_w is not a finite real number at the point.
    """
    require_current(spec, arts)
    d = gather(spec, arts)
    xi, x, v = interface_point(d, point)
    model = cone_model(spec)
    values = model.values

    def at(matrix, args, arrays):
        return lambdify(matrix, list(args), values)(*arrays).reshape(sp.Matrix(matrix).shape)

    ls = d.q == "least_squares"
    l = at(d.l, model.xi, xi)[:, 0]
    pm = at(d.p, model.xi, xi)[:, 0]
    g = at(d.g, model.x, x) if ls else np.zeros((d.n, d.n_inputs))
    dpd = at(d.dp_delta, model.xi, xi) if ls else np.zeros((d.n, d.m_hat))
    u = interface_u(l, d.K, x, pm, d.L if ls else None, g, dpd, v, d.U, interface_codes(d.q, d.saturate))
    if not np.all(np.isfinite(u)):
        raise DesignError("u_w", f"u_w is not real at {dict(point)}", "a point where l, p, g and dp/dxi delta are defined")
    return [float(value) + 0.0 for value in u]


def task_plan_export(spec: Spec, arts: Mapping[str, Artefact], stored: Artefact | None = None) -> TaskPlanExport:
    """The task's plan for the export and ``ashc eval DIR plan``: read from ``synthesize.h5`` when it is current
    (``stored``), else planned again (deterministic: :func:`ashc_cli.design.task_plan.plan_task`, what synthesize and
    simulate run).

    Parameters
    ----------
    spec : Spec
        A spec with a task.
    arts : mapping of str to Artefact
        The design's artefacts, made from ``spec``.
    stored : Artefact, optional
        The folder's synthesize artefact, if it belongs to this design.

    Returns
    -------
    TaskPlanExport

    Raises
    ------
    SpecError
        If the spec has no task.
    DesignError
        If no tolerance EPS gives a plan (naming the part of the task).
    """
    if spec.task is None:
        raise SpecError("task", "missing", "a task on the output (docs/spec-format.md, 'task') to export or evaluate its plan")
    if stored is not None:
        v = stored.values
        switches = np.asarray(v["switch_times"], dtype=float).reshape(-1)
        refs = np.asarray(v["references"], dtype=float).reshape(len(spec.abstract.states), -1).T     # stored (n_hat, segments)
        return TaskPlanExport(switches, refs[:switches.size], float(v["gain"]), float(v["v_max"]), float(v["tolerance"]),
                              np.asarray(v["xi0"], dtype=float).reshape(-1), "held" if stored.meta.get("planner") in ("grid", "error_aware") else "setpoint")
    from ashc_cli.design import task_plan
    from ashc_cli.design.pipeline import design_model

    return TaskPlanExport.of(task_plan.plan_task(design_model(spec, arts), arts))


def plan_value(plan: TaskPlanExport, spec: Spec, arts: Mapping[str, Artefact], point: Mapping[str, float]) -> tuple[str, list[float]]:
    """The plan at a point, with the tool's own numerics (``ashc eval DIR plan``): its reference xi_ref(t) at ``t``
    alone; with the abstract state too, the abstract input v(t, xi) of its set-point law (the exported
    ``ashc_plan_controller``); a table of held inputs (law ``held``) gives the period's input v_held(t) either way.

    Parameters
    ----------
    plan : TaskPlanExport
    spec : Spec
    arts : mapping of str to Artefact
    point : mapping of str to float
        ``t``, and optionally every abstract state by the spec's names.

    Returns
    -------
    what : str
        ``xi_ref``, ``v`` or ``v_held``.
    values : list of float

    Raises
    ------
    SpecError
        Without t, or with some abstract states but not all, or with another name.
    """
    names = list(spec.abstract.states)
    extra = sorted(set(point) - {"t", *names})
    given = ", ".join(f"{k}={point[k]:g}" for k in point) or "nothing"
    want = f"t=T (the plan's reference), or t and every abstract state ({', '.join(names)}) for its v"
    if "t" not in point:
        raise SpecError("--at", f"no t given (got {given})", want)
    if extra or (set(names) & set(point) and not set(names) <= set(point)):
        raise SpecError("--at", f"{given}: " + (f"unknown {', '.join(extra)}" if extra else "some abstract states but not all"), want)
    ref = plan.reference(point["t"])
    if plan.law == "held":      # a table of held inputs (the grid planner, error-aware planning): the period's input, whatever xi is
        m_hat = len(spec.abstract.inputs)
        return "v_held", [float(r) for r in np.ravel(ref)[:m_hat]]
    if not set(names) <= set(point):
        return "xi_ref", [float(r) for r in ref]
    from ashc_cli.closedloop.laws import held_law, setpoint_law
    from ashc_cli.closedloop.terms import DesignTerms
    from ashc_cli.design.pipeline import design_model

    xi = np.array([float(point[k]) for k in names])
    at = DesignTerms(design_model(spec, arts), arts).at_xi(xi)
    phi = np.ascontiguousarray(np.asarray(at[0], dtype=float).reshape(-1))
    delta = np.ascontiguousarray(np.asarray(at[1], dtype=float).reshape(len(names), -1))
    v = np.empty(delta.shape[1])
    (held_law if plan.law == "held" else setpoint_law)(float(point["t"]), np.ascontiguousarray(xi), np.ascontiguousarray(ref, dtype=float),
                                                      phi, delta, plan.prm, v)
    return "v", [float(x) for x in v]

