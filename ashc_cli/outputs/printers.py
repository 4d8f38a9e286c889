"""The printers of ``ashc export``: a :class:`~ashc_cli.outputs.export_design.Design` as one C99 file with its header
(:func:`c_sources`) or one numpy module (:func:`python_source`).  The formulas are printed by sympy
(``C99CodePrinter``, ``NumPyPrinter``) after common subexpressions are eliminated; the pseudo-inverses are written
out as :mod:`ashc_cli.outputs.export` describes."""

from __future__ import annotations

import math
import re
from collections.abc import Sequence

import numpy as np
import sympy as sp
from sympy.printing.c import C99CodePrinter
from sympy.printing.numpy import NumPyPrinter

from ashc_cli import __version__
from ashc_cli.errors import DesignError
from ashc_cli.problem.model import parameter_symbol, state_symbol
from ashc_cli.design.upstream import DOMAIN_RTOL

from ashc_cli.closedloop import interface as law
from ashc_cli.closedloop.compiled import interface_codes
from ashc_cli.closedloop.laws import held_law, pinv_into, setpoint, setpoint_direction, setpoint_law
from ashc_cli.outputs import translate
from ashc_cli.outputs.export_design import NEEDED, Design
from ashc_cli.numerics.linalg import lower_bandwidth

__all__ = ["c_sources", "python_source", "PINV_RCOND", "JACOBI_SWEEPS"]

#: numpy.linalg.pinv's default cut-off: singular values <= PINV_RCOND * the largest are taken as zero.
PINV_RCOND = 1e-15
#: Sweeps of the C pseudo-inverse's Jacobi SVD at most (it converges in a handful for the small sizes here).
JACOBI_SWEEPS = 60
#: The laws the exported interface and controller run: the compiled loops' own functions, printed (callees first).
#: pinv_into is numpy's pinv in Python and the Jacobi SVD below in C.
LAWS = (pinv_into, law.saturate, law.feedback_of, law.lt_times, law.q_of, law.times, law.apply, setpoint_direction, setpoint, setpoint_law,
        held_law)


def _name(fn) -> str:
    return getattr(fn, "py_func", fn).__name__


def _needed(called: set[str], extra=()) -> list:
    """The functions of :data:`LAWS` and ``extra`` (a registered controller's law) that ``called`` (names) reach,
    callees first."""
    laws = LAWS + tuple(fn for fn in extra if fn not in LAWS)
    calls = {_name(fn): translate.calls(fn) for fn in laws}
    want, todo = set(), list(called)
    while todo:
        name = todo.pop()
        if name in calls and name not in want:
            want.add(name)
            todo += list(calls[name])
    return [fn for fn in laws if _name(fn) in want]


def _c_laws(called: set[str], pinv_kinds: tuple[bool, bool], extra=()) -> list[str]:
    """The C text of the laws ``called`` reaches (:func:`ashc_cli.outputs.translate.c_function`), pinv_into
    written on the helpers the design needs: (pinv_vector exists, pinv_small exists)."""
    known: dict = {}
    lines: list[str] = []
    for fn in _needed(called, extra):
        name = _name(fn)
        if fn is pinv_into:
            vector, general = pinv_kinds
            body = (["    if (a_rows == 1 || a_cols == 1) pinv_vector(a_rows * a_cols, a, out);", "    else pinv_small(a_rows, a_cols, a, out);"]
                    if vector and general else ["    pinv_vector(a_rows * a_cols, a, out);"] if vector else ["    pinv_small(a_rows, a_cols, a, out);"])
            lines += ["/* out = pinv(a) (cols x rows): a single row or column a^T / |a|^2, else the Jacobi SVD above */",
                      "static void pinv_into(const double *a, int a_rows, int a_cols, double *out, int out_rows, int out_cols)",
                      "{", "    (void)out_rows;", "    (void)out_cols;", *body, "}", ""]
        else:
            lines += translate.c_function(fn, known)
        known[name] = translate.header(fn, known)
    return lines


# --- printing --------------------------------------------------------------------------------------------


class _CPrinter(C99CodePrinter):
    """sympy's C99 printer for strict C99: no M_PI-style macros (POSIX, not C99), numbers as literals, and
    integers beyond ``int`` written as doubles."""

    def __init__(self):
        super().__init__({"math_macros": {}, "strict": True})

    def _print_Pi(self, expr):
        return repr(math.pi)

    def _print_Exp1(self, expr):
        return repr(math.e)

    def _print_NumberSymbol(self, expr):
        return repr(float(expr))

    def _print_Integer(self, expr):
        value = int(expr)
        return f"{value}.0" if abs(value) > 2**31 - 1 else str(value)

    def _print_Float(self, expr):
        return _float_text(expr)


class _PythonPrinter(NumPyPrinter):
    """sympy's numpy printer, with every float written to the last bit (its default keeps 15 digits)."""

    def __init__(self):
        super().__init__({"fully_qualified_modules": True, "strict": True})

    def _print_Float(self, expr):
        return _float_text(expr)


def _float_text(expr) -> str:
    """A sympy Float as the shortest literal that reads back as the same double."""
    value = float(expr)
    if not math.isfinite(value):
        raise DesignError("export", f"an expression holds the number {value}", "finite numbers")
    return repr(value)


def _renamer(design: Design):
    """A function mapping an expression in the spec's symbols to one in the generated code's names:
    ``xi[i]``, ``x[i]`` and ``PRM_<name>`` (by name, so symbols read back with other assumptions match)."""
    # With the assumptions of the model's symbols (real states, parameters signed as their values), so that
    # rebuilding an expression in the new names cannot rewrite it.
    names = {name: state_symbol(f"xi[{i}]") for i, name in enumerate(design.abstract_states)}
    names.update({name: state_symbol(f"x[{i}]") for i, name in enumerate(design.states)})
    names.update({name: parameter_symbol(f"PRM_{name}", value) for name, value in design.parameters.items()})

    def rename(expr, what: str):
        expr = sp.sympify(expr)
        subs = {}
        for s in sorted(expr.free_symbols, key=lambda s: s.name):
            if s.name not in names:
                raise DesignError(f"export.{what}", f"uses '{s.name}', which is neither a state nor a parameter of the spec",
                                  "expressions in the spec's states and parameters")
            subs[s] = names[s.name]
        return expr.xreplace(subs)

    return rename


def _assignments(outputs: Sequence[tuple[str, sp.MatrixBase]], rename, lang: str, indent: str = "    ") -> list[str]:
    """Statements setting each ``array[k]`` to entry k (row-major) of its matrix, after sympy's CSE."""
    targets, exprs = [], []
    for array, matrix in outputs:
        for k, e in enumerate(sp.Matrix(matrix)):
            targets.append(f"{array}[{k}]")
            exprs.append(rename(e, array))
    replacements, reduced = sp.cse(exprs, symbols=sp.numbered_symbols("cse"))
    printer = _CPrinter() if lang == "c" else _PythonPrinter()
    try:
        if lang == "c":
            lines = [f"const double {s} = {printer.doprint(e)};" for s, e in replacements]
            lines += [f"{t} = {printer.doprint(e)};" for t, e in zip(targets, reduced)]
        else:
            lines = [f"{s} = {printer.doprint(e)}" for s, e in replacements]
            lines += [f"{t} = {printer.doprint(e)}" for t, e in zip(targets, reduced)]
    except Exception as exc:  # a function the printer cannot write (sympy's PrintMethodNotImplementedError and kin)
        raise DesignError("export", f"an expression cannot be written in {'C99' if lang == 'c' else 'Python'}: {' '.join(str(exc).split())[:200]}",
                          "expressions of the spec's whitelisted functions") from None
    out = []
    for line in lines:
        out.extend(indent + part for part in line.splitlines())
    return out


def _num(value: float) -> str:
    """A double as a literal that reads back exactly (parenthesised when negative, for macros)."""
    value = float(value)
    if not math.isfinite(value):
        raise DesignError("export", f"a constant of the design is {value}", "finite numbers (U, V, m_domain, K, L)")
    text = repr(value + 0.0)
    return f"({text})" if text.startswith("-") else text


def _c_rows(array: np.ndarray) -> str:
    """A 2-D array as a C initialiser."""
    return "{" + ", ".join("{" + ", ".join(_num(v) for v in row) + "}" for row in np.atleast_2d(array)) + "}"


def _py_rows(array: np.ndarray) -> str:
    return "numpy.array([" + ", ".join("[" + ", ".join(repr(float(v) + 0.0) for v in row) + "]" for row in np.atleast_2d(array)) + "])"


def _guard_name(name: str) -> str:
    return "ASHC_" + re.sub(r"[^A-Za-z0-9]", "_", name).upper() + "_H"


def _head_comment(design: Design, what: str) -> list[str]:
    return [f"Generated by ashc {__version__} (`ashc export`) from design '{design.name}': {what}; do not edit.",
            f"spec SHA-256 {design.provenance['spec']};",
            "artefacts: " + ", ".join(f"{stage}.h5 {design.provenance[stage][:16]}" for stage in NEEDED) + "."]


def _saturate_text(saturate) -> str:
    if saturate == "scale":
        return "scale: l + s (correction) with the largest s in [0, 1] that keeps u in U"
    return "clip each channel to U" if saturate else "none (u may leave U)"


# --- C ---------------------------------------------------------------------------------------------------


def c_sources(design: Design, header_name: str = "ashc_design.h", controller=None) -> tuple[str, str]:
    """The C99 source and header of a design.

    Parameters
    ----------
    design : Design
        From :func:`gather`.
    header_name : str
        The header's file name, which the source includes.
    controller : (Controller, prm), optional
        A registered abstract controller (:mod:`ashc_cli.closedloop.controllers`, one with a printed law) and its
        parameters for ``ashc_controller``; default the set-point law with the spec's gain and v_max (else
        arguments).

    Returns
    -------
    source, header : str
    """
    d = design
    controller_args = "const double *xi, const double *xi_ref, double *v" if d.gain is not None or controller is not None else \
        "const double *xi, const double *xi_ref, double gain, double v_max, double *v"
    source = _c_preamble(d, header_name, controller) + _c_terms(d) + _c_controller(d, controller_args, controller) + _c_plan(d)
    return "\n".join(source), "\n".join(_c_header(d, controller_args, controller))


def _plan_law(d: Design):
    """The law the task's plan runs: the set-point law, or the grid planner's held input."""
    return held_law if d.plan.law == "held" else setpoint_law


def _plan_calls(d: Design) -> set[str]:
    """The laws the task's plan calls, none without a plan."""
    return {_name(_plan_law(d))} if d.plan is not None else set()


def _plan_says(d: Design) -> str:
    if d.plan.law == "held":
        return (f"The task's plan (ashc synthesize, the grid planner): from t = switches[k] on, v = references[k] (its first abstract "
                f"inputs), held, |v_a| <= v_max {d.plan.v_max:.6g}: the proved table's inputs along its route from xi0; it keeps "
                f"|psi - y| <= EPS = {d.plan.eps:.6g} (budget mode, eq. (38))")
    return (f"The task's plan (ashc synthesize): from t = switches[k] on, the set-point law with gain {d.plan.gain:.6g} and "
            f"v_max {d.plan.v_max:.6g} aims at references[k]; it keeps |psi - y| <= EPS = {d.plan.eps:.6g} (budget mode, eq. (38))")


def _c_plan(d: Design) -> list[str]:
    """ashc_plan_reference(t, xi_ref) and ashc_plan_controller(t, xi, v): the task's plan, none without one."""
    if d.plan is None:
        return []
    K = len(d.plan.switches)
    P, prm = (1, "ASHC_PLAN_V_MAX") if d.plan.law == "held" else (2, "ASHC_PLAN_GAIN, ASHC_PLAN_V_MAX")
    return [f"const double ashc_plan_switches[ASHC_PLAN_SEGMENTS] = {{{', '.join(_num(x) for x in d.plan.switches)}}};",
            f"const double ashc_plan_references[ASHC_PLAN_SEGMENTS][{NAS}] = {_c_rows(d.plan.refs)};", "",
            "void ashc_plan_reference(double t, double *xi_ref)", "{", "    int k = 0, i;",
            f"    while (k + 1 < {K} && t >= ashc_plan_switches[k + 1]) k++;",
            f"    for (i = 0; i < {NAS}; i++) xi_ref[i] = ashc_plan_references[k][i];", "}", "",
            "void ashc_plan_controller(double t, const double *xi, double *v)", "{",
            f"    double ref[{NAS}], phi[{NAS}], delta[{NAS} * {NAI}];", f"    const double prm[{P}] = {{{prm}}};",
            "    ashc_plan_reference(t, ref);", "    abstract_terms(xi, phi, delta);",
            f"    {_name(_plan_law(d))}(t, xi, {NAS}, ref, {NAS}, phi, {NAS}, delta, {NAS}, {NAI}, prm, {P}, v, {NAI});", "}", ""]


def _c_plan_header(d: Design) -> list[str]:
    """The plan's constants and prototypes in the header, none without a plan."""
    if d.plan is None:
        return []
    return [f"/* {_plan_says(d)}. */", f"#define ASHC_PLAN_SEGMENTS {len(d.plan.switches)}",
            f"#define ASHC_PLAN_GAIN {_num(d.plan.gain)}", f"#define ASHC_PLAN_V_MAX {_num(d.plan.v_max)}",
            f"#define ASHC_PLAN_EPS {_num(d.plan.eps)}",
            "extern const double ashc_plan_switches[ASHC_PLAN_SEGMENTS];   /* s: when each segment starts */",
            f"extern const double ashc_plan_references[ASHC_PLAN_SEGMENTS][{NAS}];   /* xi_ref of each segment */",
            "/* xi_ref: the plan's reference at time t. */", "void ashc_plan_reference(double t, double *xi_ref);",
            "/* v: the plan's abstract input at time t and abstract state xi. */",
            "void ashc_plan_controller(double t, const double *xi, double *v);", ""]


def _py_plan(d: Design) -> list[str]:
    """ashc_plan_reference(t) and ashc_plan_controller(t, xi) in the Python export, none without a plan."""
    if d.plan is None:
        return []
    return [f"#: {_plan_says(d)}.", f"PLAN_SWITCHES = numpy.array([{', '.join(repr(float(x)) for x in d.plan.switches)}])",
            f"PLAN_REFERENCES = numpy.array({np.asarray(d.plan.refs, dtype=float).tolist()!r})",
            f"PLAN_GAIN, PLAN_V_MAX, PLAN_EPS = {float(d.plan.gain)!r}, {float(d.plan.v_max)!r}, {float(d.plan.eps)!r}", "", "",
            "def ashc_plan_reference(t):", '    """The plan\'s reference xi_ref at time t."""',
            "    k = max(int(numpy.searchsorted(PLAN_SWITCHES, float(t), side='right')) - 1, 0)",
            "    return PLAN_REFERENCES[k].copy()", "", "",
            "def ashc_plan_controller(t, xi):", '    """The plan\'s abstract input v at time t and abstract state xi."""',
            "    xi = numpy.ascontiguousarray(xi, dtype=float)", "    phi, delta = _abstract_terms(xi)", "    v = numpy.empty(N_ABSTRACT_INPUTS)",
            f"    {_name(_plan_law(d))}(float(t), xi, ashc_plan_reference(t), phi, delta, numpy.array("
            f"{'[PLAN_V_MAX]' if d.plan.law == 'held' else '[PLAN_GAIN, PLAN_V_MAX]'}), v)",
            "    return v", "", ""]


def _law_of(d: Design, controller) -> tuple:
    """(printed law, C text of its parameters or None for the set-point's gain and v_max, count, one-line law)."""
    if controller is None:
        return setpoint_law, None, 2, "v = clip(delta(xi)^+ (gain (xi_ref - xi) - phi_bar(xi)), -v_max, v_max): the set-point abstract controller"
    c, prm = controller
    if c.printed is None:
        raise DesignError("abstract_controller.kind", repr(c.name), "a controller whose law is printed (Controller.printed)")
    prm = np.asarray(prm, dtype=float).reshape(-1)
    return c.printed, prm, prm.size, f"{c.says}: the abstract controller {c.name}"


#: The C macros of the design's dimensions.
NS, NI, NAS, NAI, NO = "ASHC_N_STATES", "ASHC_N_INPUTS", "ASHC_N_ABSTRACT_STATES", "ASHC_N_ABSTRACT_INPUTS", "ASHC_N_OUTPUTS"


def _c_header(d: Design, controller_args: str, controller=None) -> list[str]:
    """The header's lines: dimensions, status codes, constants and the prototypes."""
    ls, has_gain = d.q == "least_squares", d.gain is not None

    h = ["/*", *(" * " + line for line in _head_comment(d, "its interface, abstract controller, p, kappa and m")), " */",
         f"#ifndef {_guard_name(d.name)}", f"#define {_guard_name(d.name)}", "",
         "#ifdef __cplusplus", 'extern "C" {', "#endif", "",
         f"#define {NS} {d.n}            /* x: {', '.join(d.states)} */",
         f"#define {NI} {d.n_inputs}            /* u: {', '.join(d.inputs)} */",
         f"#define {NAS} {d.n_hat}   /* xi: {', '.join(d.abstract_states)} */",
         f"#define {NAI} {d.m_hat}   /* v: {', '.join(d.abstract_inputs)} */",
         f"#define {NO} {d.n_outputs}           /* y = h(x), psi = kappa(xi) */", "",
         "/* Status of ashc_m. */", "#define ASHC_OK 0",
         "#define ASHC_OUTSIDE_CERTIFIED_SET 1   /* h(x) is not in ashc_m_domain: m is not certified there (xi set to NaN) */",
         "#define ASHC_NOT_REAL 2                /* m(x) is not a finite real number */", "",
         "/* Relative widening of ashc_m_domain (times max(1, width)) within which m is still evaluated. */",
         f"#define ASHC_M_DOMAIN_RTOL {_num(DOMAIN_RTOL)}", ""]
    if has_gain:
        h += ["/* The set-point controller's gain and bound on |v| (spec simulate.tracking.abstract_controller). */",
              f"#define ASHC_GAIN {_num(d.gain)}", f"#define ASHC_V_MAX {_num(d.v_max)}", ""]
    h += [f"extern const double ashc_input_bounds[{NI}][2];          /* U: [lo, hi] per input */",
          f"extern const double ashc_abstract_domain[{NAS}][2];  /* V: [lo, hi] per abstract state */",
          f"extern const double ashc_m_domain[{NO}][2];             /* where m is certified ({d.m_domain_set}): h(x) in this box */", "",
          "/* p(xi): the manifold map (n values). */", "void ashc_p(const double *xi, double *p);",
          "/* psi = kappa(xi): the abstract output (one value per output). */", "void ashc_kappa(const double *xi, double *psi);",
          "/* xi = m(x), the left inverse, only where certified: returns ASHC_OK, ASHC_OUTSIDE_CERTIFIED_SET or ASHC_NOT_REAL. */",
          "int ashc_m(const double *x, double *xi);",
          f"/* u = SAT(l(xi){' + K (x - p(xi))' if d.K is not None else ''}{' + q(xi, x) v' if ls else ''}): the interface (saturation: {_saturate_text(d.saturate)}). */",
          "void ashc_interface(const double *xi, const double *x, const double *v, double *u);",
          f"/* {_law_of(d, controller)[3]}. */",
          f"void ashc_controller({controller_args});",
          "/* dxi = phi_bar(xi) + delta(xi) v: the abstract system, to integrate xi. */",
          "void ashc_abstract_rhs(const double *xi, const double *v, double *dxi);", "",
          *_c_plan_header(d),
          "#ifdef __cplusplus", "}", "#endif", "", f"#endif /* {_guard_name(d.name)} */", ""]

    return h


def _c_preamble(d: Design, header_name: str, controller=None) -> list[str]:
    """The source's comment, includes, parameters, constant arrays and the pseudo-inverse helpers."""
    ls = d.q == "least_squares"
    pinv_uses = [(d.n_hat, d.m_hat)] + ([(d.n, d.n_inputs)] if ls else [])
    general = [shape for shape in pinv_uses if min(shape) > 1]
    vector = [shape for shape in pinv_uses if min(shape) == 1]
    c = ["/*", *(" * " + line for line in _head_comment(d, "C99, math.h only, no allocation")),
         " *", f" * Arrays are row-major; xi[i] is abstract state i ({', '.join(d.abstract_states)}), x[i] state i ({', '.join(d.states)}),",
         f" * u[j] input j ({', '.join(d.inputs)}), v[a] abstract input a ({', '.join(d.abstract_inputs)}).", " */",
         "#include <math.h>", f'#include "{header_name}"', ""]
    if d.parameters:
        c += ["/* The spec's parameters. */"] + [f"#define PRM_{k} {_num(v)}" for k, v in d.parameters.items()] + [""]
    c += [f"const double ashc_input_bounds[{NI}][2] = {_c_rows(d.U)};",
          f"const double ashc_abstract_domain[{NAS}][2] = {_c_rows(d.V)};",
          f"const double ashc_m_domain[{NO}][2] = {_c_rows(d.m_domain)};"]
    if d.K is not None:
        c += ["/* The feedback gain K of k(z, x, u) = u + K (z - x) (stabilise stage, feedback: linear_gain). */",
              f"static const double K[{NI}][{NS}] = {_c_rows(d.K)};"]
    if ls:
        c += ["/* M = L L^T (bound stage), for the least-squares q. */", f"static const double L[{NS}][{NS}] = {_c_rows(d.L)};"]
    c += ["", *translate.C_MIN_MAX, ""]
    if vector:
        c += ["/* Pseudo-inverse of a single column or row a (len entries): a^T / |a|^2, zero for a zero vector. */",
              "static void pinv_vector(int len, const double *a, double *out)", "{", "    double s = 0.0;", "    int i;",
              "    for (i = 0; i < len; i++) s += a[i] * a[i];", "    for (i = 0; i < len; i++) out[i] = s > 0.0 ? a[i] / s : 0.0;", "}", ""]
    if general:
        c += _c_pinv_small(max(r * k for r, k in general), max(min(r, k) for r, k in general))
    fn = _law_of(d, controller)[0]
    called = {_name(fn), "apply"} | ({"feedback_of"} if d.K is not None else set()) | ({"q_of", "times"} if ls else set()) | _plan_calls(d)
    c += ["/* The laws of the interface and of the abstract controller: the compiled closed loops' own functions",
          " * (ashc_cli/closedloop/interface.py, laws.py, controllers.py) printed by ashc_cli/outputs/translate.py; an",
          " * array A comes with its extents A_rows, A_cols (x_n for a vector), row-major. */", ""]
    c += _c_laws(called, (bool(vector), bool(general)), (fn,))
    return c


def _c_terms(d: Design) -> list[str]:
    """The generated expression blocks (interface terms, abstract terms, h, m, p, kappa), ashc_m and ashc_interface."""
    rename, ls = _renamer(d), d.q == "least_squares"
    c: list[str] = []
    interface_outputs = [("l", d.l)] + ([("pm", d.p)] if d.K is not None else []) + ([("dpd", d.dp_delta), ("g", d.g)] if ls else [])
    uses_x = d.K is not None or ls
    sig = ", ".join(["const double *xi"] + (["const double *x"] if uses_x else []) + [f"double *{a}" for a, _ in interface_outputs])
    c += [f"/* {', '.join(a for a, _ in interface_outputs)}: "
          + ", ".join({"l": "l(xi)", "pm": "p(xi)", "dpd": "dp/dxi delta(xi)", "g": "g(x)"}[a] for a, _ in interface_outputs) + " */",
          f"static void interface_terms({sig})", *_c_body(["xi"] + (["x"] if uses_x else []), interface_outputs, rename), "",
          "/* phi_bar(xi) and delta(xi) */", "static void abstract_terms(const double *xi, double *phi, double *delta)",
          *_c_body(["xi"], [("phi", d.phi_bar), ("delta", d.delta)], rename), "",
          "/* y = h(x) (as the inverse stage stored it) */", "static void output_terms(const double *x, double *y)",
          *_c_body(["x"], [("y", d.h)], rename), "",
          "/* m(x), the left inverse (inverse stage) */", "static void m_terms(const double *x, double *m)",
          *_c_body(["x"], [("m", d.m)], rename), "",
          "void ashc_p(const double *xi, double *p)", *_c_body(["xi"], [("p", d.p)], rename), "",
          "void ashc_kappa(const double *xi, double *psi)", *_c_body(["xi"], [("psi", d.kappa)], rename), "",
          "int ashc_m(const double *x, double *xi)", "{", f"    double y[{NO}];", "    int i;", "    output_terms(x, y);",
          f"    for (i = 0; i < {NO}; i++) {{",
          "        const double tol = ASHC_M_DOMAIN_RTOL * fmax(1.0, ashc_m_domain[i][1] - ashc_m_domain[i][0]);",
          "        if (!(y[i] >= ashc_m_domain[i][0] - tol && y[i] <= ashc_m_domain[i][1] + tol)) {",
          "            int k;", f"            for (k = 0; k < {NAS}; k++) xi[k] = NAN;", "            return ASHC_OUTSIDE_CERTIFIED_SET;",
          "        }", "    }", "    m_terms(x, xi);", f"    for (i = 0; i < {NAS}; i++)",
          "        if (!isfinite(xi[i])) return ASHC_NOT_REAL;", "    return ASHC_OK;", "}", ""]
    c += _c_interface(d, interface_outputs, uses_x)
    return c


def _c_controller(d: Design, controller_args: str, controller=None) -> list[str]:
    """ashc_controller (the abstract controller's printed law at t = 0) and the abstract right-hand side."""
    fn, prm, count, _ = _law_of(d, controller)
    if prm is None:
        values = "ASHC_GAIN, ASHC_V_MAX" if d.gain is not None else "gain, v_max"
    else:
        values = ", ".join(_num(p) for p in prm) if count else "0.0"
    c = [f"void ashc_controller({controller_args})", "{", f"    double phi[{NAS}], delta[{NAS} * {NAI}];",
         f"    const double prm[{max(count, 1)}] = {{{values}}};", "    abstract_terms(xi, phi, delta);",
         f"    {_name(fn)}(0.0, xi, {NAS}, xi_ref, {NAS}, phi, {NAS}, delta, {NAS}, {NAI}, prm, {count}, v, {NAI});", "}", ""]
    c += ["void ashc_abstract_rhs(const double *xi, const double *v, double *dxi)", "{",
          f"    double phi[{NAS}], delta[{NAS} * {NAI}];", "    int i, a;", "    abstract_terms(xi, phi, delta);",
          f"    for (i = 0; i < {NAS}; i++) {{", "        double s = 0.0;",
          f"        for (a = 0; a < {NAI}; a++) s += delta[i * {NAI} + a] * v[a];", "        dxi[i] = phi[i] + s;", "    }", "}", ""]
    return c


def _c_body(inputs: Sequence[str], outputs, rename) -> list[str]:
    """The braced body of a C function computing ``outputs`` from the arrays ``inputs`` (``(void)`` for those
    the formulas do not read, so -Wextra stays quiet)."""
    body = _assignments(outputs, rename, "c")
    text = "\n".join(body)
    unused = [f"    (void){name};" for name in inputs if not re.search(rf"\b{name}\[", text)]
    return ["{", *unused, *body, "}"]


def _c_pinv_small(entries: int, small: int) -> list[str]:
    """A fixed-size Moore-Penrose pseudo-inverse (one-sided Jacobi SVD) for matrices of at most ``entries``
    entries whose smaller side is at most ``small``: its work arrays are sized by these, on the stack."""
    return [
        f"#define PINV_ENTRIES {entries}",
        f"#define PINV_SMALL {small}",
        "/* Moore-Penrose pseudo-inverse of the rows x cols matrix a (row-major; rows * cols <= PINV_ENTRIES,",
        " * min(rows, cols) <= PINV_SMALL) into out (cols x rows), by a one-sided Jacobi SVD (Hestenes) of a or a^T,",
        " * whichever has at least as many rows as columns; singular values <= "
        f"{PINV_RCOND:g} times the largest are taken as zero",
        " * (numpy.linalg.pinv's cut-off), so a rank-deficient matrix is handled as numpy does. */",
        "static void pinv_small(int rows, int cols, const double *a, double *out)",
        "{",
        "    double w[PINV_ENTRIES], vv[PINV_SMALL * PINV_SMALL], s2[PINV_SMALL];",
        "    const int tr = rows < cols;",
        "    const int r = tr ? cols : rows, c = tr ? rows : cols;",
        "    double smax = 0.0;",
        "    int i, j, k, sweep;",
        "    for (i = 0; i < r; i++)",
        "        for (j = 0; j < c; j++) w[i * c + j] = tr ? a[j * cols + i] : a[i * cols + j];",
        "    for (i = 0; i < c; i++)",
        "        for (j = 0; j < c; j++) vv[i * c + j] = i == j ? 1.0 : 0.0;",
        f"    for (sweep = 0; sweep < {JACOBI_SWEEPS}; sweep++) {{",
        "        int rotated = 0;",
        "        for (j = 0; j < c - 1; j++) {",
        "            for (k = j + 1; k < c; k++) {",
        "                double alpha = 0.0, beta = 0.0, gamma = 0.0, zeta, t, cs, sn;",
        "                for (i = 0; i < r; i++) {",
        "                    alpha += w[i * c + j] * w[i * c + j];",
        "                    beta += w[i * c + k] * w[i * c + k];",
        "                    gamma += w[i * c + j] * w[i * c + k];",
        "                }",
        "                if (gamma == 0.0 || fabs(gamma) <= 1e-15 * sqrt(alpha * beta)) continue;",
        "                rotated = 1;",
        "                zeta = (beta - alpha) / (2.0 * gamma);",
        "                t = fabs(zeta) > 1e150 ? 0.5 / zeta : (zeta >= 0.0 ? 1.0 : -1.0) / (fabs(zeta) + sqrt(1.0 + zeta * zeta));",
        "                cs = 1.0 / sqrt(1.0 + t * t);",
        "                sn = cs * t;",
        "                for (i = 0; i < r; i++) {",
        "                    const double p = w[i * c + j], q = w[i * c + k];",
        "                    w[i * c + j] = cs * p - sn * q;",
        "                    w[i * c + k] = sn * p + cs * q;",
        "                }",
        "                for (i = 0; i < c; i++) {",
        "                    const double p = vv[i * c + j], q = vv[i * c + k];",
        "                    vv[i * c + j] = cs * p - sn * q;",
        "                    vv[i * c + k] = sn * p + cs * q;",
        "                }",
        "            }",
        "        }",
        "        if (!rotated) break;",
        "    }",
        "    for (j = 0; j < c; j++) {",
        "        s2[j] = 0.0;",
        "        for (i = 0; i < r; i++) s2[j] += w[i * c + j] * w[i * c + j];",
        "        if (sqrt(s2[j]) > smax) smax = sqrt(s2[j]);",
        "    }",
        "    /* pinv of the r x c matrix w0 = W V^T: sum over kept j of V[:, j] W[:, j]^T / s_j^2 (c x r) */",
        "    for (i = 0; i < c; i++) {",
        "        for (k = 0; k < r; k++) {",
        "            double s = 0.0;",
        "            for (j = 0; j < c; j++)",
        f"                if (sqrt(s2[j]) > {PINV_RCOND!r} * smax) s += vv[i * c + j] * w[k * c + j] / s2[j];",
        "            if (tr) out[k * c + i] = s; else out[i * r + k] = s;",
        "        }",
        "    }",
        "}",
        "",
    ]


def _c_interface(d: Design, interface_outputs, uses_x: bool) -> list[str]:
    """ashc_interface: the design's terms, then the compiled loops' own law (closedloop/interface.py, printed)."""
    ls = d.q == "least_squares"
    q_ls, sat = interface_codes(d.q, d.saturate)
    decl = [f"    double {a}[{ {'l': NI, 'pm': NS, 'dpd': f'{NS} * {NAI}', 'g': f'{NS} * {NI}'}[a] }];" for a, _ in interface_outputs]
    lines = ["void ashc_interface(const double *xi, const double *x, const double *v, double *u)", "{", *decl,
             f"    double feedback[{NI}], qv[{NI}], corr[{NI}];"]
    if ls:
        lines += [f"    double q[{NI} * {NAI}], ltg[{NS} * {NI}], ltd[{NS} * {NAI}], pg[{NI} * {NS}];"]
    if d.K is None or not ls:
        lines += ["    int j;"]
    if not uses_x:
        lines += ["    (void)x;"]
    if not ls:
        lines += ["    (void)v;"]
    args = ", ".join(["xi"] + (["x"] if uses_x else []) + [a for a, _ in interface_outputs])
    lines += [f"    interface_terms({args});"]
    if d.K is not None:
        lines += ["    /* K (x - p(xi)): k(x, p(xi), l(xi)) - l(xi) of eq. (15) */", f"    feedback_of(&K[0][0], {NI}, {NS}, x, {NS}, pm, {NS}, feedback, {NI});"]
    else:
        lines += [f"    for (j = 0; j < {NI}; j++) feedback[j] = 0.0;   /* identity feedback: K = 0 */"]
    if ls:
        lines += ["    /* q = pinv(L^T g) (L^T dp/dxi delta), eq. (43) */",
                  f"    q_of(&L[0][0], {NS}, {NS}, {lower_bandwidth(d.L)}, g, {NS}, {NI}, dpd, {NS}, {NAI}, {q_ls}, q, {NI}, {NAI}, ltg, {NS}, {NI}, ltd, {NS}, {NAI}, pg, {NI}, {NS});",
                  f"    times(q, {NI}, {NAI}, v, {NAI}, qv, {NI});"]
    else:
        lines += [f"    for (j = 0; j < {NI}; j++) qv[j] = 0.0;   /* q = 0 */"]
    lines += [f"    /* u = SAT(l + K e + q v), eq. (44): {_saturate_text(d.saturate)} */",
              f"    apply(l, {NI}, feedback, {NI}, qv, {NI}, 1.0, &ashc_input_bounds[0][0], {NI}, 2, {sat}, corr, {NI}, u, {NI});"]
    return lines + ["}", ""]


# --- Python ----------------------------------------------------------------------------------------------


def _py_laws(d: Design, controller, interface_outputs) -> list[str]:
    """The Python export's laws (the compiled loops' source), ashc_interface and ashc_controller."""
    ls, has_gain, uses_x = d.q == "least_squares", d.gain is not None, d.K is not None or d.q == "least_squares"
    lines: list[str] = []
    terms = ", ".join(a for a, _ in interface_outputs)
    q_ls, sat = interface_codes(d.q, d.saturate)
    fn_law, prm, _, says = _law_of(d, controller)
    called = {_name(fn_law), "apply"} | ({"feedback_of"} if d.K is not None else set()) | ({"q_of", "times"} if ls else set()) | _plan_calls(d)
    lines += ["# The laws of the interface and of the abstract controller: the compiled closed loops' own functions",
              "# (closedloop/interface.py, laws.py, controllers.py of ashc), their source as it is.", "", ""]
    for fn in _needed(called, (fn_law,)):
        lines += [*translate.python_source(fn).rstrip("\n").splitlines(), "", ""]
    lines += ["def ashc_interface(xi, x, v):",
              f'    """u = SAT(l(xi){" + K (x - p(xi))" if d.K is not None else ""}{" + q(xi, x) v" if ls else ""}), saturation: {_saturate_text(d.saturate)}."""',
              "    xi = numpy.asarray(xi, dtype=float)", "    x = numpy.asarray(x, dtype=float)", "    v = numpy.asarray(v, dtype=float)",
              f"    {terms} = _interface_terms({'xi, x' if uses_x else 'xi'})",
              "    feedback = numpy.zeros(N_INPUTS)", "    qv = numpy.zeros(N_INPUTS)"]
    if d.K is not None:
        lines += ["    feedback_of(K, x, pm, feedback)  # K (x - p(xi)), eq. (15)"]
    if ls:
        lines += ["    q = numpy.empty((N_INPUTS, N_ABSTRACT_INPUTS))",
                  f"    q_of(L, {lower_bandwidth(d.L)}, g, dpd, {q_ls}, q, numpy.empty((N_STATES, N_INPUTS)), numpy.empty((N_STATES, N_ABSTRACT_INPUTS)), "
                  "numpy.empty((N_INPUTS, N_STATES)))  # eq. (43)", "    times(q, v, qv)"]
    lines += ["    u = numpy.empty(N_INPUTS)", f"    apply(l, feedback, qv, 1.0, INPUT_BOUNDS, {sat}, numpy.empty(N_INPUTS), u)  # eq. (44)",
              "    return u", "", ""]
    args = "xi, xi_ref" if has_gain or controller is not None else "xi, xi_ref, gain, v_max"
    values = (("GAIN, V_MAX" if has_gain else "gain, v_max") if prm is None else ", ".join(repr(float(p)) for p in prm))
    lines += [f"def ashc_controller({args}):", f'    """{says}."""',
              "    xi = numpy.ascontiguousarray(xi, dtype=float)", "    xi_ref = numpy.ascontiguousarray(xi_ref, dtype=float)",
              "    phi, delta = _abstract_terms(xi)", "    v = numpy.empty(N_ABSTRACT_INPUTS)",
              f"    {_name(fn_law)}(0.0, xi, xi_ref, phi, delta, numpy.array([{values}], dtype=float), v)",
              "    return v", "", ""]
    return lines


def python_source(design: Design, controller=None) -> str:
    """The numpy module of a design: the same functions as the C file, returning arrays.

    Parameters
    ----------
    design : Design
        From :func:`gather`.
    controller : (Controller, prm), optional
        As :func:`c_sources`.

    Returns
    -------
    str
        The module's source.  ``ashc_m(x)`` returns ``(status, xi)``; ``ashc_controller(xi, xi_ref)`` takes
        ``gain`` and ``v_max`` as further arguments when the spec gives no abstract controller.  The
        interface and the controller are those of the set-point law (tests/oracle.py ``tracking_law``), operation
        for operation (numpy's pinv where a pseudo-inverse is not of one column).
    """
    d = design
    rename = _renamer(d)
    ls = d.q == "least_squares"
    has_gain = d.gain is not None
    interface_outputs = [("l", d.l)] + ([("pm", d.p)] if d.K is not None else []) + ([("dpd", d.dp_delta), ("g", d.g)] if ls else [])

    def function(name: str, args: str, outputs, doc: str) -> list[str]:
        body = [f"def {name}({args}):", f'    """{doc}"""']
        for arg in args.split(", "):
            body.append(f"    {arg} = numpy.asarray({arg}, dtype=float)")
        for array, matrix in outputs:
            body.append(f"    {array} = numpy.empty({sp.Matrix(matrix).rows * sp.Matrix(matrix).cols})")
        body += _assignments(outputs, rename, "python")
        # delta, dp/dxi delta and g are matrices (2-D, even with one column), the others vectors
        shaped = [f"{array}.reshape({sp.Matrix(matrix).rows}, {sp.Matrix(matrix).cols})" if array in ("delta", "dpd", "g") else array
                  for array, matrix in outputs]
        body.append(f"    return {', '.join(shaped)}")
        return body + ["", ""]

    head = _head_comment(d, "numpy only")
    lines = ['"""' + head[0], "", *head[1:], "",
             f"Arrays: xi[i] is abstract state i ({', '.join(d.abstract_states)}), x[i] state i ({', '.join(d.states)}), "
             f"u[j] input j ({', '.join(d.inputs)}), v[a] abstract input a ({', '.join(d.abstract_inputs)}).", '"""', "",
             "import functools", "", "import numpy", "import numpy as np", "",
             f"N_STATES = {d.n}", f"N_INPUTS = {d.n_inputs}", f"N_ABSTRACT_STATES = {d.n_hat}", f"N_ABSTRACT_INPUTS = {d.m_hat}",
             f"N_OUTPUTS = {d.n_outputs}", "",
             "#: Status of ashc_m.", "OK, OUTSIDE_CERTIFIED_SET, NOT_REAL = 0, 1, 2", "",
             *(["# The spec's parameters.", *(f"PRM_{k} = {float(v)!r}" for k, v in d.parameters.items()), ""] if d.parameters else []),
             f"INPUT_BOUNDS = {_py_rows(d.U)}  # U", f"ABSTRACT_DOMAIN = {_py_rows(d.V)}  # V",
             f"M_DOMAIN = {_py_rows(d.m_domain)}  # where m is certified ({d.m_domain_set}): h(x) in this box",
             f"M_DOMAIN_RTOL = {DOMAIN_RTOL!r}", f"Q = {d.q!r}", f"SATURATE = {d.saturate!r}"]
    lines += [f"K = {_py_rows(d.K)}  # feedback gain (feedback: linear_gain)" if d.K is not None else "K = None  # identity feedback"]
    lines += [f"L = {_py_rows(d.L)}  # M = L L^T" if ls else "L = None  # q = 0"]
    if has_gain:
        lines += [f"GAIN = {d.gain!r}", f"V_MAX = {d.v_max!r}"]
    lines += ["", ""]
    uses_x = d.K is not None or ls
    lines += function("_interface_terms", "xi, x" if uses_x else "xi", interface_outputs, "l(xi)" + (", p(xi)" if d.K is not None else "")
                      + (", dp/dxi delta(xi), g(x)" if ls else "") + ".")
    lines += function("_abstract_terms", "xi", [("phi", d.phi_bar), ("delta", d.delta)], "phi_bar(xi), delta(xi).")
    lines += function("_output_terms", "x", [("y", d.h)], "y = h(x).")
    lines += function("_m_terms", "x", [("m", d.m)], "m(x), unchecked.")
    lines += function("ashc_p", "xi", [("p", d.p)], "p(xi): the manifold map.")
    lines += function("ashc_kappa", "xi", [("psi", d.kappa)], "psi = kappa(xi): the abstract output.")
    lines += ["def ashc_m(x):",
              '    """(status, xi = m(x)): OK, or OUTSIDE_CERTIFIED_SET (h(x) not in M_DOMAIN; xi is NaN) or NOT_REAL."""',
              "    x = numpy.asarray(x, dtype=float)", "    y = _output_terms(x)",
              "    tol = M_DOMAIN_RTOL * numpy.maximum(1.0, M_DOMAIN[:, 1] - M_DOMAIN[:, 0])",
              "    if not numpy.all((y >= M_DOMAIN[:, 0] - tol) & (y <= M_DOMAIN[:, 1] + tol)):",
              "        return OUTSIDE_CERTIFIED_SET, numpy.full(N_ABSTRACT_STATES, numpy.nan)", "    xi = _m_terms(x)",
              "    return (OK if numpy.all(numpy.isfinite(xi)) else NOT_REAL), xi", "", ""]
    lines += _py_laws(d, controller, interface_outputs) + _py_plan(d)
    lines += ["def ashc_abstract_rhs(xi, v):", '    """dxi = phi_bar(xi) + delta(xi) v."""',
              "    v = numpy.asarray(v, dtype=float)", "    phi, delta = _abstract_terms(xi)", "    return phi + delta @ v", ""]
    text = "\n".join(lines)
    if "functools." not in text.split('"""', 2)[2]:   # sympy prints min/max of several arguments with functools.reduce
        text = text.replace("import functools\n\n", "", 1)
    return text


