"""The figure of a task on two outputs (``ashc synthesize``): the output plane with the task's sets, psi of the plan
and y of the plant's run, and a grid plan's winning cells of V with its route beside it (:func:`draw_plane`).  A task
on one output is drawn over time by :func:`ashc_cli.outputs.plots.draw_task`.
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np

from ashc_cli.outputs.plots import COLUMN_WIDTH, PSI_STYLE, Y_STYLE, legend_above, plt

__all__ = ["GridView", "draw_plane"]

#: What the plane figures draw of a grid plan: V's box, the cells winning from step 0 (n_hat-D bool), each reach set's
#: cells and each avoid set's (the cells whose period may meet it), and the route's states (steps + 1, n_hat).
GridView = namedtuple("GridView", "lo hi winning targets avoids route")


def _boxes(ax, task, eps: float):
    """The task's sets in the output plane: the always box, each avoid box, each reach box with its deflation by EPS."""
    from matplotlib.patches import Rectangle

    if task.always is not None:
        (a, b), (c, d) = task.always
        ax.add_patch(Rectangle((a, c), b - a, d - c, fill=False, edgecolor="0.35", linewidth=0.8, label="always"))
    for k, av in enumerate(task.avoid):
        (a, b), (c, d) = av.set
        ax.add_patch(Rectangle((a, c), b - a, d - c, facecolor="#d62728", alpha=0.25, linewidth=0, label="avoid" if k == 0 else None))
    for k, r in enumerate(task.reach):
        (a, b), (c, d) = r.set
        ax.add_patch(Rectangle((a, c), b - a, d - c, facecolor="#2ca02c", alpha=0.25, linewidth=0, label="reach" if k == 0 else None))
        ax.add_patch(Rectangle((a + eps, c + eps), b - a - 2 * eps, d - c - 2 * eps, fill=False, edgecolor="#2ca02c", linestyle="--",
                               linewidth=0.8, label=r"deflated by $\varepsilon$" if k == 0 else None))
        ax.annotate(f"reach[{k}] by {r.by:g} s", ((a + b) / 2, d), ha="center", va="bottom", fontsize=6, color="#2ca02c")


def draw_plane(task, y: np.ndarray, psi: np.ndarray, eps: float, view: GridView | None = None, labels=("$y_1$", "$y_2$")):
    """A task on two outputs in the output plane: the sets, psi of the plan and y of the plant's run; with a grid
    plan of two abstract states, beside it V with the cells winning from the start, the sets' cells and the route.

    Parameters
    ----------
    task : Task
        ``spec.task`` on two outputs (None: no output panel, only V).
    y, psi : ndarray (2, N), (2, M)
    eps : float
        The tolerance the sets were deflated by.
    view : GridView, optional
        The grid plan (two abstract states).
    labels : pair of str

    Returns
    -------
    matplotlib Figure
    """
    panels = (task is not None) + (view is not None)
    fig, axes = plt.subplots(1, panels, figsize=(COLUMN_WIDTH * panels, 3.2), layout="constrained", squeeze=False)
    axes = list(axes[0])
    if task is not None:
        ax = axes.pop(0)
        _boxes(ax, task, eps)
        ax.plot(psi[0], psi[1], label=r"$\psi$ (plan)", **PSI_STYLE)
        ax.plot(y[0], y[1], label="$y$ (plant)", **Y_STYLE)
        ax.plot(psi[0, 0], psi[1, 0], "o", color="k", markersize=3, label="start")
        ax.set_xlabel(labels[0])
        ax.set_ylabel(labels[1])
        ax.autoscale_view()
        legend_above(ax, ncol=3)
    if view is not None:
        from matplotlib.colors import ListedColormap

        ax = axes.pop(0)
        ext = (view.lo[0], view.hi[0], view.lo[1], view.hi[1])
        ax.imshow(np.asarray(view.winning, dtype=float).T, origin="lower", extent=ext, aspect="auto",
                  cmap=ListedColormap(["white", "#cfe3f7"]), vmin=0, vmax=1, interpolation="nearest")
        nx, ny = np.asarray(view.winning).shape
        gx = np.linspace(view.lo[0], view.hi[0], nx)
        gy = np.linspace(view.lo[1], view.hi[1], ny)
        for cells, color in [(m, "#2ca02c") for m in view.targets] + [(m, "#d62728") for m in view.avoids]:
            if np.any(cells) and not np.all(cells):
                ax.contour(gx, gy, np.asarray(cells, dtype=float).T, levels=[0.5], colors=color, linewidths=0.8)
        route = np.asarray(view.route)
        ax.plot(route[:, 0], route[:, 1], color="k", linewidth=1.0, marker=".", markersize=2, label="route")
        ax.set_xlim(ext[0], ext[1])
        ax.set_ylim(ext[2], ext[3])
        ax.set_xlabel(r"$\xi_1$")
        ax.set_ylabel(r"$\xi_2$")
        ax.set_title("V: winning from the start (blue), reach cells (green), avoid cells (red)", fontsize="small")
    return fig
