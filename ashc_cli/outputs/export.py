"""The design as code (issue 15): a finished design exported as one C99 file (with its header) or one numpy module.

``ashc export`` turns the stored expressions of a design into source code a controller can run without ashc:

``ashc_p(xi)``, ``ashc_kappa(xi)``
    The manifold map p (manifold stage) and the abstract output map kappa (kappa stage).
``ashc_m(x)``
    The left inverse m (inverse stage), evaluated only where it is certified: the output y = h(x) must lie in
    ``inverse.m_domain`` (widened by ``DOMAIN_RTOL``, as ``ashc eval`` and ``simulate`` test it).  It returns a
    status: ``0`` (ok), ``1`` (outside the certified set; the result is NaN) or ``2`` (m is not real there).
``ashc_interface(xi, x, v)``
    The interface u_w = SAT(l(xi) + K (x - p(xi)) + q(xi, x) v) of :func:`ashc_cli.closedloop.reference.tracking_law`
    (eqs. Interface, egInterface, egInterfaceSat): the feedback K (x - p) when the design synthesised a gain
    (``feedback: linear_gain``); q = pinv(L^T g(x)) L^T dp/dxi delta(xi) (eq. egqLS, with M = L L^T) or q = 0
    as the spec's ``interface.q`` says; SAT as :func:`ashc_cli.problem.model.apply_saturation` (``interface.saturate``:
    clip per channel, scale the correction, or none).
``ashc_controller(xi, xi_ref)``
    The set-point abstract controller of the tracking scenario, v = clip(delta^+ (gain (xi_ref - xi) -
    phi_bar(xi)), -v_max, v_max), with gain and v_max from ``simulate.tracking.abstract_controller`` when the
    spec gives one, else as two more arguments.
``ashc_abstract_rhs(xi, v)``
    The abstract system's right-hand side phi_bar(xi) + delta(xi) v, to integrate xi on the controller.

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

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import sympy as sp
from sympy.printing.c import C99CodePrinter
from sympy.printing.numpy import NumPyPrinter

from ashc_cli import __version__
from ashc_cli.design.artefacts import Artefact
from ashc_cli.errors import ArtefactError, DesignError, SpecError
from ashc_cli.problem.model import apply_saturation, build_model, lambdify, parameter_symbol, state_symbol
from ashc_cli.problem.spec import Spec
from ashc_cli.design.upstream import DOMAIN_RTOL, certified_set

__all__ = ["LANGUAGES", "NEEDED", "STATUS", "Design", "gather", "require_current", "c_sources", "python_source",
           "export_sources", "check_target", "write_export", "interface_value", "interface_point"]

#: The languages ``ashc export --lang`` writes.
LANGUAGES = ("c", "python")
#: The stages whose artefacts the exported code is built from.
NEEDED = ("stabilise", "manifold", "kappa", "inverse", "delta", "bound")
#: The status ``ashc_m`` returns, by value.
STATUS = {0: "ok", 1: "outside the certified set (h(x) not in inverse.m_domain)", 2: "m is not real at x"}
#: numpy.linalg.pinv's default cut-off: singular values <= PINV_RCOND * the largest are taken as zero.
PINV_RCOND = 1e-15
#: Sweeps of the C pseudo-inverse's Jacobi SVD at most (it converges in a handful for the small sizes here).
JACOBI_SWEEPS = 60


# --- what the exported code is made of -------------------------------------------------------------------


@dataclass(frozen=True)
class Design:
    """Everything the exported code needs, gathered from a spec and its design's artefacts.

    Attributes
    ----------
    name : str
        The spec's name.
    provenance : dict of str to str
        The spec's SHA-256 (``spec``) and each used artefact's (by stage).
    states, inputs, abstract_states, abstract_inputs : list of str
        The spec's names, in order (the index of each in the arrays of the generated code).
    n_outputs : int
        The number of outputs (rows of h and kappa).
    parameters : dict of str to float
        The spec's parameters (named constants of the generated code).
    phi_bar, l, delta, p, kappa, dp_delta, g, h, m : sympy Matrix
        phi_bar and l (spec), delta (delta stage), p (manifold), kappa (kappa), dp/dxi delta (bound), g
        (spec), h and m (inverse stage); in the spec's symbols.
    U, V, m_domain : ndarray (k, 2)
        The input box, the abstract domain, and the outputs where m is certified.
    m_domain_set : str
        The name of that set (``kappa(V)``, ``Y``).
    K : ndarray (m, n) or None
        The feedback gain, None when the design has none (identity feedback: K = 0).
    L : ndarray (n, n)
        M = L L^T (bound stage), for the least-squares q.
    q : str
        ``least_squares`` or ``zero``.
    saturate : True, False or "scale"
        The interface's saturation (``interface.saturate``).
    gain, v_max : float or None
        The set-point controller's, from ``simulate.tracking.abstract_controller`` (None: arguments).
    """

    name: str
    provenance: dict
    states: list
    inputs: list
    abstract_states: list
    abstract_inputs: list
    n_outputs: int
    parameters: dict
    phi_bar: sp.Matrix
    l: sp.Matrix
    delta: sp.Matrix
    p: sp.Matrix
    kappa: sp.Matrix
    dp_delta: sp.Matrix
    g: sp.Matrix
    h: sp.Matrix
    m: sp.Matrix
    U: np.ndarray
    V: np.ndarray
    m_domain: np.ndarray
    m_domain_set: str
    K: np.ndarray | None
    L: np.ndarray
    q: str
    saturate: bool | str
    gain: float | None
    v_max: float | None

    @property
    def n(self) -> int:
        """The number of states."""
        return len(self.states)

    @property
    def n_inputs(self) -> int:
        """The number of inputs (m of the paper)."""
        return len(self.inputs)

    @property
    def n_hat(self) -> int:
        """The number of abstract states."""
        return len(self.abstract_states)

    @property
    def m_hat(self) -> int:
        """The number of abstract inputs."""
        return len(self.abstract_inputs)


def _stage(arts: Mapping[str, Artefact], stage: str) -> Artefact:
    if stage not in arts:
        raise ArtefactError(stage, f"no {stage}.h5 artefact (the exported code is built from stages {', '.join(NEEDED)})",
                            "run `ashc design SPEC --out DIR` first")
    return arts[stage]


def require_current(spec: Spec, arts: Mapping[str, Artefact]) -> None:
    """Refuse artefacts that are missing or were made from another spec than ``spec``.

    Parameters
    ----------
    spec : Spec
        The spec the code is exported for.
    arts : mapping of str to Artefact
        The design's artefacts, by stage.

    Raises
    ------
    ArtefactError
        Naming the first stage of :data:`NEEDED` that is missing or made from another spec (SHA-256 differs).
    """
    for stage in NEEDED:
        art = _stage(arts, stage)
        if art.provenance.get("spec_sha256") != spec.sha256:
            raise ArtefactError(f"{stage}.h5", f"was made from another spec than '{spec.name}' (SHA-256 differs)",
                                "the folder designed from this spec (`ashc design SPEC --out DIR`)")


def gather(spec: Spec, arts: Mapping[str, Artefact]) -> Design:
    """The expressions and numbers of a design that the exported code is made of.

    Parameters
    ----------
    spec : Spec
        The design's spec (for phi_bar, l, g, U, the interface and the controller, which no artefact holds).
    arts : mapping of str to Artefact
        The artefacts of stages :data:`NEEDED`.

    Returns
    -------
    Design

    Raises
    ------
    ArtefactError
        If a needed artefact is missing or holds no expected value (e.g. an inverse artefact without m_domain).
    """
    for stage in NEEDED:
        _stage(arts, stage)
    model = build_model(spec)
    inverse = arts["inverse"]
    box, set_name, _ = certified_set(inverse)
    K = np.asarray(arts["stabilise"].values.get("K", np.zeros((model.m, model.n))), dtype=float).reshape(model.m, model.n)
    V = model.V if model.V is not None else np.asarray(arts["manifold"].value("V"), dtype=float)
    tracking = spec.simulate.tracking
    ctl = tracking.abstract_controller if tracking is not None and tracking.abstract_controller.kind == "setpoint" else None
    provenance = {"spec": spec.sha256, **{stage: str(arts[stage].provenance.get("sha256", "")) for stage in NEEDED}}
    design = Design(
        name=spec.name, provenance=provenance, states=list(spec.concrete.states), inputs=list(spec.concrete.inputs),
        abstract_states=list(spec.abstract.states), abstract_inputs=list(spec.abstract.inputs), n_outputs=model.p,
        parameters={k: float(v) for k, v in spec.parameters.items()},
        phi_bar=model.phi_bar, l=model.l, delta=arts["delta"].expr("delta"), p=arts["manifold"].expr("p"),
        kappa=arts["kappa"].expr("kappa"), dp_delta=arts["bound"].expr("dp_delta"), g=model.g,
        h=inverse.expr("h"), m=inverse.expr("m"),
        U=np.asarray(model.U, dtype=float), V=np.asarray(V, dtype=float).reshape(model.n_hat, 2), m_domain=box, m_domain_set=set_name,
        K=K if np.any(K != 0) else None, L=np.asarray(arts["bound"].value("L"), dtype=float).reshape(model.n, model.n),
        q=spec.interface.q, saturate=spec.interface.saturate,
        gain=None if ctl is None else float(ctl.gain), v_max=None if ctl is None else float(ctl.v_max),
    )
    expected = {"phi_bar": (design.n_hat, 1), "l": (design.n_inputs, 1), "delta": (design.n_hat, design.m_hat),
                "p": (design.n, 1), "kappa": (design.n_outputs, 1), "dp_delta": (design.n, design.m_hat),
                "g": (design.n, design.n_inputs), "h": (design.n_outputs, 1), "m": (design.n_hat, 1)}
    for key, shape in expected.items():
        if tuple(getattr(design, key).shape) != shape:
            raise ArtefactError(key, f"has shape {tuple(getattr(design, key).shape)}, the spec's names need {shape}",
                                "artefacts made from this spec (`ashc design SPEC --force`)")
    return design


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
        for s in expr.free_symbols:
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


def c_sources(design: Design, header_name: str = "ashc_design.h") -> tuple[str, str]:
    """The C99 source and header of a design.

    Parameters
    ----------
    design : Design
        From :func:`gather`.
    header_name : str
        The header's file name, which the source includes.

    Returns
    -------
    source, header : str
    """
    d = design
    rename = _renamer(d)
    NS, NI, NAS, NAI, NO = "ASHC_N_STATES", "ASHC_N_INPUTS", "ASHC_N_ABSTRACT_STATES", "ASHC_N_ABSTRACT_INPUTS", "ASHC_N_OUTPUTS"
    ls = d.q == "least_squares"
    has_gain = d.gain is not None
    controller_args = "const double *xi, const double *xi_ref, double *v" if has_gain else \
        "const double *xi, const double *xi_ref, double gain, double v_max, double *v"

    # --- header
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
         f"/* Relative widening of ashc_m_domain (times max(1, width)) within which m is still evaluated. */",
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
          "/* v = clip(delta(xi)^+ (gain (xi_ref - xi) - phi_bar(xi)), -v_max, v_max): the set-point abstract controller. */",
          f"void ashc_controller({controller_args});",
          "/* dxi = phi_bar(xi) + delta(xi) v: the abstract system, to integrate xi. */",
          "void ashc_abstract_rhs(const double *xi, const double *v, double *dxi);", "",
          "#ifdef __cplusplus", "}", "#endif", "", f"#endif /* {_guard_name(d.name)} */", ""]

    # --- source
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
    c += ["", "static double clip(double z, double lo, double hi)", "{", "    return z < lo ? lo : (z > hi ? hi : z);", "}", ""]
    if vector:
        c += ["/* Pseudo-inverse of a single column or row a (len entries): a^T / |a|^2, zero for a zero vector. */",
              "static void pinv_vector(int len, const double *a, double *out)", "{", "    double s = 0.0;", "    int i;",
              "    for (i = 0; i < len; i++) s += a[i] * a[i];", "    for (i = 0; i < len; i++) out[i] = s > 0.0 ? a[i] / s : 0.0;", "}", ""]
    if general:
        c += _c_pinv_small(max(r * k for r, k in general), max(min(r, k) for r, k in general))
    # expression blocks
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
    pinv_delta = f"pinv_vector({NAS} * {NAI}, delta, dplus);" if min(d.n_hat, d.m_hat) == 1 else f"pinv_small({NAS}, {NAI}, delta, dplus);"
    c += ["static void controller_law(const double *xi, const double *xi_ref, double gain, double v_max, double *v)", "{",
          f"    double phi[{NAS}], delta[{NAS} * {NAI}], dplus[{NAI} * {NAS}], e[{NAS}];", "    int i, a;",
          "    abstract_terms(xi, phi, delta);", f"    {pinv_delta}",
          f"    for (i = 0; i < {NAS}; i++) e[i] = gain * (xi_ref[i] - xi[i]) - phi[i];",
          f"    for (a = 0; a < {NAI}; a++) {{", "        double s = 0.0;",
          f"        for (i = 0; i < {NAS}; i++) s += dplus[a * {NAS} + i] * e[i];", "        v[a] = clip(s, -v_max, v_max);", "    }", "}", ""]
    if has_gain:
        c += [f"void ashc_controller({controller_args})", "{", "    controller_law(xi, xi_ref, ASHC_GAIN, ASHC_V_MAX, v);", "}", ""]
    else:
        c += [f"void ashc_controller({controller_args})", "{", "    controller_law(xi, xi_ref, gain, v_max, v);", "}", ""]
    c += ["void ashc_abstract_rhs(const double *xi, const double *v, double *dxi)", "{",
          f"    double phi[{NAS}], delta[{NAS} * {NAI}];", "    int i, a;", "    abstract_terms(xi, phi, delta);",
          f"    for (i = 0; i < {NAS}; i++) {{", "        double s = 0.0;",
          f"        for (a = 0; a < {NAI}; a++) s += delta[i * {NAI} + a] * v[a];", "        dxi[i] = phi[i] + s;", "    }", "}", ""]
    return "\n".join(c), "\n".join(h)


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
    NS, NI, NAI = "ASHC_N_STATES", "ASHC_N_INPUTS", "ASHC_N_ABSTRACT_INPUTS"
    ls = d.q == "least_squares"
    decl = [f"    double {a}[{ {'l': NI, 'pm': NS, 'dpd': f'{NS} * {NAI}', 'g': f'{NS} * {NI}'}[a] }];" for a, _ in interface_outputs]
    lines = ["void ashc_interface(const double *xi, const double *x, const double *v, double *u)", "{", *decl,
             f"    double feedback[{NI}], correction[{NI}];"]
    if ls:
        lines += [f"    double Ltg[{NS} * {NI}], Ltd[{NS} * {NAI}], pg[{NI} * {NS}], q[{NI} * {NAI}];", "    int i, j, k, a;"]
    elif d.K is not None:
        lines += ["    int i, j;"]
    else:
        lines += ["    int j;"]
    if not uses_x:
        lines += ["    (void)x;"]
    if not ls:
        lines += ["    (void)v;"]
    args = ", ".join(["xi"] + (["x"] if uses_x else []) + [a for a, _ in interface_outputs])
    lines += [f"    interface_terms({args});"]
    if d.K is not None:
        lines += ["    /* K (x - p(xi)): k(x, p(xi), l(xi)) - l(xi) of eq. Interface */", f"    for (j = 0; j < {NI}; j++) {{",
                  "        double s = 0.0;", f"        for (i = 0; i < {NS}; i++) s += K[j][i] * (x[i] - pm[i]);",
                  "        feedback[j] = s;", "    }"]
    else:
        lines += [f"    for (j = 0; j < {NI}; j++) feedback[j] = 0.0;   /* identity feedback: K = 0 */"]
    lines += [f"    for (j = 0; j < {NI}; j++) correction[j] = feedback[j];"]
    if ls:
        pinv = f"pinv_vector({NS} * {NI}, Ltg, pg);" if min(d.n, d.n_inputs) == 1 else f"pinv_small({NS}, {NI}, Ltg, pg);"
        lines += ["    /* q = pinv(L^T g) (L^T dp/dxi delta), eq. egqLS */", f"    for (i = 0; i < {NS}; i++) {{",
                  f"        for (j = 0; j < {NI}; j++) {{", "            double s = 0.0;",
                  f"            for (k = 0; k < {NS}; k++) s += L[k][i] * g[k * {NI} + j];", f"            Ltg[i * {NI} + j] = s;", "        }",
                  f"        for (a = 0; a < {NAI}; a++) {{", "            double s = 0.0;",
                  f"            for (k = 0; k < {NS}; k++) s += L[k][i] * dpd[k * {NAI} + a];", f"            Ltd[i * {NAI} + a] = s;", "        }",
                  "    }", f"    {pinv}", f"    for (j = 0; j < {NI}; j++) {{", f"        for (a = 0; a < {NAI}; a++) {{",
                  "            double s = 0.0;", f"            for (i = 0; i < {NS}; i++) s += pg[j * {NS} + i] * Ltd[i * {NAI} + a];",
                  f"            q[j * {NAI} + a] = s;", "        }", "    }", f"    for (j = 0; j < {NI}; j++) {{", "        double s = 0.0;",
                  f"        for (a = 0; a < {NAI}; a++) s += q[j * {NAI} + a] * v[a];", "        correction[j] = feedback[j] + s;", "    }"]
    if d.saturate == "scale":
        lines += ["    /* SAT (scale): l + s correction with the largest s in [0, 1] keeping u in U (one factor for every channel) */",
                  "    {", "        double smin = HUGE_VAL, s;", f"        for (j = 0; j < {NI}; j++) {{", "            const double cj = correction[j];",
                  "            double room = HUGE_VAL;",
                  "            if (cj > 0.0) room = (ashc_input_bounds[j][1] - l[j]) / cj;",
                  "            else if (cj < 0.0) room = (ashc_input_bounds[j][0] - l[j]) / cj;",
                  "            if (room < smin || room != room) smin = room;", "        }",
                  "        s = smin < 0.0 ? 0.0 : (smin > 1.0 ? 1.0 : smin);",
                  f"        for (j = 0; j < {NI}; j++) u[j] = l[j] + s * correction[j];", "    }"]
    elif d.saturate:
        lines += ["    /* SAT (clip): each channel to U */",
                  f"    for (j = 0; j < {NI}; j++) u[j] = clip(l[j] + correction[j], ashc_input_bounds[j][0], ashc_input_bounds[j][1]);"]
    else:
        lines += ["    /* no saturation: u may leave U */", f"    for (j = 0; j < {NI}; j++) u[j] = l[j] + correction[j];"]
    return lines + ["}", ""]


# --- Python ----------------------------------------------------------------------------------------------


def python_source(design: Design) -> str:
    """The numpy module of a design: the same functions as the C file, returning arrays.

    Parameters
    ----------
    design : Design
        From :func:`gather`.

    Returns
    -------
    str
        The module's source.  ``ashc_m(x)`` returns ``(status, xi)``; ``ashc_controller(xi, xi_ref)`` takes
        ``gain`` and ``v_max`` as further arguments when the spec gives no abstract controller.  The
        interface and the controller are those of :func:`ashc_cli.closedloop.reference.tracking_law`, operation
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
             "import functools", "", "import numpy", "",
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
    lines += ["", "",
              "def _pinv(a):", '    """linalg.pinv: one column in closed form a^T / |a|^2 (zero for a zero column), else numpy\'s pinv."""',
              "    if a.shape[1] == 1:", "        s = float(a[:, 0] @ a[:, 0])", "        return a.T / s if s > 0 else numpy.zeros_like(a.T)",
              "    return numpy.linalg.pinv(a)", "", ""]
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
    terms = ", ".join(a for a, _ in interface_outputs)
    lines += ["def ashc_interface(xi, x, v):",
              f'    """u = SAT(l(xi){" + K (x - p(xi))" if d.K is not None else ""}{" + q(xi, x) v" if ls else ""}), saturation: {_saturate_text(d.saturate)}."""',
              "    xi = numpy.asarray(xi, dtype=float)", "    x = numpy.asarray(x, dtype=float)", "    v = numpy.asarray(v, dtype=float)",
              f"    {terms} = _interface_terms({'xi, x' if uses_x else 'xi'})",
              "    feedback = K @ (x - pm)" if d.K is not None else "    feedback = numpy.zeros(N_INPUTS)",
              "    correction = feedback"]
    if ls:
        lines += ["    q = _pinv(L.T @ g) @ (L.T @ dpd)  # eq. egqLS", "    correction = correction + q @ v"]
    if d.saturate == "scale":
        lines += ["    lo, hi = INPUT_BOUNDS[:, 0], INPUT_BOUNDS[:, 1]", "    with numpy.errstate(divide='ignore', invalid='ignore'):",
                  "        room = numpy.where(correction > 0, (hi - l) / correction, numpy.where(correction < 0, (lo - l) / correction, numpy.inf))",
                  "    s = numpy.clip(numpy.min(room), 0.0, 1.0)", "    return l + s * correction"]
    elif d.saturate:
        lines += ["    return numpy.clip(l + correction, INPUT_BOUNDS[:, 0], INPUT_BOUNDS[:, 1])"]
    else:
        lines += ["    return l + correction"]
    lines += ["", ""]
    args = "xi, xi_ref" if has_gain else "xi, xi_ref, gain, v_max"
    lines += [f"def ashc_controller({args}):", '    """v = clip(delta^+ (gain (xi_ref - xi) - phi_bar(xi)), -v_max, v_max)."""',
              *(["    gain, v_max = GAIN, V_MAX"] if has_gain else []),
              "    xi = numpy.asarray(xi, dtype=float)", "    xi_ref = numpy.asarray(xi_ref, dtype=float)",
              "    phi, delta = _abstract_terms(xi)",
              "    return numpy.clip(_pinv(delta) @ (gain * (xi_ref - xi) - phi), -v_max, v_max)", "", "",
              "def ashc_abstract_rhs(xi, v):", '    """dxi = phi_bar(xi) + delta(xi) v."""',
              "    v = numpy.asarray(v, dtype=float)", "    phi, delta = _abstract_terms(xi)", "    return phi + delta @ v", ""]
    text = "\n".join(lines)
    if "functools." not in text.split('"""', 2)[2]:   # sympy prints min/max of several arguments with functools.reduce
        text = text.replace("import functools\n\n", "", 1)
    return text


# --- the API the CLI calls ------------------------------------------------------------------------------


def _check_lang(lang: str) -> str:
    lang = str(lang).lower()
    if lang not in LANGUAGES:
        raise SpecError("--lang", f"'{lang}' is not a language ashc exports", " or ".join(LANGUAGES))
    return lang


def check_target(lang: str, output: str | Path) -> tuple[str, Path]:
    """Validate ``--lang`` and ``--output`` before any work (the CLI calls it before designing).

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


def export_sources(spec: Spec, arts: Mapping[str, Artefact], lang: str, stem: str = "ashc_design") -> dict[str, str]:
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
    design = gather(spec, arts)
    if lang == "c":
        source, header = c_sources(design, f"{stem}.h")
        return {f"{stem}.c": source, f"{stem}.h": header}
    return {f"{stem}.py": python_source(design)}


def write_export(spec: Spec, arts: Mapping[str, Artefact], lang: str, output: str | Path) -> list[Path]:
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
    texts = export_sources(spec, arts, lang, output.stem)
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

    The same law as :func:`ashc_cli.closedloop.reference.tracking_law`'s u: SAT(l(xi) + K (x - p(xi)) + q(xi, x) v),
    the terms lambdified from the spec and the artefacts, q by :func:`ashc_cli.numerics.linalg.pinv`, SAT by
    :func:`ashc_cli.problem.model.apply_saturation`.

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
    from ashc_cli.numerics.linalg import pinv

    require_current(spec, arts)
    d = gather(spec, arts)
    xi, x, v = interface_point(d, point)
    model = build_model(spec)
    values = model.values

    def at(matrix, args, arrays):
        return lambdify(matrix, list(args), values)(*arrays).reshape(sp.Matrix(matrix).shape)

    l = at(d.l, model.xi, xi)[:, 0]
    feedback = np.zeros(d.n_inputs)
    if d.K is not None:
        feedback = d.K @ (x - at(d.p, model.xi, xi)[:, 0])
    correction = feedback
    if d.q == "least_squares":
        g = at(d.g, model.x, x)
        dpd = at(d.dp_delta, model.xi, xi)
        correction = correction + (pinv(d.L.T @ g) @ (d.L.T @ dpd)) @ v
    u = apply_saturation(l, correction, d.U, d.saturate)
    if not np.all(np.isfinite(u)):
        raise DesignError("u_w", f"u_w is not real at {dict(point)}", "a point where l, p, g and dp/dxi delta are defined")
    return [float(value) + 0.0 for value in u]
