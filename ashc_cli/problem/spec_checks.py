"""The checks of a spec that tie its keys together (sizes n, m, p, n_hat, m_hat, names, references), run by
:func:`ashc_cli.problem.spec.parse_spec_text` after pydantic has validated each key on its own."""

from __future__ import annotations

from typing import TYPE_CHECKING

from ashc_cli.errors import SpecError

if TYPE_CHECKING:     # the classes are spec.py's, which imports this module: annotations only, no import cycle
    from ashc_cli.problem.spec import Concrete, Spec, Tracking

__all__ = ["check_shapes", "MAX_REFERENCE_SAMPLES"]


def _check_pair(where: str, pair: list[float]) -> None:
    lo, hi = pair
    if lo > hi:
        raise SpecError(where, f"lo = {lo} > hi = {hi}", "a pair [lo, hi] with lo <= hi")


def _check_len(where: str, items: list, n: int, what: str) -> None:
    if len(items) != n:
        raise SpecError(where, f"has {len(items)} entries", f"{n} ({what})")


def check_shapes(spec: Spec) -> None:
    """Check the dimensions that tie fields together (n, m, p, n_hat, m_hat) and name clashes.

    Parameters
    ----------
    spec : Spec
        A spec its models have validated key by key.

    Raises
    ------
    SpecError
        Naming the first field whose length or contents do not fit.
    """
    c, a = spec.concrete, spec.abstract
    n, m, p = len(c.states), len(c.inputs), len(c.h)
    nh, mh = len(a.states), len(a.inputs)
    _check_dynamics(c, n, m)
    _check_disturbances(c, n)
    _check_len("concrete.input_bounds", c.input_bounds, m, "one pair per input")
    _check_len("concrete.output_set", c.output_set, p, "one pair per output of h")
    for key, pairs in (("concrete.input_bounds", c.input_bounds), ("concrete.output_set", c.output_set)):
        for i, pair in enumerate(pairs):
            _check_pair(f"{key}[{i}]", pair)
    if c.state_box is not None:
        _check_len("concrete.state_box", c.state_box, n, "one pair per state")
        for i, pair in enumerate(c.state_box):
            _check_pair(f"concrete.state_box[{i}]", pair)
    if a.manifold_guess is not None:
        _check_len("abstract.manifold_guess", a.manifold_guess, n, "one number per concrete state")
    if a.m is not None:
        _check_len("abstract.m", a.m, nh, "one expression in the concrete states per abstract state")
    if a.p is not None:
        _check_len("abstract.p", a.p, n, "one expression in the abstract states per concrete state")
    _check_len("abstract.phi_bar", a.phi_bar, nh, "one per abstract state")
    _check_len("abstract.l", a.l, m, "one per concrete input")
    if a.domain != "auto":
        _check_len("abstract.domain", a.domain, nh, "one pair per abstract state")
        for i, pair in enumerate(a.domain):
            _check_pair(f"abstract.domain[{i}]", pair)
    if isinstance(a.delta, list):
        _check_len("abstract.delta", a.delta, nh, "one row per abstract state")
        for i, row in enumerate(a.delta):
            _check_len(f"abstract.delta[{i}]", row, mh, "one column per abstract input")
    elif a.delta == "identity" and nh != mh:
        raise SpecError("abstract.delta", f"'identity' needs as many abstract inputs as states, got {mh} and {nh}", "an n_hat x m_hat matrix of expressions")
    elif a.delta not in ("identity", "flatten") and (nh, mh) != (1, 1):
        raise SpecError("abstract.delta", "a single expression needs one abstract state and one input", f"a {nh} x {mh} matrix of expressions")
    _check_given(spec, n, m)
    _check_names(spec)
    _check_units(spec)
    _check_simulate(spec, n, m, p, nh, mh)
    _check_task(spec, n, p, nh)


def _check_given(spec: Spec, n: int, m: int) -> None:
    """stabilisability.M, K and linearise_at: their shapes, and that they come with the method and feedback that read them."""
    st = spec.stabilisability
    if st.linearise_at is not None:     # read by method given and by polytopic_lmi's norm-bound route
        _check_len("stabilisability.linearise_at.x", st.linearise_at.x, n, "one value per state")
        _check_len("stabilisability.linearise_at.u", st.linearise_at.u, m, "one value per input")
    if st.method != "given":
        for key in ("M", "K"):
            if getattr(st, key) is not None:
                raise SpecError(f"stabilisability.{key}", "given with method 'polytopic_lmi'", f"method: given, or no {key}")
        return
    if st.M is None:
        raise SpecError("stabilisability.M", "missing for method 'given'", f"a symmetric {n} x {n} matrix, or lyapunov")
    if st.M != "lyapunov":
        _check_len("stabilisability.M", st.M, n, "one row per state")
        for i, row in enumerate(st.M):
            _check_len(f"stabilisability.M[{i}]", row, n, "one column per state")
    if st.K is not None and st.feedback != "linear_gain":
        raise SpecError("stabilisability.K", f"given with feedback '{st.feedback}'", "feedback: linear_gain (k(z, x, u) = u + K (z - x)), or no K")
    if st.feedback == "linear_gain" and st.K is None:
        raise SpecError("stabilisability.K", "missing for method 'given' with feedback 'linear_gain'", f"a {m} x {n} matrix, or lqr")
    if isinstance(st.K, list):
        _check_len("stabilisability.K", st.K, m, "one row per input")
        for i, row in enumerate(st.K):
            _check_len(f"stabilisability.K[{i}]", row, n, "one column per state")



def _check_box(where: str, box: list[list[float]], p: int) -> None:
    """A set of the task: one [lo, hi] interval per output, lo < hi."""
    _check_len(where, box, p, "one [lo, hi] interval per output")
    for i, (lo, hi) in enumerate(box):
        if not lo < hi:
            raise SpecError(f"{where}[{i}]", f"lo = {lo:g} >= hi = {hi:g}", "an interval [lo, hi] with lo < hi")


def _check_task(spec: Spec, n: int, p: int, nh: int) -> None:
    """The task's sets have one interval per output; deadlines, holds and windows lie within the horizon; the
    reaches come in the order of their deadlines; there is an abstract start."""
    task = spec.task
    if task is None:
        return
    H = task.horizon
    if task.always is None and not task.reach and not task.avoid:
        raise SpecError("task", "asks for nothing (no always, reach or avoid)", "at least one of always, reach, avoid")
    if task.always is not None:
        _check_box("task.always", task.always, p)
    last = 0.0
    for k, r in enumerate(task.reach):
        _check_box(f"task.reach[{k}].set", r.set, p)
        if r.by + r.hold > H * (1 + 1e-12):
            raise SpecError(f"task.reach[{k}].by", f"by + hold = {r.by + r.hold:g} s is past the horizon {H:g} s",
                            "a deadline and hold that end within task.horizon")
        if r.by < last:
            raise SpecError(f"task.reach[{k}].by", f"{r.by:g} s is before the deadline of reach {k - 1} ({last:g} s)",
                            "the reaches in the order they are to be met (deadlines non-decreasing)")
        last = r.by
    for k, a in enumerate(task.avoid):
        _check_box(f"task.avoid[{k}].set", a.set, p)
        t0, t1 = a.during
        if not 0 <= t0 <= t1 <= H * (1 + 1e-12):
            raise SpecError(f"task.avoid[{k}].during", f"[{t0:g}, {t1:g}]", f"a window [a, b] with 0 <= a <= b <= horizon = {H:g} s")
    if task.x0 != "on_manifold":
        _check_len("task.x0", task.x0, n, "one per concrete state")
    xi0 = task.xi0 if task.xi0 is not None else (spec.simulate.tracking.xi0 if spec.simulate.tracking is not None else None)
    if xi0 is None:
        raise SpecError("task.xi0", "missing (and no simulate.tracking.xi0 to take)", "the abstract start, one number per abstract state")
    _check_len("task.xi0", xi0, nh, "one per abstract state")
    if task.planner is not None and task.planner.cells is not None:
        _check_len("task.planner.cells", task.planner.cells, nh, "one cell count per abstract state")


def _check_dynamics(c: Concrete, n: int, m: int) -> None:
    """Either f_bar and g, or f alone, each of its shape."""
    given = [k for k in ("f_bar", "g", "f") if getattr(c, k) is not None]
    if c.f is not None and given != ["f"]:
        raise SpecError("concrete.f", f"given with {' and '.join(k for k in given if k != 'f')}", "either f (x' = f(x, u)) or f_bar and g (x' = f_bar(x) + g(x) u), not both")
    if c.f is not None:
        _check_len("concrete.f", c.f, n, "one expression in the states and inputs per state")
        return
    for key in ("f_bar", "g"):
        if getattr(c, key) is None:
            raise SpecError(f"concrete.{key}", "is missing", "f_bar and g (x' = f_bar(x) + g(x) u), or f alone (x' = f(x, u))")
    _check_len("concrete.f_bar", c.f_bar, n, "one per state")
    _check_len("concrete.g", c.g, n, "one row per state")
    for i, row in enumerate(c.g):
        _check_len(f"concrete.g[{i}]", row, m, "one column per input")


def _check_disturbances(c: Concrete, n: int) -> None:
    """disturbances, e and disturbance_bounds all given or none; e is n x d, one bound per disturbance."""
    given = [k for k in ("disturbances", "e", "disturbance_bounds") if getattr(c, k) is not None]
    if not given:
        return
    missing = [k for k in ("disturbances", "e", "disturbance_bounds") if k not in given]
    if missing:
        raise SpecError(f"concrete.{missing[0]}", f"is missing (concrete.{given[0]} is given)",
                        "disturbances (names), e (n rows of one expression per disturbance) and disturbance_bounds together")
    d = len(c.disturbances)
    if d == 0:
        raise SpecError("concrete.disturbances", "is empty", "at least one disturbance name, or no disturbance keys")
    _check_len("concrete.e", c.e, n, "one row per state")
    for i, row in enumerate(c.e):
        _check_len(f"concrete.e[{i}]", row, d, "one column per disturbance")
    _check_len("concrete.disturbance_bounds", c.disturbance_bounds, d, "one pair per disturbance")
    for i, pair in enumerate(c.disturbance_bounds):
        _check_pair(f"concrete.disturbance_bounds[{i}]", pair)


def _check_disturbance_run(spec: Spec) -> None:
    """tracking.disturbance: one value per disturbance, inside its bounds, not with a guaranteed controller."""
    tr, c = spec.simulate.tracking, spec.concrete
    if tr is None or tr.disturbance is None:
        return
    if c.disturbances is None:
        raise SpecError("simulate.tracking.disturbance", "is given but the plant has no concrete.disturbances", "concrete.disturbances, e and disturbance_bounds first")
    _check_len("simulate.tracking.disturbance", tr.disturbance, len(c.disturbances), "one value per disturbance")
    for i, (w, (lo, hi)) in enumerate(zip(tr.disturbance, c.disturbance_bounds)):
        if not lo <= w <= hi:
            raise SpecError(f"simulate.tracking.disturbance[{i}]", f"{w:g} is outside disturbance_bounds [{lo:g}, {hi:g}]", "a value inside the bounds the bound is certified for")
    if tr.abstract_controller.kind == "guaranteed":
        raise SpecError("simulate.tracking.disturbance", "is given with a guaranteed controller, whose guarantee does not count a disturbance",
                        "kind setpoint or signal with a disturbance, or no disturbance")


def _check_names(spec: Spec) -> None:
    seen: dict[str, str] = {}
    groups = [
        ("parameters", list(spec.parameters)),
        ("concrete.states", spec.concrete.states),
        ("concrete.inputs", spec.concrete.inputs),
        ("concrete.disturbances", spec.concrete.disturbances or []),
        ("abstract.states", spec.abstract.states),
        ("abstract.inputs", spec.abstract.inputs),
    ]
    for where, names in groups:
        for name in names:
            if name in seen:
                raise SpecError(where, f"name '{name}' is already used in {seen[name]}", "names unique across parameters, states and inputs")
            seen[name] = where


def _check_units(spec: Spec) -> None:
    c, a = spec.concrete, spec.abstract
    allowed = {*c.states, *c.inputs, *a.states, *a.inputs, "t", "y", *(f"y{k + 1}" for k in range(len(c.h)))}
    for key in spec.units:
        if key not in allowed:
            raise SpecError(f"units.{key}", "is not a declared state or input, t, or an output name", f"one of {', '.join(sorted(allowed))}")


def _check_reference(tr: Tracking, p: int) -> None:
    """Exactly one of reference_levels (with dwell) and reference (with reference_period, optional); none of them
    with an abstract input v(t)."""
    if tr.abstract_controller.kind == "signal":
        given = [k for k in ("reference_levels", "dwell", "reference", "reference_period") if getattr(tr, k) is not None]
        if given:
            raise SpecError(f"simulate.tracking.{given[0]}", "is given with abstract_controller.kind: signal (v(t) drives the abstraction, nothing is tracked)",
                            "no reference with an abstract input v(t); or kind setpoint with reference_levels or reference")
        return
    if (tr.reference_levels is None) == (tr.reference is None):
        which = "both" if tr.reference is not None else "neither"
        raise SpecError("simulate.tracking", f"gives {which} of reference_levels and reference",
                        "reference_levels (set points, with dwell) or reference (a signal r(t), one expression in t per output)")
    if tr.reference_levels is not None:
        if tr.dwell is None:
            raise SpecError("simulate.tracking.dwell", "is missing", "how long each of reference_levels is held (s)")
        if tr.reference_period is not None:
            raise SpecError("simulate.tracking.reference_period", "is given with reference_levels", "reference_period only with reference (dwell holds levels)")
        return
    if tr.dwell is not None:
        raise SpecError("simulate.tracking.dwell", "is given with a reference signal", "reference_period (how often r(t) is sampled and held), or reference_levels")
    _check_len("simulate.tracking.reference", tr.reference_texts(), p, "one expression in t per output")
    if tr.hold() > tr.t_final:
        raise SpecError("simulate.tracking.reference_period", f"{tr.hold():g} s is longer than the run (t_final = {tr.t_final:g} s)", "a period below t_final")
    if tr.t_final / tr.hold() > MAX_REFERENCE_SAMPLES:
        raise SpecError("simulate.tracking.reference_period", f"{tr.hold():g} s samples r(t) {tr.t_final / tr.hold():.0f} times",
                        f"at most {MAX_REFERENCE_SAMPLES} samples over the run (a period of at least {tr.t_final / MAX_REFERENCE_SAMPLES:.3g} s)")


#: The most samples of a reference signal over one run (each is a reference state solved for, and a segment of the run).
MAX_REFERENCE_SAMPLES = 20000


def _check_simulate(spec: Spec, n: int, m: int, p: int, nh: int, mh: int) -> None:
    tr = spec.simulate.tracking
    if tr is not None:
        _check_len("simulate.tracking.xi0", tr.xi0, nh, "one per abstract state")
        if tr.x0 != "on_manifold":
            _check_len("simulate.tracking.x0", tr.x0, n, "one per concrete state")
        _check_reference(tr, p)
        _check_disturbance_run(spec)
        if tr.abstract_controller.kind == "signal":
            _check_len("simulate.tracking.abstract_controller.v", tr.abstract_controller.texts(), mh, "one expression in t per abstract input")
        for i, (entry, level) in enumerate(zip(tr.reference_levels or [], tr.level_values())):
            timed = hasattr(entry, "by")         # a TimedLevel (level, by, hold), not a plain number or list
            where = f"simulate.tracking.reference_levels[{i}]" + (".level" if timed else "")
            size = len(level) if isinstance(level, list) else 1
            if size != p:
                raise SpecError(where, f"has {size} values", f"{p} (one per output)")
            if timed:
                if tr.abstract_controller.kind != "guaranteed":
                    raise SpecError(f"simulate.tracking.reference_levels[{i}]", f"has a deadline (by, hold) but the controller is '{tr.abstract_controller.kind}', which guarantees no tolerance",
                                    "abstract_controller.kind: guaranteed, or a plain level")
                seg = tr.segment(i)
                held = None if seg is None else seg[1] - seg[0]
                if held is None:
                    raise SpecError(f"simulate.tracking.reference_levels[{i}]", f"has a deadline but the run ends (t_final = {tr.t_final:g} s) before level {i} is asked for",
                                    "a t_final that reaches every level with a deadline")
                if entry.by + entry.hold > held * (1 + 1e-12):
                    raise SpecError(f"simulate.tracking.reference_levels[{i}].hold", f"by + hold = {entry.by + entry.hold:g} s runs past the {held:g} s this level is held",
                                    "by + hold within the level's dwell (the last level: up to t_final)")
    mr = spec.simulate.m_relation
    if mr is not None:
        _check_len("simulate.m_relation.x0", mr.x0, n, "one per concrete state")
        us = mr.u if isinstance(mr.u, list) else [mr.u]
        _check_len("simulate.m_relation.u", us, m, "one expression in t per concrete input")
