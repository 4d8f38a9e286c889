"""The abstract controllers, by name: each is one law v = law(t, z, ref, phi, delta, prm, v) compiled with numba
(:data:`~ashc_cli.closedloop.laws.LAW_SIGNATURE`), registered here, and then run by every tracking run
(:func:`ashc_cli.closedloop.runner.closed_loop_run`: ``simulate``, ``tradeoff``, ``synthesize``'s check, the reach
times) and printed by ``ashc export`` when it is written in the subset :mod:`ashc_cli.outputs.translate` reads.

Adding a controller (docs/guide.md, "Adding a controller"; tests/test_controllers.py does it from a test file)::

    @njit(LAW_SIGNATURE, cache=True)
    def proportional(t: float, z: F1, ref: F1, phi: F1, delta: F2, prm: F1, v: F1):
        for a in range(v.size):
            v[a] = min(max(prm[0] * (ref[a] - z[a]), -prm[1]), prm[1])

    register(Controller("proportional", lambda model: proportional, lambda law: np.array([law.gain, law.v_max]),
                        "v = clip(k (xi_ref - xi), -v_max, v_max)", printed=proportional))

The governor of the guaranteed controller is not a law of this kind: it scales the set-point law's v by the
largest s that keeps the comparison system's w below its level, with a loop of its own
(:mod:`ashc_cli.closedloop.governor`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import sympy as sp

from ashc_cli.closedloop import compiled
from ashc_cli.closedloop.laws import held_law, setpoint_law
from ashc_cli.closedloop.plan import Law
from ashc_cli.errors import DesignError, NumericalError
from ashc_cli.problem.expr import parse_expression
from ashc_cli.problem.model import TIME, Model

__all__ = ["Controller", "register", "controller", "names", "REGISTRY", "abstract_input", "law_of", "ENTRY_POINTS"]

#: The entry-point group an installed package registers its controllers under: each entry point names a
#: :class:`Controller` (or a function returning one), loaded the first time a spec names a controller not
#: registered yet.
ENTRY_POINTS = "ashc.controllers"
#: Names the spec's kinds use for other things: not registrable.
_RESERVED = frozenset({"guaranteed", "governor", "registered", "budget"})


@dataclass(frozen=True)
class Controller:
    """One abstract controller.

    Attributes
    ----------
    name : str
        What :class:`~ashc_cli.closedloop.plan.Law` ``kind`` names it.
    law : callable
        ``law(model)``: the compiled law for a design's model (a numba function of
        :data:`~ashc_cli.closedloop.laws.LAW_SIGNATURE`; the signal's is generated from the spec).
    prm : callable
        ``prm(law)``: the law's parameters (1-D float array) from the run's :class:`~ashc_cli.closedloop.plan.Law`.
    says : str
        The law in one line (the comment of the exported ``ashc_controller``).
    printed : function, optional
        The law in the subset ``ashc export`` prints (usually the same numba function); None: not exported.
    """

    name: str
    law: Callable
    prm: Callable[[Law], np.ndarray]
    says: str
    printed: Callable | None = None


#: The registered controllers by name.
REGISTRY: dict[str, Controller] = {}


def register(c: Controller) -> Controller:
    """Register ``c`` under its name (a second registration under one name replaces the first).

    Parameters
    ----------
    c : Controller

    Returns
    -------
    Controller
        ``c``.
    """
    if c.name in _RESERVED:
        raise DesignError("Controller.name", repr(c.name), f"a name other than {sorted(_RESERVED)}")
    REGISTRY[c.name] = c
    return c


def names() -> list[str]:
    """The registered names, sorted."""
    return sorted(REGISTRY)


def controller(name: str) -> Controller:
    """The controller registered as ``name``.

    Parameters
    ----------
    name : str

    Raises
    ------
    DesignError
        Naming the registered ones.
    """
    if name not in REGISTRY:
        _load_entry_points()
    try:
        return REGISTRY[name]
    except KeyError:
        raise DesignError("simulate.tracking.abstract_controller.name", repr(name),
                          f"a registered controller: one of {names()} (or an installed package's, entry points {ENTRY_POINTS})") from None


def _load_entry_points() -> None:
    """Register the controllers installed packages declare under :data:`ENTRY_POINTS` (an entry point that fails
    to load is named in the error)."""
    from importlib.metadata import entry_points

    for ep in entry_points(group=ENTRY_POINTS):
        try:
            obj = ep.load()
            c = obj if isinstance(obj, Controller) else obj()
        except Exception as exc:          # a broken plugin: its name and why, not a traceback
            raise DesignError(f"entry point {ENTRY_POINTS}:{ep.name}", f"{ep.value} did not load ({type(exc).__name__}: {exc})",
                              "a Controller or a function returning one") from exc
        if not isinstance(c, Controller):
            raise DesignError(f"entry point {ENTRY_POINTS}:{ep.name}", f"{ep.value} gave a {type(c).__name__}", "a Controller")
        REGISTRY.setdefault(c.name, c)


def law_of(ctl) -> Law:
    """The run's :class:`~ashc_cli.closedloop.plan.Law` from the spec's ``abstract_controller`` of kind setpoint,
    signal or registered (a guaranteed controller's law comes from its plan, :mod:`~ashc_cli.closedloop.plan`).

    Parameters
    ----------
    ctl : SetpointController, SignalController or RegisteredController

    Returns
    -------
    Law

    Raises
    ------
    DesignError
        If a registered name is not registered (naming those that are).
    """
    if ctl.kind == "signal":
        return Law("signal", 0.0, 0.0)
    if ctl.kind == "registered":
        controller(ctl.name)
        return Law(ctl.name, float(ctl.gain), float(ctl.v_max), params=tuple(float(x) for x in ctl.params))
    return Law("setpoint", float(ctl.gain), float(ctl.v_max))


def abstract_input(model: Model) -> sp.Matrix:
    """The tracking scenario's abstract input v(t) (``abstract_controller.kind: signal``), parsed: one expression in t
    and the parameters per abstract input (the time signals triangle, square, step allowed).

    Parameters
    ----------
    model : Model

    Returns
    -------
    sympy Matrix (m_hat, 1)

    Raises
    ------
    SpecError
        Naming ``simulate.tracking.abstract_controller.v[i]``.
    """
    names = {**model.params, "t": TIME}
    texts = model.spec.simulate.tracking.abstract_controller.texts()
    return sp.Matrix([parse_expression(s, names, f"simulate.tracking.abstract_controller.v[{i}]", signal=True) for i, s in enumerate(texts)])


def _signal_law(model):
    """The spec's v(t) (``abstract_controller.kind: signal``), generated and compiled."""
    try:
        return compiled.abstract_signal(model, abstract_input(model)).law
    except compiled.Unsupported as exc:
        raise NumericalError("simulate", str(exc), "an abstract input v(t) the compiled closed loop can run") from exc


register(Controller("setpoint", lambda model: setpoint_law, lambda law: np.array([law.gain, law.v_max], dtype=float),
                    "v = clip(delta^+ (gain (xi_ref - xi) - phi_bar(xi)), -v_max, v_max)", printed=setpoint_law))
register(Controller("signal", _signal_law, lambda law: np.zeros(0), "v = v(t), the spec's abstract input (open loop)"))
register(Controller("held", lambda model: held_law, lambda law: np.array([law.v_max], dtype=float),
                    "v = the grid planner's input for the period, held (the segment's reference), |v_a| <= v_max", printed=held_law))
