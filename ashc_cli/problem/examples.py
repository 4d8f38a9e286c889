"""Spec generators for scalable example plants (``ashc example``).

``ladder(N)``: an N-stage switched LC ladder, a Cuk-like converter extended stage by stage.  Its 4N states
alternate inductor currents and capacitor voltages, x = (i_1, v_2, i_3, v_4, ..., v_4N); neighbours are
coupled as in an LC transmission line, every inductor has a series resistance r and every capacitor a
parallel conductance G_c, and the duty cycle u switches the first cell as in a boost/Cuk stage:

    L di_1/dt = E - (1 - u) v_2 - r i_1
    C dv_2/dt = (1 - u) i_1 - i_3 - G_c v_2
    L di_j/dt = v_(j-1) - v_(j+1) - r i_j               (j odd, 3 <= j <= 4N - 1)
    C dv_j/dt = i_(j-1) - i_(j+1) - G_c v_j             (j even, i_(4N+1) = 0)

so f(x, u) = A(u) x + b with A affine in u, and y = v_4N (the last capacitor).

The ladder is one line of fixed totals cut into N stages: the per-cell values are L = L0 / N, C = C0 / N,
r = r0 / N and G_c = G0 / N (``TOTALS``; N = 1 is the line itself).  At DC the inductors are short
circuits of resistance r and the capacitors open circuits of conductance G_c, so the output at a fixed
duty cycle depends on the total series resistance 2 N r = 2 r0 and the total shunt conductance
2 N G_c = 2 G0 only, up to the discretisation: kappa(V) stays of the order of E (a boost ratio
E / (1 - u) less the line's loss) at every N.  With per-cell losses fixed instead, the output decayed
like exp(-2 N sqrt(r G_c)) (kappa(V) = [0.0059, 0.0112] V at N = 64).

Stability: with H = diag(L, C, ...), A(u) = H^-1 (J(u) - D) with J(u) skew-symmetric and D = diag(r, G_c,
...) > 0, so M = H certifies A^T M + M A = -2 D <= -lambda M for lambda = 2 min(r / L, G_c / C) =
2 min(r0 / L0, G0 / C0) = 4 (the ratios do not depend on N), for every u: the ladder is incrementally
stable for any N, and the spec asks for half that rate, 2.  The LC frequencies grow like N (the cells get
shorter), the decay rate does not.
"""

from __future__ import annotations

from pathlib import Path

import yaml

from ashc_cli.errors import SpecError

__all__ = ["ladder", "rc_ladder", "chain", "ring", "parameters", "TOTALS", "SHIPPED", "shipped", "shipped_spec"]

#: The example specs shipped with the package (the repository's specs/ links here).
SHIPPED = Path(__file__).resolve().parents[1] / "specs"

#: Short names for the shipped specs a newcomer asks for first.
ALIASES = {"cuk": "cuk_converter", "boost": "boost_converter", "pendulum": "inverted_pendulum"}


def shipped() -> dict[str, str]:
    """The shipped example specs: name -> the spec's ``description``.

    Returns
    -------
    dict of str to str
        In name order.
    """
    out = {}
    for path in sorted(SHIPPED.glob("*.yaml")):
        data = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
        out[path.stem] = " ".join(str(data.get("description", "")).split())
    return out


def shipped_spec(name: str) -> tuple[str, str]:
    """One shipped spec, by its name, an alias (``cuk``) or a prefix that names one spec only.

    Parameters
    ----------
    name : str
        ``cuk_converter``, ``cuk``, ``quarter``, ...

    Returns
    -------
    name : str
        The spec's name (its file's stem).
    text : str
        The spec file as shipped (comments included).

    Raises
    ------
    SpecError
        If no shipped spec, or more than one, answers to ``name``.
    """
    names = list(shipped())
    full = ALIASES.get(name, name)
    if full not in names:
        matches = [n for n in names if n.startswith(name)]
        if len(matches) != 1:
            what = f"'{name}' names {len(matches)} shipped specs ({', '.join(matches)})" if matches else f"'{name}' is no example"
            raise SpecError("KIND", what, "a family (ladder, rc_ladder, chain) or a shipped spec: " + ", ".join(names)
                            + " (`ashc example --list` describes them)")
        full = matches[0]
    return full, (SHIPPED / f"{full}.yaml").read_text(encoding="utf-8")

#: The line's totals: source voltage E, and L0, C0, r0, G0 split over the N stages (``parameters``).
TOTALS = {"E": 10.0, "L": 1.0e-2, "C": 1.0e-2, "r": 0.2, "G_c": 0.02}


def parameters(stages: int) -> dict[str, float]:
    """The per-cell parameters of the N-stage ladder: E, and L, C, r, G_c = the totals / N.

    Parameters
    ----------
    stages : int
        N.

    Returns
    -------
    dict of str to float
        Keyed as ``TOTALS``.
    """
    return {k: v if k == "E" else v / stages for k, v in TOTALS.items()}


#: The ladder's reach-avoid task (``ashc example ladder --task``): from the output at duty cycle 0.36 (about 15.5 V)
#: into [17, 23] V by 140 s and held there 15 s, never above 23.5 V (the avoid box) nor outside [10, 24.5] V.  The
#: output set and kappa do not depend on N (the line's totals are fixed), so the task is the same at every N; the
#: bound's gain G grows with N (438 at N = 8, 1406 at N = 128), and with it the time the planner needs.
LADDER_TASK = {"horizon": 160.0, "always": [[10.0, 24.5]], "reach": [{"set": [[17.0, 23.0]], "by": 140.0, "hold": 15.0}],
               "avoid": [{"set": [[23.5, 30.0]], "during": [0.0, 160.0]}], "xi0": [0.36], "planner": {"kind": "grid", "cells": [800]}}


def ladder(stages: int, task: bool = False) -> str:
    """The YAML text of the N-stage ladder spec (n = 4 N states).

    Parameters
    ----------
    stages : int
        N, at least 1 (not checked).
    task : bool
        Append :data:`LADDER_TASK` (a reach-avoid task on the output for ``ashc synthesize``, issue 42).

    Returns
    -------
    str
        A comment line naming the generator, then the spec.
    """
    n = 4 * stages
    values = parameters(stages)
    E = values["E"]
    x = [f"i{j}" if j % 2 == 1 else f"v{j}" for j in range(1, n + 1)]
    f_bar, g = [], []
    for j in range(1, n + 1):
        k = j - 1
        if j == 1:
            f_bar.append("(E - v2 - r*i1)/L")
            g.append(["v2/L"])
        elif j == 2:
            nxt = f" - {x[2]}" if n > 2 else ""
            f_bar.append(f"(i1{nxt} - G_c*v2)/C")
            g.append(["-i1/C"])
        elif j % 2 == 1:
            nxt = f" - {x[k + 1]}" if j < n else ""
            f_bar.append(f"({x[k - 1]}{nxt} - r*{x[k]})/L")
            g.append(["0"])
        else:
            nxt = f" - {x[k + 1]}" if j < n else ""
            f_bar.append(f"({x[k - 1]}{nxt} - G_c*{x[k]})/C")
            g.append(["0"])
    # Half of 2 min(r/L, G_c/C), from the totals: the ratios are the same at every N (and exact there).
    lam = min(TOTALS["r"] / TOTALS["L"], TOTALS["G_c"] / TOTALS["C"])
    spec = {
        "name": f"ladder_{stages}",
        "description": f"{stages}-stage switched LC ladder (Cuk-like, n = {n}; per-cell L, C, r, G_c = line totals / {stages}); "
                       f"generated by `ashc example ladder --stages {stages}{' --task' if task else ''}`",
        "parameters": values,
        "concrete": {
            "states": x, "inputs": ["u"], "f_bar": f_bar, "g": g, "h": [x[-1]],
            "input_bounds": [[0.0, 1.0]], "output_set": None,
        },
        "stabilisability": {"method": "polytopic_lmi", "decay_rate": lam, "feedback": "identity"},
        "abstract": {"states": ["xi"], "inputs": ["w"], "phi_bar": ["0"], "l": ["xi"], "domain": [[0.0, 0.6]],
                     "delta": "identity", "pde_tolerance": 1.0e-9, "pde_max_degree": 30},
        "interface": {"q": "least_squares", "saturate": True},
        # Duty-cycle steps between outputs of order E inside Y, 3 s apart (the error decays like e^-t), and the
        # m-relation from the equilibrium at duty cycle 0.3 under a duty cycle swinging around it.
        "simulate": {
            "tracking": {"t_final": 9.0, "xi0": [0.3], "x0": "on_manifold", "reference_levels": [1.2 * E, 2.0 * E, 1.5 * E],
                         "dwell": 3.0, "abstract_controller": {"kind": "setpoint", "gain": 4.0, "v_max": 0.5}},
            "m_relation": {"t_final": 4.0, "x0": [round(v, 6) for v in _equilibrium(stages, 0.3)], "u": "0.3 + 0.1*sin(2*pi*t)"},
        },
        "units": {"t": "s", "y": "V"},
    }
    spec["concrete"]["output_set"] = [list(_output_range(stages))]
    if task:
        spec["task"] = LADDER_TASK
    return _generated("ladder", stages, spec)


def _output_range(stages: int) -> tuple[float, float]:
    """An output box inside kappa(V): the DC output at duty cycles 0.05 and 0.55, computed numerically."""
    lo, hi = sorted((_equilibrium(stages, 0.05)[-1], _equilibrium(stages, 0.55)[-1]))
    return round(lo, 6), round(hi, 6)


def _equilibrium(stages: int, u: float) -> list[float]:
    """The equilibrium state of the N-stage ladder at the constant duty cycle u (A(u) x + b = 0)."""
    import numpy as np

    n = 4 * stages
    E, L, C, r, G = (parameters(stages)[k] for k in ("E", "L", "C", "r", "G_c"))
    A = np.zeros((n, n))
    for j in range(n):
        inductor = j % 2 == 0
        A[j, j] = -(r / L if inductor else G / C)
        scale = 1 / L if inductor else 1 / C
        switched = (1 - u) if j <= 1 else 1.0   # the duty cycle scales the i1-v2 coupling only
        if j >= 1:
            A[j, j - 1] = scale * (switched if j == 1 else 1.0)
        if j + 1 < n:
            A[j, j + 1] = -scale * (switched if j == 0 else 1.0)
    b = np.zeros(n)
    b[0] = E / L
    return np.linalg.solve(A, -b).tolist()


# --- the MORwiki nonlinear RC ladder ---------------------------------------------------------------------------

#: The diode law of the MORwiki nonlinear RC ladder: i = g(v) = exp(40 v) + v - 1.
DIODE = "exp(40*({v})) + ({v}) - 1"


def rc_ladder(stages: int) -> str:
    """The YAML text of the N-stage nonlinear RC ladder (MORwiki benchmark), n = N states (the node voltages).

        x1' = -g(x1) - g(x1 - x2) + u,   xk' = g(x(k-1) - xk) - g(xk - x(k+1)),   xN' = g(x(N-1) - xN),   y = x1

    with the diode current g(v) = exp(40 v) + v - 1 (unit capacitors and resistors).  For a constant u every branch
    current vanishes at the equilibrium, so all nodes sit at x* = g^-1(u): p(xi) = (x*(xi), ..., x*(xi)) with
    l(xi) = xi, and kappa(xi) = x*(xi) rises from 0 at xi = 0 to about 0.0101 at xi = 0.5.  Each diode is one
    nonlinear term of slope g' = 40 exp(40 v) + 1 >= 1 over the state box: a network whose every term dissipates
    with the storage function M = I (the stage finds it: :mod:`ashc_cli.design.contraction.network`).

    Parameters
    ----------
    stages : int
        N, at least 2 (ValueError otherwise).

    Returns
    -------
    str
        A comment line naming the generator, then the spec.
    """
    if stages < 2:
        raise ValueError("an RC ladder needs at least 2 stages")
    x = [f"x{k}" for k in range(1, stages + 1)]

    def g(v: str) -> str:
        return DIODE.format(v=v)

    f_bar = [f"-({g(x[0])}) - ({g(f'{x[0]} - {x[1]}')})"]
    for k in range(1, stages - 1):
        f_bar.append(f"{g(f'{x[k - 1]} - {x[k]}')} - ({g(f'{x[k]} - {x[k + 1]}')})")
    f_bar.append(g(f"{x[-2]} - {x[-1]}"))
    spec = {
        "name": f"rc_ladder_{stages}",
        "description": f"MORwiki nonlinear RC ladder, {stages} nodes (diode g(v) = exp(40 v) + v - 1); generated by `ashc example rc_ladder --stages {stages}`",
        "concrete": {
            "states": x, "inputs": ["u"], "f_bar": f_bar, "g": [["1"]] + [["0"] for _ in range(stages - 1)], "h": [x[0]],
            "input_bounds": [[0.0, 0.5]], "output_set": [[0.001, 0.009]], "state_box": [[-0.05, 0.05] for _ in range(stages)],
        },
        "stabilisability": {"method": "polytopic_lmi", "decay_rate": "maximise", "feedback": "identity"},
        "abstract": {"states": ["xi"], "inputs": ["v"], "phi_bar": ["0"], "l": ["xi"], "domain": [[0.0, 0.5]], "delta": "identity",
                     "pde_tolerance": 1.0e-9},
        "interface": {"q": "least_squares", "saturate": True},
        "simulate": {"tracking": {"t_final": 30.0, "xi0": [0.1], "x0": "on_manifold", "reference_levels": [0.005, 0.008, 0.002],
                                  "dwell": 10.0, "abstract_controller": {"kind": "setpoint", "gain": 1.0, "v_max": 0.2}}},
        "units": {"t": "s", "y": "V"},
    }
    return _generated("rc_ladder", stages, spec)


# --- a chain of masses --------------------------------------------------------------------------------------------

#: Mass, spring, damper between neighbours and damper to the ground of every cell of the chain.
CHAIN = {"m_c": 1.0, "k_c": 1.0, "c_c": 0.1, "c_0": 0.2}


def chain(masses: int) -> str:
    """The YAML text of a chain of N masses (n = 2 N states), fixed to a wall at one end and pushed at the other:

        q_i' = v_i,   m v_i' = k (q_(i-1) - 2 q_i + q_(i+1)) + c (v_(i-1) - 2 v_i + v_(i+1)) - c_0 v_i   (q_0 = 0),

    with the last cell's right-hand neighbour missing and the force u on the last mass; y = q_N.  A linear plant with a
    constant input matrix: one matrix A, whose certificate for large N comes from the Lyapunov equation, not an SDP.  At
    a constant force every spring carries u: p(xi) = (xi / k, 0, 2 xi / k, 0, ..., N xi / k, 0) with l(xi) = xi.

    Parameters
    ----------
    masses : int
        N, at least 1 (ValueError otherwise).

    Returns
    -------
    str
        A comment line naming the generator, then the spec.
    """
    if masses < 1:
        raise ValueError("a chain needs at least one mass")
    q = [f"q{i}" for i in range(1, masses + 1)]
    v = [f"v{i}" for i in range(1, masses + 1)]
    states, f_bar, g = [], [], []
    for i in range(masses):
        left_q, left_v = (q[i - 1], v[i - 1]) if i > 0 else ("0", "0")
        spring = f"k_c*({left_q} - {q[i]})" + (f" + k_c*({q[i + 1]} - {q[i]})" if i + 1 < masses else "")
        damper = f"c_c*({left_v} - {v[i]})" + (f" + c_c*({v[i + 1]} - {v[i]})" if i + 1 < masses else "")
        states += [q[i], v[i]]
        f_bar += [v[i], f"({spring} + {damper} - c_0*{v[i]})/m_c"]
        g += [["0"], ["1/m_c" if i + 1 == masses else "0"]]
    span = float(masses) / CHAIN["k_c"]
    spec = {
        "name": f"chain_{masses}",
        "description": f"chain of {masses} masses (n = {2 * masses}), wall at one end, force on the last mass; generated by `ashc example chain --stages {masses}`",
        "parameters": dict(CHAIN),
        "concrete": {"states": states, "inputs": ["u"], "f_bar": f_bar, "g": g, "h": [q[-1]],
                     "input_bounds": [[-1.0, 1.0]], "output_set": [[round(-0.8 * span, 6), round(0.8 * span, 6)]]},
        "stabilisability": {"method": "polytopic_lmi", "decay_rate": "maximise", "feedback": "identity"},
        "abstract": {"states": ["xi"], "inputs": ["w"], "phi_bar": ["0"], "l": ["xi"], "domain": [[-0.9, 0.9]], "delta": "identity"},
        "interface": {"q": "least_squares", "saturate": True},
        "simulate": {"tracking": {"t_final": 200.0, "xi0": [0.0], "x0": "on_manifold",
                                  "reference_levels": [round(0.5 * span, 6), round(-0.5 * span, 6)], "dwell": 100.0,
                                  "abstract_controller": {"kind": "setpoint", "gain": 0.2, "v_max": 0.05}}},
        "units": {"t": "s"},
    }
    return _generated("chain", masses, spec)


#: The pendulum ring's parameters: gravity over length, damping, cubic damping, coupling.
RING = {"k": 4.0, "c": 1.5, "d": 0.2, "a": 0.2}


def ring(pendulums: int) -> str:
    """The YAML text of N pendulums coupled all to all (n = 2 N states), the benchmark of many distinct nonlinear terms:

        th_i' = om_i,   om_i' = -k sin(th_i) - c om_i - d om_i^3 + sum_(j != i) a sin(th_j - th_i) + [i = 1] u,

    y = th_1.  df/dx has 2 N + N (N - 1) / 2 distinct nonlinear terms (sin, cos of differences, om^2): 44 at N = 8,
    far past what the vertex argument enumerates, so ``polytopic_lmi`` takes the norm-bound test by itself.

    Parameters
    ----------
    pendulums : int
        N, at least 1 (ValueError otherwise).

    Returns
    -------
    str
        A comment line naming the generator, then the spec.
    """
    if pendulums < 1:
        raise ValueError("a ring needs at least one pendulum")
    states, f_bar, g = [], [], []
    for i in range(1, pendulums + 1):
        coupling = "".join(f" + a*sin(th{j} - th{i})" for j in range(1, pendulums + 1) if j != i)
        states += [f"th{i}", f"om{i}"]
        f_bar += [f"om{i}", f"-k*sin(th{i}) - c*om{i} - d*om{i}**3{coupling}"]
        g += [["0"], ["1" if i == 1 else "0"]]
    spec = {
        "name": f"ring_{pendulums}",
        "description": f"{pendulums} pendulums coupled all to all through sin of their differences (n = {2 * pendulums}); generated by "
                       f"`ashc example ring --stages {pendulums}`",
        "parameters": dict(RING),
        "concrete": {"states": states, "inputs": ["u"], "f_bar": f_bar, "g": g, "h": ["th1"], "input_bounds": [[-1.0, 1.0]],
                     "output_set": [[-0.02, 0.02]], "state_box": [[-0.15, 0.15] if k % 2 == 0 else [-0.5, 0.5] for k in range(2 * pendulums)]},
        "stabilisability": {"method": "polytopic_lmi", "decay_rate": "maximise", "feedback": "identity"},
        "abstract": {"states": ["xi"], "inputs": ["v"], "phi_bar": ["0"], "l": ["xi"], "domain": [[-0.3, 0.3]], "delta": "identity"},
        "interface": {"q": "least_squares", "saturate": True},
    }
    return _generated("ring", pendulums, spec, width=300)


def _generated(kind: str, stages: int, spec: dict, width: int = 140) -> str:
    """The YAML text of a generated spec: a comment line naming the generator, then the spec in its key order."""
    return (f"# Generated by ashc example {kind} --stages {stages}; see ashc_cli/problem/examples.py for the model.\n"
            + yaml.safe_dump(spec, sort_keys=False, width=width))
