"""The YAML spec contract (``docs/spec-format.md``) as pydantic models, and the loader.

:func:`load_spec` reads a file with a safe YAML loader (no aliases, no duplicate keys), validates it
against :class:`Spec` (unknown keys are errors, with the closest valid key suggested), checks the
shapes that relate fields to each other, and returns the model with its SHA-256.  Every problem becomes
one :class:`~ashc_cli.errors.SpecError` naming the field.  Expressions stay text here; :mod:`ashc_cli.problem.model`
parses them.
"""

from __future__ import annotations

import difflib
import hashlib
import json
import keyword
import re
import types
import typing
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any, Literal, Union

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, FiniteFloat, ValidationError, ValidationInfo, field_validator
from pydantic_core import PydanticCustomError

from ashc_cli.problem.spec_checks import check_shapes
from ashc_cli.problem.spec_yaml import load_yaml
from ashc_cli.errors import SpecError
from ashc_cli.problem.expr import RESERVED_NAMES

__all__ = ["Spec", "load_spec", "parse_spec_text", "canonical", "spec_sha256", "keys_sha256", "MAX_SPEC_BYTES"]

#: Largest spec file accepted, in bytes.
MAX_SPEC_BYTES = 1_000_000

_IDENT = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")


def _expression_text(value: Any) -> Any:
    """Accept a number where an expression is expected (YAML reads ``0`` as an int)."""
    if isinstance(value, bool):
        return value  # left for the str check to refuse
    if isinstance(value, (int, float)):
        return repr(value)
    return value


def _identifier(value: Any) -> Any:
    if isinstance(value, str):
        if not _IDENT.match(value):
            raise ValueError(f"'{value}' is not a name (letters, digits and _, starting with a letter)")
        if keyword.iskeyword(value) or value in RESERVED_NAMES:
            raise ValueError(f"'{value}' is reserved (a keyword, a function name, pi or t)")
    return value


Expr = Annotated[str, BeforeValidator(_expression_text)]
Name = Annotated[str, BeforeValidator(_identifier)]
Bounds = Annotated[list[FiniteFloat], Field(min_length=2, max_length=2)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


#: pydantic error type of a map of bounds whose keys do not match the declared names (its ``expected`` is in ctx).
BOUNDS_MAP_ERROR = "bounds_map"


def _bounds_by_name(value: Any, names: Any, what: str) -> Any:
    """A map of [lo, hi] pairs keyed by ``names`` as the list of pairs in the order of ``names``.

    ``input_bounds: {u: [0.0, 0.8]}`` is ``input_bounds: [[0.0, 0.8]]``: every name exactly once, no other key
    (duplicate keys are refused by the YAML loader).  A list, or a map met when ``names`` itself is invalid,
    is returned as it is (the list validation then reports it).
    """
    if not isinstance(value, dict) or not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        return value
    listed = ", ".join(names)
    expected = f"a map with one [lo, hi] pair for each of {listed} (every {what} exactly once), or a list of pairs in that order"
    unknown = [k for k in value if k not in names]
    if unknown:
        raise PydanticCustomError(BOUNDS_MAP_ERROR, "unknown {what} {key}", {"what": what, "key": _short(unknown[0], 40), "expected": expected})
    missing = [k for k in names if k not in value]
    if missing:
        raise PydanticCustomError(BOUNDS_MAP_ERROR, "no pair for {what} {key}", {"what": what, "key": _short(missing[0], 40), "expected": expected})
    return [value[k] for k in names]


class Concrete(_Strict):
    """The concrete system x' = f_bar(x) + g(x) u (eq. (13)), or x' = f(x, u) (eq. (1)); y = h(x).

    Either ``f_bar`` and ``g`` (input-affine), or ``f`` alone: n expressions in the states and the inputs.  An ``f``
    that is affine in u is split into f_bar = f(x, 0) and g = df/du by the model; one that is not is designed by the
    paper's Remark 4 (the invariance PDE with f(p(xi), l(xi)) on its right, condition (B) by Proposition 1).
    """

    states: list[Name] = Field(min_length=1)
    inputs: list[Name] = Field(min_length=1)
    f_bar: list[Expr] | None = None
    g: list[list[Expr]] | None = None
    #: The right-hand side x' = f(x, u) of a plant written as a whole (instead of f_bar and g).
    f: list[Expr] | None = None
    h: list[Expr] = Field(min_length=1)
    #: One [lo, hi] pair per input, as a list in input order or a map keyed by the input names.
    input_bounds: list[Bounds]
    #: One [lo, hi] pair per output of h, as a list or a map keyed by y1, y2, ..., yp.
    output_set: list[Bounds]
    #: The box of states the design is certified on, where the plant is not globally simple: needed when f
    #: is not affine in x (the Jacobian LMI is imposed over it) or h is not linear (L_h is computed over it).
    state_box: list[Bounds] | None = None
    #: Disturbance inputs w (names), entering as x' = f + e(x) w with w in ``disturbance_bounds`` (gAAS-style term).
    disturbances: list[Name] | None = None
    #: The disturbance's input matrix e(x): n rows of d expressions in the states and parameters.
    e: list[list[Expr]] | None = None
    #: One [lo, hi] pair per disturbance, as a list or a map keyed by the disturbance names.
    disturbance_bounds: list[Bounds] | None = None

    @field_validator("disturbance_bounds", mode="before")
    @classmethod
    def _disturbance_bounds_map(cls, value: Any, info: ValidationInfo) -> Any:
        return _bounds_by_name(value, info.data.get("disturbances"), "disturbance")

    @field_validator("input_bounds", mode="before")
    @classmethod
    def _input_bounds_map(cls, value: Any, info: ValidationInfo) -> Any:
        return _bounds_by_name(value, info.data.get("inputs"), "input")

    @field_validator("output_set", mode="before")
    @classmethod
    def _output_set_map(cls, value: Any, info: ValidationInfo) -> Any:
        h = info.data.get("h")
        return _bounds_by_name(value, [f"y{k + 1}" for k in range(len(h))] if isinstance(h, list) else None, "output")


class LinearisationPoint(_Strict):
    """A state and an input of the plant (``stabilisability.linearise_at``)."""

    x: list[FiniteFloat] = Field(min_length=1)
    u: list[FiniteFloat] = Field(min_length=1)


class Stabilisability(_Strict):
    """How the incremental Lyapunov function V(x, z) = (x - z)^T M (x - z) is obtained (eq. (28))."""

    method: Literal["polytopic_lmi", "given"]
    decay_rate: Annotated[float, Field(gt=0, allow_inf_nan=False)] | Literal["maximise"]
    feedback: Literal["identity", "linear_gain"] = "identity"
    #: ``method: given``: the matrix of V(x, z) = (x - z)^T M (x - z), n x n symmetric positive definite, or ``lyapunov``
    #: (M from the Lyapunov equation of the closed loop linearised at ``linearise_at``, shifted by the decay rate).
    M: list[list[FiniteFloat]] | Literal["lyapunov"] | None = None
    #: ``method: given`` with ``feedback: linear_gain``: the gain K (m x n) of k(z, x, u) = u + K (z - x), or ``lqr``
    #: (K = -R^-1 B^T P of the Riccati equation of the linearisation, Q = I, R = I).
    K: list[list[FiniteFloat]] | Literal["lqr"] | None = None
    #: Where ``M: lyapunov`` and ``K: lqr`` linearise the plant: the states and the inputs (default: the centres of
    #: ``concrete.state_box`` and of ``concrete.input_bounds``); also the centre of the norm-bound proof.
    linearise_at: LinearisationPoint | None = None
    #: The form of M searched by ``polytopic_lmi``: ``full``, ``diagonal`` (n unknowns, a sparse LMI: fast for
    #: large networks), or ``auto`` (full up to ``stabilise.FULL_MAX_STATES`` states, else diagonal first and
    #: full only if the diagonal LMI is infeasible).
    structure: Literal["auto", "full", "diagonal"] = "auto"
    #: What the search optimises: ``rate`` (the decay rate as given, or the largest with ``maximise``) or
    #: ``min_gain`` (the M that minimises the gain G of the bound at the decay rate, or over the lambda-G frontier
    #: with ``maximise``).
    objective: Literal["rate", "min_gain"] = "rate"


DeltaSpec = Literal["identity", "flatten"] | list[list[Expr]] | Expr


class Abstract(_Strict):
    """The abstract system xi' = phi_bar(xi) + delta(xi) v, psi = kappa(xi) (eq. (2) in the input-affine form of eq. (12))."""

    states: list[Name] = Field(min_length=1)
    inputs: list[Name] = Field(min_length=1)
    phi_bar: list[Expr]
    l: list[Expr]
    domain: Literal["auto"] | list[Bounds]
    delta: DeltaSpec = "identity"
    #: Relative residual the polynomial solver of the invariance PDE must reach on an independent grid.
    pde_tolerance: Annotated[float, Field(gt=0, lt=1, allow_inf_nan=False)] = 1e-8
    #: Safety cap on the polynomial degree of the PDE solvers, which raise the degree until
    #: ``pde_tolerance`` is met or the fit stops improving (the degree used is reported).  With one abstract
    #: state each piece's degree is at most min(this, 32), and V is split into pieces where one is not enough.
    pde_max_degree: Annotated[int, Field(ge=1, le=128)] = 64
    #: Work budget of the collocation of the invariance PDE with several abstract states: the sum over its
    #: Jacobian evaluations of rows x columns^2 (the arithmetic of one least-squares step); a fit that would exceed
    #: it stops with the best residual reached, naming this key.  A count, never a clock: the same spec gives the
    #: same p on any machine.
    pde_work: Annotated[float, Field(gt=0, allow_inf_nan=False)] = 2e12
    #: A point near the equilibrium p at the centre of V, where Newton continuation starts (phi_bar = 0, no closed form).
    manifold_guess: list[FiniteFloat] | None = None
    #: An explicit left inverse m(x) of p (n_hat expressions in the concrete states and parameters).  The
    #: inverse stage checks it (m(p(xi)) = xi on V, condition (ii) on X_y) instead of constructing one.
    m: list[Expr] | None = None
    #: An explicit manifold p(xi) (n expressions in the abstract states and parameters), where eq. (14a) has several
    #: solutions (the abstraction is the plant itself: p = xi and p = 0).  Checked, never trusted: it must solve
    #: eq. (14a) (symbolically, or to pde_tolerance on a grid of V) and have dp/dxi of full rank.
    p: list[Expr] | None = None


class Interface(_Strict):
    """The interface u_w = l(xi) + q(xi, x) v (eqs. (15), (42), (44)).

    ``saturate``: ``true`` clips each input channel of l + K (x - p) + q v to its bounds (eq. (44));
    ``scale`` multiplies the whole correction K (x - p) + q v by the one factor s in [0, 1] that brings u
    into U (so the correction keeps its direction, and the uniform bound of an identity-feedback design
    holds for any number of inputs); ``false`` applies it unclipped (u may leave U).
    """

    q: Literal["zero", "least_squares"] = "least_squares"
    saturate: bool | Literal["scale"] = True


class Proofs(_Strict):
    """The work budgets of the proofs (interval branch and bound), the same for every stage."""

    #: Boxes one sup, inf or sign search may enclose (``numerics/boxsearch.py``).  When a search spends them short of
    #: its tolerance, its bound is kept (still rigorous, looser) or its claim left "sampled", and the stage says so.  A
    #: count, never a clock: the same spec gives the same numbers on an idle machine and on a loaded one.
    max_boxes: Annotated[int, Field(ge=100, le=100_000_000)] = 20000


class SetpointController(_Strict):
    """v = clip(delta(xi)^+ (gain (xi_ref - xi) - phi_bar(xi)), -v_max, v_max), elementwise."""

    kind: Literal["setpoint"]
    gain: Annotated[float, Field(gt=0, allow_inf_nan=False)]
    v_max: Annotated[float, Field(gt=0, allow_inf_nan=False)]


class GuaranteedController(_Strict):
    """A controller that meets |psi - y| <= tolerance by construction (eq. (9), docs/guaranteed.md).

    ``budget``: the set-point law with the largest v_max for which the uniform bound of Theorem 2,
    sqrt(W0 e^(-(lambda - eps) t) / alpha_h) + G v_max, stays below the tolerance.  ``governor``: v = s v_sp
    with the largest s in [0, 1] that keeps the comparison system's w below tolerance^2 alpha_h.  ``auto``: the
    governor when its conditions hold (it then allows every v the budget allows, and more), else the budget.
    """

    kind: Literal["guaranteed"]
    tolerance: Annotated[float, Field(gt=0, allow_inf_nan=False)]
    gain: Annotated[float, Field(gt=0, allow_inf_nan=False)]
    mode: Literal["auto", "budget", "governor"] = "auto"


class SignalController(_Strict):
    """A user-supplied abstract input v(t) (one expression in t and the parameters per abstract input): the abstraction
    is driven open loop, xi' = phi_bar(xi) + delta(xi) v(t), and the interface makes the plant follow it."""

    kind: Literal["signal"]
    v: Expr | list[Expr]

    def texts(self) -> list[str]:
        """The expressions, one per abstract input."""
        return list(self.v) if isinstance(self.v, list) else [self.v]


class RegisteredController(_Strict):
    """A controller registered by name (docs/guide.md, "Adding a controller"): in Python with
    ``ashc_cli.closedloop.controllers.register``, or by an installed package under the entry-point group
    ``ashc.controllers``.  Its law reads its parameters from ``gain``, ``v_max`` and ``params`` (as its registration
    says); ``falsify`` runs it clipped to |v| <= min(v_max, the certified limit)."""

    kind: Literal["registered"]
    name: Annotated[str, Field(pattern=r"^[A-Za-z_][A-Za-z0-9_]*$", max_length=64)]
    v_max: Annotated[float, Field(gt=0, allow_inf_nan=False)]
    gain: Annotated[float, Field(gt=0, allow_inf_nan=False)] = 1.0
    params: list[FiniteFloat] = Field(default_factory=list, max_length=64)


#: The abstract controllers, told apart by ``kind``.
AbstractController = Annotated[SetpointController | GuaranteedController | SignalController | RegisteredController,
                               Field(discriminator="kind")]
#: The tags of the discriminated unions: pydantic puts them in an error's location, the messages leave them out.
_UNION_TAGS = {"setpoint", "guaranteed", "signal", "registered", "TimedLevel"}


class TimedLevel(_Strict):
    """A reference level with a deadline: held within the tolerance from ``by`` seconds after the switch to it,
    for ``hold`` seconds (a guaranteed controller reports whether its guarantee covers it)."""

    level: FiniteFloat | list[FiniteFloat]
    by: Annotated[float, Field(ge=0, allow_inf_nan=False)]
    hold: Annotated[float, Field(gt=0, allow_inf_nan=False)]


class Tracking(_Strict):
    """The tracking scenario of Figs. 7, 8: set-point levels held for ``dwell`` seconds each, or a reference signal
    r(t) (``reference``, one expression in t per output) sampled every ``reference_period`` seconds and held."""

    t_final: Annotated[float, Field(gt=0, allow_inf_nan=False)]
    xi0: list[FiniteFloat]
    x0: Literal["on_manifold"] | list[FiniteFloat] = "on_manifold"
    reference_levels: list[FiniteFloat | list[FiniteFloat] | TimedLevel] | None = Field(default=None, min_length=1)
    dwell: Annotated[float, Field(gt=0, allow_inf_nan=False)] | None = None
    reference: Expr | list[Expr] | None = None
    reference_period: Annotated[float, Field(gt=0, allow_inf_nan=False)] | None = None
    abstract_controller: AbstractController
    #: A constant disturbance w applied to the plant over the whole run (one value per ``concrete.disturbances``).
    disturbance: list[FiniteFloat] | None = None

    def level_values(self) -> list[float | list[float]]:
        """The levels as numbers (one, or one list per level), deadlines dropped (empty for a reference signal)."""
        return [r.level if isinstance(r, TimedLevel) else r for r in self.reference_levels or []]

    def reference_texts(self) -> list[str]:
        """The reference signal's expressions, one per output (empty for set-point levels)."""
        if self.reference is None:
            return []
        return list(self.reference) if isinstance(self.reference, list) else [self.reference]

    def hold(self) -> float:
        """How long each level is held (s): ``dwell``, or for a reference signal ``reference_period`` (default
        t_final / ``REFERENCE_SAMPLES``); the whole run for an abstract input v(t) (``kind: signal``)."""
        if self.abstract_controller.kind == "signal":
            return float(self.t_final)
        if self.reference is None:
            return float(self.dwell)
        return float(self.reference_period) if self.reference_period is not None else self.t_final / REFERENCE_SAMPLES

    def segment(self, index: int) -> tuple[float, float] | None:
        """(start, end) in s of the dwell in which level ``index`` is held, None if the run ends before it.

        Level k is held from k dwell to (k + 1) dwell, the last one to t_final (as ``simulate`` runs them).
        """
        start = index * self.dwell
        if start >= self.t_final - 1e-12:
            return None
        last = index == len(self.reference_levels) - 1
        return start, self.t_final if last else min(self.t_final, (index + 1) * self.dwell)


#: A reference signal without ``reference_period`` is sampled this many times over the run (and held in between).
REFERENCE_SAMPLES = 400


class MRelation(_Strict):
    """The m-relation scenario of Figs. 9, 10: v = b(x) + c(x) u, xi0 = m(x0)."""

    t_final: Annotated[float, Field(gt=0, allow_inf_nan=False)]
    x0: list[FiniteFloat]
    u: Expr | list[Expr]


class Simulate(_Strict):
    """The simulation scenarios; either may be left out."""

    tracking: Tracking | None = None
    m_relation: MRelation | None = None


class TaskReach(_Strict):
    """Reach ``set`` by ``by`` seconds and hold it ``hold`` seconds: F_[0, by] G_[0, hold] (y in set)."""

    set: list[Bounds] = Field(min_length=1)
    by: Annotated[float, Field(ge=0, allow_inf_nan=False)]
    hold: Annotated[float, Field(ge=0, allow_inf_nan=False)] = 0.0


class TaskAvoid(_Strict):
    """Stay out of ``set`` during the window ``during`` = [a, b] seconds: G_[a, b] (y not in set)."""

    set: list[Bounds] = Field(min_length=1)
    during: Bounds


class TaskPlanner(_Strict):
    """Which planner ``ashc synthesize`` runs on the abstraction (docs/guide.md, "The planner on the abstraction").

    ``setpoint`` aims the set-point law at each reach set in turn, in the budget mode (one abstract state);
    ``error_aware`` does too, with the comparison bound w carried along the plan and each period's input scaled to
    keep it below alpha_h EPS^2, the sets deflated by sqrt(w(t) / alpha_h) (one abstract state; docs/guaranteed.md);
    ``grid`` solves the task as a game on a uniform grid of V with the input held over ``tau`` (proved); ``auto`` (the
    default) runs error-aware planning with one abstract state, then the budget's set-point plan, then the grid when
    that plan is refused for an avoid set (the grid can wait or go around); the grid with more abstract states."""

    kind: Literal["auto", "setpoint", "grid", "error_aware"] = "auto"
    #: Cells of V per abstract state [default: 400, 80 x 80 or 24 x 24 x 24].
    cells: list[Annotated[int, Field(ge=2, le=2000)]] | None = None
    #: The sampling period (s) the table's input is held over [default: horizon / 100].
    tau: Annotated[float, Field(gt=0, allow_inf_nan=False)] | None = None
    #: Abstract inputs per abstract input axis, spread over [-v_max, v_max] [default: 5].
    inputs: Annotated[int, Field(ge=2, le=41)] = 5


class Task(_Strict):
    """A task on the output over a finite horizon, a bounded-time fragment of signal temporal logic
    (``docs/spec-format.md``, "task"): ``always`` a box, each ``reach`` by its deadline and held, each ``avoid``
    box left alone in its window.  Each set is one [lo, hi] interval per output."""

    horizon: Annotated[float, Field(gt=0, allow_inf_nan=False)]
    always: list[Bounds] | None = Field(default=None, min_length=1)
    reach: list[TaskReach] = Field(default_factory=list)
    avoid: list[TaskAvoid] = Field(default_factory=list)
    x0: Literal["on_manifold"] | list[FiniteFloat] = "on_manifold"
    #: The abstract start [default: simulate.tracking.xi0].
    xi0: list[FiniteFloat] | None = None
    #: The planner on the abstraction [default: auto].
    planner: TaskPlanner | None = None


class Spec(_Strict):
    """A whole ashc spec (``docs/spec-format.md``)."""

    name: Annotated[str, Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]*$", max_length=100)]
    description: str = ""
    parameters: dict[Name, FiniteFloat] = Field(default_factory=dict)
    concrete: Concrete
    stabilisability: Stabilisability
    abstract: Abstract
    interface: Interface = Field(default_factory=Interface)
    #: Work budgets of the proofs (``proofs.max_boxes``).
    proofs: Proofs = Field(default_factory=Proofs)
    simulate: Simulate = Field(default_factory=Simulate)
    #: An output task (reach, hold, avoid) for `ashc synthesize`; None: no task.
    task: Task | None = None
    #: Units for figure axes: keys are declared state/input names, ``t``, ``y`` (every output) or ``y1``, ``y2``, ...
    units: dict[str, Annotated[str, Field(max_length=20)]] = Field(default_factory=dict)

    @property
    def sha256(self) -> str:
        """SHA-256 of the spec's canonical JSON: comments and layout do not change it."""
        return spec_sha256(self)


def canonical(spec: Spec) -> dict:
    """A spec's canonical data: its validated values as JSON types, keys added in later versions left out when absent.

    Bounds given as a map are stored as the list in name order, so both forms read alike; ``abstract.m``, the task, the
    proofs' default budgets and the tracking scenario's optional keys are left out when absent, so specs without them
    hash as they did before the keys existed.

    Parameters
    ----------
    spec : Spec
        A validated spec.

    Returns
    -------
    dict
        JSON-able.
    """
    data = spec.model_dump(mode="json")
    if data["abstract"].get("m") is None:
        data["abstract"].pop("m", None)
    for key in ("f", "disturbances", "e", "disturbance_bounds"):     # added later: absent, not null
        if data["concrete"].get(key) is None:
            data["concrete"].pop(key, None)
    if data.get("task") is None:          # added later: a spec without a task hashes as before
        data.pop("task", None)
    elif data["task"].get("planner") is None:
        data["task"].pop("planner", None)
    if data.get("proofs") == Proofs().model_dump(mode="json"):     # added later: the default budgets hash as before
        data.pop("proofs", None)
    tracking = (data.get("simulate") or {}).get("tracking") or {}
    for key in ("reference", "reference_period", "reference_levels", "dwell", "disturbance"):   # keys added later, or left out: absent, not null
        if key in tracking and tracking[key] is None:
            tracking.pop(key)
    return data


def spec_sha256(spec: Spec) -> str:
    """SHA-256 of a spec's canonical JSON form (sorted keys, validated values; :func:`canonical`).

    Parameters
    ----------
    spec : Spec
        A validated spec.

    Returns
    -------
    str
        The digest in hex (64 characters).
    """
    text = json.dumps(canonical(spec), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def keys_sha256(spec: Spec, keys: Sequence[str]) -> str:
    """SHA-256 of the values of some keys of a spec (what one stage reads): another key may change without changing it.

    Parameters
    ----------
    spec : Spec
        A validated spec.
    keys : sequence of str
        Dotted keys (``concrete``, ``abstract.states``); a key the spec leaves out reads as null.

    Returns
    -------
    str
        The digest in hex (64 characters).
    """
    data = canonical(spec)
    picked = {}
    for key in keys:
        node = data
        for part in key.split("."):
            node = node.get(part) if isinstance(node, dict) else None
        picked[key] = node
    text = json.dumps(picked, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


# --- YAML ----------------------------------------------------------------------------------------------


#: What a YAML document's top level is, in YAML's words (not Python's type names).
_YAML_KINDS = {"list": "a list", "str": "a string", "int": "a number", "float": "a number", "bool": "a boolean"}


# --- validation errors to one line -----------------------------------------------------------------------


_FIELD = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_TAGS = {"float", "int", "str", "bool", "list", "dict"}  # pydantic's names for Union branches


def _path(loc: tuple) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out or "spec"


def _model_at(loc: tuple, branch: str | None = None) -> type[BaseModel] | None:
    """The pydantic model that holds the keys at ``loc`` (for suggesting a key), if one does.

    ``branch``: the tag of the union member the location is in (``guaranteed``, ``TimedLevel``), if any.
    """
    model: Any = Spec
    last = max((k for k, part in enumerate(loc) if not isinstance(part, int)), default=-1)
    for k, part in enumerate(loc):
        if isinstance(part, int) or model is None:
            continue
        field = model.model_fields.get(part)
        if field is None:
            return None
        model = _first_model(field.annotation, branch if k == last else None)
    return model


def _tags_at(loc: tuple) -> list[str]:
    """The tags of the union members a field at ``loc`` may hold (``setpoint``, ``guaranteed``)."""
    parent = _model_at(loc[:-1]) if loc else None
    field = parent.model_fields.get(loc[-1]) if parent is not None and isinstance(loc[-1], str) else None
    found: list[str] = []

    def walk(annotation: Any) -> None:
        if isinstance(annotation, type) and issubclass(annotation, BaseModel):
            found.append(_tag_of(annotation))
        else:
            for arg in typing.get_args(annotation):
                walk(arg)

    if field is not None:
        walk(field.annotation)
    return found


def _tag_of(model: type[BaseModel]) -> str:
    """The tag pydantic gives a union member in an error's location: its ``kind`` literal, else its class name."""
    kind = model.model_fields.get("kind")
    args = typing.get_args(kind.annotation) if kind is not None else ()
    return str(args[0]) if args else model.__name__


def _first_model(annotation: Any, branch: str | None = None) -> type[BaseModel] | None:
    """The model an annotation refers to: the union member tagged ``branch`` when given, else the first one."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation if branch is None or _tag_of(annotation) == branch else None
    origin = typing.get_origin(annotation)
    if origin in (Union, types.UnionType, list) or origin is Annotated:
        for arg in typing.get_args(annotation):
            found = _first_model(arg, branch)
            if found is not None:
                return found
    return None


def _short(value: Any, limit: int = 50) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _validation_to_spec_error(exc: ValidationError) -> SpecError:
    errors = exc.errors()
    # An unknown key explains the "missing" errors it causes, so it goes first; otherwise a Union
    # reports one error per branch and the most specific (longest location) says most.
    err = max(errors, key=lambda e: (e["type"] == "extra_forbidden", len(e["loc"])))
    kind = err["type"]
    if kind == "extra_forbidden":
        # The offending key can be anything YAML allows (a number, punctuation): keep it as it is.
        parent = tuple(p for p in err["loc"][:-1] if isinstance(p, int) or (_FIELD.match(p) and p not in _TAGS))
        branch = next((p for p in err["loc"][:-1] if p in _UNION_TAGS), None)   # the union member holding the key
        parent = tuple(p for p in parent if p not in _UNION_TAGS)
        key = str(err["loc"][-1]) if err["loc"] else "?"
        model = _model_at(parent, branch)
        valid = sorted(model.model_fields) if model else []
        close = difflib.get_close_matches(key, valid, n=1)
        hint = f" (did you mean '{close[0]}'?)" if close else ""
        return SpecError(_path(parent + (key,)), f"unknown key {_short(key)}{hint}", f"one of the keys {', '.join(valid)}")
    loc = tuple(p for p in err["loc"] if isinstance(p, int) or (_FIELD.match(p) and p not in _TAGS and p not in _UNION_TAGS))
    where = _path(loc)
    if kind == "missing":
        return SpecError(where, "missing", "this key (see docs/spec-format.md)")
    value = err.get("input")
    if kind in ("union_tag_invalid", "union_tag_not_found"):
        ctx = err.get("ctx") or {}
        key = ctx.get("discriminator", "kind").strip("'")
        tags = ctx.get("expected_tags", "").replace("'", "") or ", ".join(_tags_at(loc))
        shown = f"{key} {_short(value.get(key))}" if isinstance(value, dict) and key in value else f"no {key}"
        return SpecError(f"{where}.{key}" if kind == "union_tag_invalid" else where,
                         f"{shown} is not one of the kinds" if kind == "union_tag_invalid" else f"{shown} given (got {_short(value)})",
                         f"{key}: {' or '.join(t.strip() for t in tags.split(','))}" if tags else f"a {key}")
    return SpecError(where, f"{_plain_message(kind, err)} (got {_short(value)})", _expected_for(kind, err))


def _plain_message(kind: str, err: dict) -> str:
    """pydantic's message for an error, in the spec's words (no "after validation", no regular expressions)."""
    ctx = err.get("ctx") or {}
    if kind in ("too_short", "too_long") and "actual_length" in ctx:
        count = ctx["actual_length"]
        return f"has {count} item{'s' if count != 1 else ''}"
    if kind == "string_pattern_mismatch":
        return "is not a name of letters, digits, '_', '.' and '-' starting with a letter or digit"
    if kind == "string_too_long":
        return f"is longer than {ctx.get('max_length')} characters"
    return err["msg"].replace("Value error, ", "")


def _expected_for(kind: str, err: dict) -> str:
    ctx = err.get("ctx") or {}
    if kind == "literal_error":
        return ctx.get("expected", "one of the listed values")
    if kind == BOUNDS_MAP_ERROR:
        return ctx["expected"]
    if kind in ("too_short", "too_long"):
        if ctx.get("field_type") == "List" and ctx.get("min_length") == 2 and ctx.get("max_length", 2) == 2:
            return "a pair [lo, hi]"
        least, most = ctx.get("min_length"), ctx.get("max_length")
        return f"at least {least} item(s)" if kind == "too_short" and least is not None else f"at most {most} item(s)" if most is not None else "the right number of items"
    if kind == "string_pattern_mismatch":
        return "a name such as cuk_converter"
    if kind == "string_too_long":
        return f"at most {ctx.get('max_length')} characters"
    if kind.startswith("finite") or "nan" in kind:
        return "a finite number"
    if kind.startswith("greater_than_equal"):
        return f"a number >= {ctx.get('ge')}"
    if kind.startswith("greater_than"):
        return f"a number > {ctx.get('gt')}"
    return "a value of the type docs/spec-format.md gives"


# --- shapes across fields ---------------------------------------------------------------------------------


# --- entry points ---------------------------------------------------------------------------------------


def parse_spec_text(text: str, source: str = "spec") -> Spec:
    """Validate spec text (YAML) into a :class:`Spec`.

    Parameters
    ----------
    text : str
        The YAML text.
    source : str
        Where it came from (a path), for error messages.

    Returns
    -------
    Spec

    Raises
    ------
    SpecError
        On malformed YAML, a missing or unknown key, a wrong type, length or value.
    """
    data = load_yaml(text, source)
    if not isinstance(data, dict):
        what = "empty" if data is None else f"top level is {_YAML_KINDS.get(type(data).__name__, type(data).__name__)}"
        raise SpecError(source, what, "a YAML mapping with keys name, concrete, stabilisability, abstract, ...")
    try:
        spec = Spec.model_validate(data)
    except ValidationError as exc:
        raise _validation_to_spec_error(exc) from None
    check_shapes(spec)
    if spec.concrete.f is not None and "q" not in spec.interface.model_fields_set:
        # q = least_squares needs g(x); a plant written as f(x, u) is designed with q = 0 (Proposition 1) unless
        # the spec asks for it (the model then refuses it, or allows it when f is affine in u after all).
        spec = spec.model_copy(update={"interface": spec.interface.model_copy(update={"q": "zero"})})
    return spec


def load_spec(path: str | Path) -> Spec:
    """Read and validate a spec file.

    Parameters
    ----------
    path : str or Path
        The YAML file.

    Returns
    -------
    Spec
        The validated spec.

    Raises
    ------
    SpecError
        If the file cannot be read or is not a valid spec.
    """
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > MAX_SPEC_BYTES:
            raise SpecError(str(path), f"file is {size} bytes", f"a spec under {MAX_SPEC_BYTES} bytes")
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SpecError(str(path), "no such file", "the path of a YAML spec") from None
    except IsADirectoryError:
        raise SpecError(str(path), "is a directory", "the path of a YAML spec") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SpecError(str(path), f"cannot be read ({type(exc).__name__})", "a readable UTF-8 YAML file") from None
    return parse_spec_text(text, str(path))

