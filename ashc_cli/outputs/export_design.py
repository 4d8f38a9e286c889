"""What the exported code is made of (:class:`Design`): the formulas and numbers of a finished design, gathered
from a spec and its design's artefacts and checked to be current (:func:`require_current`).  The printers
(:mod:`ashc_cli.outputs.printers`) turn it into C or Python; :mod:`ashc_cli.outputs.export` writes the files."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import sympy as sp

from ashc_cli.design.artefacts import Artefact
from ashc_cli.design.pipeline import made_from
from ashc_cli.errors import ArtefactError
from ashc_cli.problem.influence import cone_model
from ashc_cli.problem.spec import Spec
from ashc_cli.design.upstream import certified_set


__all__ = ["NEEDED", "STATUS", "Design", "gather", "require_current"]

#: The stages whose artefacts the exported code is built from.
NEEDED = ("stabilise", "manifold", "kappa", "inverse", "delta", "bound")
#: The status ``ashc_m`` returns, by value.
STATUS = {0: "ok", 1: "outside the certified set (h(x) not in inverse.m_domain)", 2: "m is not real at x"}


# --- what the exported code is made of -------------------------------------------------------------------


@dataclass(frozen=True)
class TaskPlanExport:
    """The task's plan as the exported code replays it (:mod:`ashc_cli.design.task_plan`): from ``switches[k]`` on,
    the set-point law with ``gain`` and ``v_max`` aims at ``refs[k]``; or, for the grid planner (``law`` "held"), the
    table's input for the period starting at ``switches[k]`` is held (its first m_hat entries of ``refs[k]``): the
    inputs the table chooses along its route from ``xi0``, which is the abstraction's own run whatever the plant does.

    Attributes
    ----------
    switches : ndarray (K,)
        When each segment starts (the first at 0).
    refs : ndarray (K, n_hat)
        The reference state of each segment (the reach sets' references the plan switched to, in order).
    gain, v_max, eps : float
        The set-point gain, the elementwise clip of v (the budget mode) and the tolerance EPS it guarantees.
    xi0 : ndarray (n_hat,)
        The plan's start.
    law : str
        ``setpoint`` or ``held`` (the grid planner's table).
    """

    switches: np.ndarray
    refs: np.ndarray
    gain: float
    v_max: float
    eps: float
    xi0: np.ndarray
    law: str = "setpoint"

    @property
    def prm(self) -> np.ndarray:
        """The law's parameters: [gain, v_max] for the set-point law, [v_max] for the held input."""
        return np.array([self.v_max] if self.law == "held" else [self.gain, self.v_max], dtype=float)

    @staticmethod
    def of(plan) -> TaskPlanExport:
        """From a :class:`~ashc_cli.design.task_plan.TaskPlan`."""
        switches = np.asarray(plan.switches, dtype=float).reshape(-1)
        refs = np.stack([np.asarray(r, dtype=float).reshape(-1) for r in plan.refs])[:switches.size]   # the segments the plan ran
        return TaskPlanExport(switches, refs, float(plan.gain), float(plan.v_max), float(plan.eps), np.asarray(plan.xi0, dtype=float).reshape(-1),
                              plan.law().kind)

    def reference(self, t: float) -> np.ndarray:
        """The plan's reference at time t (the segment that started last; the first before 0)."""
        k = int(np.searchsorted(self.switches, float(t), side="right")) - 1
        return self.refs[max(k, 0)]


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
    plan : TaskPlanExport or None
        The task's plan (``ashc synthesize``), when the spec has a task.
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
    plan: TaskPlanExport | None = None

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
        if not made_from(spec, stage, art.provenance):
            raise ArtefactError(f"{stage}.h5", f"was made from another spec than '{spec.name}' (SHA-256 differs)",
                                "the folder designed from this spec (`ashc design SPEC --out DIR`)")


def gather(spec: Spec, arts: Mapping[str, Artefact], plan: TaskPlanExport | None = None) -> Design:
    """The expressions and numbers of a design that the exported code is made of.

    Parameters
    ----------
    spec : Spec
        The design's spec (for phi_bar, l, g, U, the interface and the controller, which no artefact holds).
    arts : mapping of str to Artefact
        The artefacts of stages :data:`NEEDED`.
    plan : TaskPlanExport, optional
        The task's plan, exported with ``ashc_plan_reference`` and ``ashc_plan_controller``.

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
    model = cone_model(spec)
    inverse = arts["inverse"]
    box, set_name, _ = certified_set(inverse)
    K = np.asarray(arts["stabilise"].values.get("K", np.zeros((model.m, model.n))), dtype=float).reshape(model.m, model.n)
    V = model.V if model.V is not None else np.asarray(arts["manifold"].value("V"), dtype=float)
    tracking = spec.simulate.tracking
    ctl = tracking.abstract_controller if tracking is not None and tracking.abstract_controller.kind == "setpoint" else None
    provenance = {"spec": spec.sha256, **{stage: str(arts[stage].provenance.get("sha256", "")) for stage in NEEDED}}
    design = Design(
        name=spec.name, provenance=provenance, states=list(model.spec.concrete.states), inputs=list(spec.concrete.inputs),
        abstract_states=list(spec.abstract.states), abstract_inputs=list(spec.abstract.inputs), n_outputs=model.p,
        parameters={k: float(v) for k, v in spec.parameters.items()},
        phi_bar=model.phi_bar, l=model.l, delta=arts["delta"].expr("delta"), p=arts["manifold"].expr("p"),
        kappa=arts["kappa"].expr("kappa"), dp_delta=arts["bound"].expr("dp_delta"), g=arts["bound"].expr("g"),
        h=inverse.expr("h"), m=inverse.expr("m"),
        U=np.asarray(model.U, dtype=float), V=np.asarray(V, dtype=float).reshape(model.n_hat, 2), m_domain=box, m_domain_set=set_name,
        K=K if np.any(K != 0) else None, L=np.asarray(arts["bound"].value("L"), dtype=float).reshape(model.n, model.n),
        q=spec.interface.q, saturate=spec.interface.saturate,
        gain=None if ctl is None else float(ctl.gain), v_max=None if ctl is None else float(ctl.v_max), plan=plan,
    )
    expected = {"phi_bar": (design.n_hat, 1), "l": (design.n_inputs, 1), "delta": (design.n_hat, design.m_hat),
                "p": (design.n, 1), "kappa": (design.n_outputs, 1), "dp_delta": (design.n, design.m_hat),
                "g": (design.n, design.n_inputs), "h": (design.n_outputs, 1), "m": (design.n_hat, 1)}
    for key, shape in expected.items():
        if tuple(getattr(design, key).shape) != shape:
            raise ArtefactError(key, f"has shape {tuple(getattr(design, key).shape)}, the spec's names need {shape}",
                                "artefacts made from this spec (`ashc design SPEC --force`)")
    return design


