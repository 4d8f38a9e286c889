"""The paper's figures, drawn from the artefacts of a design (``ashc plot``, ``ashc report``).

One function per figure of Section V, each taking the artefacts (plain data) and returning a matplotlib
Figure; :func:`write_all` saves them as PNG.  Sized for a paper column (3.5 in wide, 8 pt text) and labelled
with the spec's ``units`` where it gives them.

=========================  ===============================================================
file                       the paper's figure
=========================  ===============================================================
``kappa_xi.png``           Fig. kappa_xi: kappa(xi) over V with the output region Y
``delta_compare.png``      Fig. delta_Compare: ||theta(xi, .)|| (q = 0) for delta = I and the design's delta
``tracking_inputs.png``    Fig. Example_BoundedIn: v and u of the tracking run
``tracking_outputs.png``   Fig. Example_BoundedOut: psi and y, and e_y with the uniform and a-posteriori bounds
``m_relation_inputs.png``  Fig. Example_mRelationIn: u and v = b(x) + c(x) u
``m_relation_outputs.png`` Fig. Example_mRelationOut: psi and y
``falsify.png``            (ashc's own) the largest error / bound ratio of each falsification run
=========================  ===============================================================
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only, never a window
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .artefacts import Artefact  # noqa: E402
from .spec import Spec  # noqa: E402

__all__ = ["write_all", "save", "FIGURES"]

COLUMN_WIDTH = 3.5  # inches
STYLE = {"font.size": 8, "axes.titlesize": 8, "axes.labelsize": 8, "legend.fontsize": 7, "xtick.labelsize": 7,
         "ytick.labelsize": 7, "lines.linewidth": 1.0, "axes.grid": True, "grid.alpha": 0.3, "savefig.dpi": 200}


def _label(spec: Spec, name: str, key: str | None = None) -> str:
    """``name (unit)`` if the spec gives a unit for ``key`` (default: name)."""
    unit = spec.units.get(key or name)
    return f"{name} ({unit})" if unit else name


def _output_label(spec: Spec, k: int, symbol: str) -> str:
    unit = spec.units.get(f"y{k + 1}") or spec.units.get("y")
    sub = f"{symbol}{k + 1}" if len(spec.concrete.h) > 1 else symbol
    return f"{sub} ({unit})" if unit else sub


def _figure(rows: int = 1, height: float = 2.4):
    fig, axes = plt.subplots(rows, 1, figsize=(COLUMN_WIDTH, height * rows / (1 + 0.25 * (rows - 1))), sharex=rows > 1, squeeze=False)
    return fig, axes[:, 0]


def kappa_figure(spec: Spec, arts: dict[str, Artefact]):
    """Fig. kappa_xi: psi = kappa(xi) over V, the output region Y shaded."""
    kap = arts["kappa"].values
    xi, k = np.asarray(kap["xi_grid"]), np.asarray(kap["kappa_grid"])
    Y = np.asarray(spec.concrete.output_set, dtype=float)
    a = spec.abstract.states
    if xi.shape[0] == 1:
        fig, (ax,) = _figure()
        for j in range(k.shape[0]):
            ax.plot(xi[0], k[j], label=f"kappa{j + 1}" if k.shape[0] > 1 else "kappa")
            ax.axhspan(Y[j, 0], Y[j, 1], color=f"C{j}", alpha=0.12, label="Y" if j == 0 else None)
        ax.set_xlabel(_label(spec, a[0]))
        ax.set_ylabel(_output_label(spec, 0, "psi") if k.shape[0] == 1 else "psi")
        ax.legend(loc="best")
        return fig
    # Several abstract states: one map per output over the first two, Y's edges as contours.
    per = int(round(xi.shape[1] ** (1 / xi.shape[0])))
    fig, axes = plt.subplots(1, k.shape[0], figsize=(COLUMN_WIDTH * min(k.shape[0], 2), 2.6), squeeze=False)
    for j, ax in enumerate(axes[0]):
        grid = k[j].reshape((per,) * xi.shape[0])
        while grid.ndim > 2:
            grid = grid[..., grid.shape[-1] // 2]
        x0, x1 = xi[0].reshape((per,) * xi.shape[0]), xi[1].reshape((per,) * xi.shape[0])
        while x0.ndim > 2:
            x0, x1 = x0[..., 0], x1[..., 0]
        mesh = ax.pcolormesh(x0, x1, grid, shading="auto", cmap="viridis")
        ax.contour(x0, x1, grid, levels=sorted(set(Y[j])), colors="w", linewidths=0.8)
        fig.colorbar(mesh, ax=ax, label=_output_label(spec, j, "psi"))
        ax.set_xlabel(_label(spec, a[0]))
        ax.set_ylabel(_label(spec, a[1]))
    fig.tight_layout()
    return fig


def delta_figure(spec: Spec, arts: dict[str, Artefact]):
    """Fig. delta_Compare: ||theta(xi, .)|| with q = 0, for delta = I and the design's delta (log scale)."""
    bd = arts["bound"].values
    xi = np.asarray(bd["xi_grid"])
    ident, design = np.asarray(bd["theta_norm_q0_identity"]), np.asarray(bd["theta_norm_q0"])
    name = spec.abstract.delta if isinstance(spec.abstract.delta, str) else "spec"
    fig, (ax,) = _figure()
    x = xi[0] if xi.shape[0] == 1 else np.arange(xi.shape[1])
    ax.plot(x, ident, label=f"delta = I (dbar = {float(bd['dbar_q0_identity']):.4g})")
    ax.plot(x, design, label=f"delta: {name} (dbar = {float(bd['dbar_q0']):.4g})")
    ax.set_yscale("log")
    ax.set_xlabel(_label(spec, spec.abstract.states[0]) if xi.shape[0] == 1 else "grid point of V")
    ax.set_ylabel("||theta(xi, .)||, q = 0")
    ax.legend(loc="best")
    return fig


def _series(ax, t, rows, names):
    for j, row in enumerate(np.atleast_2d(rows)):
        ax.plot(t, row, label=names[j] if j < len(names) else None)


def _inputs_figure(spec: Spec, arts: dict[str, Artefact], scenario: str, abstract_first: bool):
    """Two panels, abstract input v and concrete input u of a run, in the order of the paper's figure."""
    s = arts["simulate"].values
    t = np.asarray(s[f"{scenario}/t"])
    fig, axes = _figure(2)
    panels = [(s[f"{scenario}/v"], spec.abstract.inputs), (s[f"{scenario}/u"], spec.concrete.inputs)]
    for ax, (rows, names) in zip(axes, panels if abstract_first else panels[::-1]):
        _series(ax, t, rows, names)
        ax.set_ylabel(_label(spec, ", ".join(names), names[0]))
    axes[-1].set_xlabel(_label(spec, "t"))
    fig.tight_layout()
    return fig


def _outputs_figure(spec: Spec, arts: dict[str, Artefact], scenario: str):
    """psi and y of a run (top) and the axes for |psi - y| (bottom, filled by the caller)."""
    s = arts["simulate"].values
    t = np.asarray(s[f"{scenario}/t"])
    fig, (ax_y, ax_e) = _figure(2)
    psi, y = np.atleast_2d(s[f"{scenario}/psi"]), np.atleast_2d(s[f"{scenario}/y"])
    for j in range(psi.shape[0]):
        ax_y.plot(t, psi[j], color=f"C{j}", label="psi" if j == 0 else None)
        ax_y.plot(t, y[j], color=f"C{j}", linestyle="--", label="y" if j == 0 else None)
    single = psi.shape[0] == 1
    ax_y.set_ylabel(_output_label(spec, 0, "psi, y") if single else "psi, y")
    ax_y.legend(loc="best")
    err = np.linalg.norm(np.atleast_2d(s[f"{scenario}/e_y"]), axis=0)
    ax_e.plot(t, err, color="k", label="|psi - y|")
    ax_e.set_ylabel(_output_label(spec, 0, "|psi - y|") if single else "|psi - y|")
    ax_e.set_xlabel(_label(spec, "t"))
    return fig, ax_e, t, err, s


def tracking_inputs_figure(spec: Spec, arts: dict[str, Artefact]):
    """Fig. Example_BoundedIn: the abstract input v and the concrete input u of the tracking run."""
    return _inputs_figure(spec, arts, "tracking", abstract_first=True)


def tracking_outputs_figure(spec: Spec, arts: dict[str, Artefact]):
    """Fig. Example_BoundedOut: psi and y, and |psi - y| with the uniform and a-posteriori bounds."""
    fig, ax_e, t, err, s = _outputs_figure(spec, arts, "tracking")
    if "tracking/posterior_bound" in s:
        ax_e.plot(t, np.asarray(s["tracking/posterior_bound"]), color="C2", label="a-posteriori bound")
    ax_e.axhline(float(s["tracking/uniform_bound"]), color="C3", linestyle=":", label="uniform bound G ||v||")
    ax_e.set_yscale("symlog", linthresh=max(1e-6, float(err.max()) * 1e-3))
    ax_e.legend(loc="best")
    fig.tight_layout()
    return fig


def m_relation_inputs_figure(spec: Spec, arts: dict[str, Artefact]):
    """Fig. Example_mRelationIn: u(t) and v = b(x) + c(x) u."""
    return _inputs_figure(spec, arts, "m_relation", abstract_first=False)


def m_relation_outputs_figure(spec: Spec, arts: dict[str, Artefact]):
    """Fig. Example_mRelationOut: psi and y coincide (Theorem mRelatOutMatch); their difference below."""
    fig, *_ = _outputs_figure(spec, arts, "m_relation")
    fig.tight_layout()
    return fig


def falsify_figure(spec: Spec, arts: dict[str, Artefact]):
    """Largest measured error / guaranteed bound of each falsification run (all must be <= 1)."""
    ratios = np.asarray(arts["falsify"].values["run_ratio"])
    fig, (ax,) = _figure()
    ax.plot(np.arange(ratios.size), ratios, "o", markersize=2)
    ax.axhline(1.0, color="C3", linestyle=":", label="bound")
    ax.set_xlabel("run")
    ax.set_ylabel("max |e_y| / bound")
    ax.set_ylim(0, max(1.05, float(ratios.max()) * 1.05))
    ax.legend(loc="best")
    return fig


#: file name -> (figure function, artefacts it needs, what it needs inside the simulate artefact)
FIGURES = {
    "kappa_xi.png": (kappa_figure, ("kappa",), None),
    "delta_compare.png": (delta_figure, ("bound",), None),
    "tracking_inputs.png": (tracking_inputs_figure, ("simulate",), "tracking/t"),
    "tracking_outputs.png": (tracking_outputs_figure, ("simulate",), "tracking/t"),
    "m_relation_inputs.png": (m_relation_inputs_figure, ("simulate",), "m_relation/t"),
    "m_relation_outputs.png": (m_relation_outputs_figure, ("simulate",), "m_relation/t"),
    "falsify.png": (falsify_figure, ("falsify",), None),
}


def save(fig, path: Path) -> Path:
    """Save a figure as PNG atomically (a reader never sees half a file) and close it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, bbox_inches="tight")
    plt.close(fig)
    tmp.replace(path)
    return path


def write_all(spec: Spec, arts: dict[str, Artefact], folder: str | Path) -> list[Path]:
    """Draw every figure the artefacts allow and save it under ``folder``; returns the paths written."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    with plt.rc_context(STYLE):
        for name, (draw, needs, key) in FIGURES.items():
            if not all(n in arts for n in needs) or (key is not None and key not in arts["simulate"].values):
                continue
            written.append(save(draw(spec, arts), folder / name))
    return written
