"""The closed-loop runner every scenario and product uses: the tracking loop of the interface and an abstract
controller (a :class:`~ashc_cli.closedloop.plan.Law`) integrated segment by segment on the compiled loop
(:mod:`ashc_cli.closedloop.compiled`, on the one Runge-Kutta engine :mod:`ashc_cli.closedloop.rk`), how runs are
sampled, and the reach times of levels held until reached.  ``simulate``, ``tradeoff``, ``synthesize`` and the task
attack call these; none of them imports a design stage's machinery for it.
"""

from __future__ import annotations

import numpy as np

from ashc_cli.closedloop import compiled, controllers
from ashc_cli.closedloop.controllers import abstract_input
from ashc_cli.closedloop.plan import GOVERNOR_BACKOFF, GOVERNOR_BISECTIONS, GOVERNOR_GRID, Law
from ashc_cli.closedloop.terms import DesignTerms
from ashc_cli.errors import NumericalError
from ashc_cli.problem.model import Model

__all__ = ["SAMPLE_DT", "MAX_RUN_SAMPLES", "TRACKING_TOL", "SETTLE_RTOL", "REACH_HORIZON_DWELLS", "REACH_SAMPLE_DWELLS", "sample_dt",
           "sample_times", "tracking_segments", "tracking_loop_for", "abstract_input", "closed_loop_run", "reach_time", "reach_times"]

#: The tracking loop's integrator and tolerances (recorded in the simulate artefact's meta).
TRACKING_TOL = {"method": "DOP853", "rtol": 1e-9, "atol": 1e-9}
SAMPLE_DT = 1e-3
#: A run is sampled every SAMPLE_DT, or every t_final / MAX_RUN_SAMPLES when that is longer (a process plant over
#: hours: 12000 s at 1 ms were 12 million samples and 3.4 GB).
MAX_RUN_SAMPLES = 200_000
#: psi must end each dwell within this fraction of the output span of its level.
SETTLE_RTOL = 1e-4
#: Reach-time runs (``reach_times``): a level is held in chunks of the spec's dwell until it is reached, at most
#: this many dwells; sampled every REACH_SAMPLE_DWELLS dwell (at least SAMPLE_DT).
REACH_HORIZON_DWELLS = 1000
REACH_SAMPLE_DWELLS = 5e-4


def sample_dt(t_final: float) -> float:
    """The sampling interval of a run of length t_final: SAMPLE_DT, or t_final / MAX_RUN_SAMPLES if longer.

    Parameters
    ----------
    t_final : float
        The run's length (s).

    Returns
    -------
    float
    """
    return max(SAMPLE_DT, float(t_final) / MAX_RUN_SAMPLES)


def sample_times(t0: float, t1: float, dt: float) -> np.ndarray:
    """Sample times t0, t0 + dt, ... strictly below t1, then t1: increasing, never outside [t0, t1].

    (np.arange can overshoot t1 by rounding, which solve_ivp refuses as "not within t_span".)

    Parameters
    ----------
    t0, t1, dt : float
        The interval and the sample spacing (s).

    Returns
    -------
    ndarray (N,)
    """
    n = int(np.floor((t1 - t0) / dt)) + 1
    inner = t0 + dt * np.arange(max(n, 1))
    inner = inner[inner < t1 - 1e-12 * max(1.0, abs(t1))]
    return np.r_[inner, t1]


def tracking_segments(t_final: float, dwell: float, n_levels: int, dt: float = SAMPLE_DT) -> list[tuple[float, float, np.ndarray, int]]:
    """(t0, t1, sample times, level index), one per dwell: level k from k dwell, the last one to t_final.

    Parameters
    ----------
    t_final, dwell : float
        The run's end and how long each level is held (s); the last level is held to t_final.
    n_levels : int
        The number of reference levels.
    dt : float
        The sample spacing (s).

    Returns
    -------
    list of (float, float, ndarray, int)
    """
    segments = []
    t0, k = 0.0, 0
    while t0 < t_final - 1e-12:
        i = min(k, n_levels - 1)
        # Segment ends as multiples of the dwell (not sums, which drift by rounding).
        t1 = t_final if k >= n_levels - 1 else min(t_final, (k + 1) * dwell)
        segments.append((t0, t1, sample_times(t0, t1, dt), i))
        t0, k = t1, k + 1
    return segments


def tracking_loop_for(model: Model, up: dict, law: Law):
    """The compiled tracking loop for ``law`` (:func:`ashc_cli.closedloop.compiled.tracking_loop`): a registered
    abstract controller (:mod:`ashc_cli.closedloop.controllers`; the budget mode is the set-point law) or the
    governor (:mod:`ashc_cli.closedloop.governor`).

    Parameters
    ----------
    model : Model
        The spec's systems.
    up : dict of str to Artefact
        The artefacts of stabilise .. bound, by stage.
    law : Law
        The law the loop will run (not read here: the compiled loop takes the law's numbers at each run; the tests'
        oracle, which replaces this function, uses it).

    Returns
    -------
    TrackingLoop

    Raises
    ------
    NumericalError
        The loop cannot be compiled (numba missing, ``ASHC_COMPILED=0``, an expression with no numba form).
    """
    try:
        return compiled.tracking_loop(model, up)
    except compiled.Unsupported as exc:
        raise NumericalError("simulate", str(exc), "a design the compiled closed loop can run (numba, ASHC_COMPILED unset)") from exc


def closed_loop_run(model: Model, plant: DesignTerms, up: dict, law: Law, z0: np.ndarray,
                    segments: list[tuple[float, float, np.ndarray, int]], refs: list[np.ndarray], loop) -> dict:
    """Integrate the tracking closed loop under ``law``, segment after segment, from z0 = [xi0, x0, W0], with
    ``loop`` (:func:`tracking_loop_for`; the tests hand it scipy's oracle).

    Parameters
    ----------
    model : Model
        The spec's systems (``interface.q`` and ``interface.saturate`` are read).
    plant, up : DesignTerms, dict of str to Artefact
        The design's compiled terms and artefacts (not read here: ``loop`` holds the design).
    law : Law
        The abstract controller: a registered one by its kind (:mod:`~ashc_cli.closedloop.controllers`), or the
        governor (its gain, v_max, level and rate).
    z0 : ndarray (n_hat + n + 1,)
        [xi0, x0, w0].
    segments, refs : list of (float, float, ndarray, int), list of ndarray (n_hat,)
        (t0, t1, sample times, level index) per segment (:func:`tracking_segments`); the reference state of each level.
    loop : TrackingLoop
        What integrates the loop (:func:`tracking_loop_for`).

    Returns
    -------
    dict
        t, xi, x, w (the comparison system), reference_index, v, u, y at the samples; psi_end (psi at the end of
        each segment); z_end; compiled (whether the compiled loop ran); for the governor also scale (s) and slack
        (the margin of its invariance condition) at the samples.
    """
    governor = (law.w_level, law.rate, GOVERNOR_GRID, GOVERNOR_BISECTIONS, GOVERNOR_BACKOFF) if law.kind == "governor" else None
    more = {}
    if governor is None:
        c = controllers.controller(law.kind)
        more["law"] = (c.law(model), c.prm(law))
    res = loop.run(np.asarray(z0, dtype=float), segments, refs, gain=law.gain, v_max=law.v_max, q_kind=model.spec.interface.q,
                   saturate=model.spec.interface.saturate, rtol=TRACKING_TOL["rtol"], atol=TRACKING_TOL["atol"], governor=governor, **more)
    out: dict = {"compiled": getattr(loop, "compiled", True)}
    if governor is not None:
        out.update(scale=res.scale, slack=res.slack)
    out.update(t=res.t, xi=res.xi, x=res.x, w=res.w, reference_index=res.reference_index, v=res.v, u=res.u, y=res.y,
               psi_end=[res.psi_end[j] for j in range(len(segments))], z_end=np.r_[res.xi[:, -1], res.x[:, -1], res.w[-1]])
    return out


def reach_time(t: np.ndarray, y: np.ndarray, level: np.ndarray, tolerance: float, t_start: float) -> float:
    """The time after ``t_start`` from which |y - level| <= tolerance holds at every sample to the last; NaN if it
    does not hold at the last sample.

    Parameters
    ----------
    t : ndarray (N,)
        Sample times of the level's dwell.
    y : ndarray (p, N)
        The plant's output there.
    level : ndarray (p,)
    tolerance : float
    t_start : float
        When the level was asked for.
    """
    inside = np.linalg.norm(np.asarray(y) - np.asarray(level, dtype=float).reshape(-1, 1), axis=0) <= tolerance
    if not inside.size or not inside[-1]:
        return float("nan")
    out = np.flatnonzero(~inside)
    return float((t[out[-1] + 1] if out.size else t[0]) - t_start)


def reach_times(model: Model, plant: DesignTerms, up: dict, law: Law, z0: np.ndarray, levels: list[np.ndarray],
                refs: list[np.ndarray], tolerance: float, dwell: float, horizon_dwells: int = REACH_HORIZON_DWELLS, *,
                loop) -> np.ndarray:
    """The time to reach each level within ``tolerance`` when each is held until it is reached.

    The levels are asked for in turn from z0; each is held in chunks of ``dwell`` until, at the end of a chunk,
    |y - level| <= tolerance and psi has settled on the level (|psi - level| <= SETTLE_RTOL x output span), or psi
    has stopped elsewhere (it moved less than that over the last chunk), at most ``horizon_dwells`` chunks; its
    time is :func:`reach_time` over all its chunks (NaN if never reached).  With a
    guaranteed controller, once psi sits on the level |y - level| <= |y - psi| stays within the tolerance, so the
    time does not depend on how long the level is held after that.  Samples every REACH_SAMPLE_DWELLS dwell.

    Parameters
    ----------
    model : Model
        The spec's systems (Y sets the output span).
    plant, up : DesignTerms, dict of str to Artefact
        Passed on to :func:`closed_loop_run`.
    law : Law
        The abstract controller.
    z0 : ndarray (n_hat + n + 1,)
        [xi0, x0, w0] at the switch to the first level.
    levels : list of ndarray (p,)
        The levels, asked for in turn.
    refs : list of ndarray (n_hat,)
        The reference state of each level.
    tolerance, dwell : float
        |y - level| that counts as reached; the length of a chunk (s).
    horizon_dwells : int
        The most chunks a level is held.
    loop : TrackingLoop
        What integrates the loop (:func:`tracking_loop_for`).

    Returns
    -------
    ndarray (len(levels),)
        Seconds from the switch to each level; NaN where it is not reached within the horizon.
    """
    span = float(np.ptp(model.Y, axis=1).max())
    settle_tol = SETTLE_RTOL * span
    dt = max(SAMPLE_DT, REACH_SAMPLE_DWELLS * dwell)
    z = np.asarray(z0, dtype=float)
    t = 0.0
    times = []
    for i, level in enumerate(levels):
        t_start, ts, ys, psi_before = t, [], [], None
        for _ in range(max(1, int(horizon_dwells))):
            seg = [(t, t + dwell, sample_times(t, t + dwell, dt), i)]
            res = closed_loop_run(model, plant, up, law, z, seg, refs, loop)
            keep = slice(None) if not ts else slice(1, None)
            ts.append(res["t"][keep])
            ys.append(res["y"][:, keep])
            z, t = res["z_end"], t + dwell
            psi_now = np.asarray(res["psi_end"][-1], dtype=float)
            at_level = np.linalg.norm(res["y"][:, -1] - level) <= tolerance
            if at_level and float(np.abs(psi_now - level).max()) <= settle_tol:
                break
            if psi_before is not None and float(np.abs(psi_now - psi_before).max()) <= settle_tol:
                break           # psi has stopped short of the level (e.g. a drift phi_bar the allowed v cannot hold against)
            psi_before = psi_now
        times.append(reach_time(np.concatenate(ts), np.concatenate(ys, axis=1), level, tolerance, t_start))
    return np.array(times, dtype=float)
