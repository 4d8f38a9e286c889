"""The robustness of an output task (``spec.task``) on a sampled run: a monitor of the bounded-time fragment of
signal temporal logic the spec can state, in the quantitative (robustness) semantics of Donze and Maler.

For a box B (one [lo, hi] per output) the predicate y in B has robustness min_j min(y_j - lo_j, hi_j - y_j) (the
distance, in output units, to leaving it; negative inside the complement), and y not in B its negation.  The task

    G_[0, H] (y in always)  and  AND_k F_[0, by_k] G_[0, hold_k] (y in S_k)  and  AND_k G_[a_k, b_k] (y not in A_k)

is evaluated at t = 0 on the samples of the run (discrete time: a window holds the samples inside it), as
rtamt's discrete-time monitor does (``tests/test_task_monitor.py`` compares the two).  Its robustness is the
smallest of the parts': >= 0 means the run meets the task, and its value is by how much y could move and still meet
it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["TaskRobustness", "box_margin", "robustness"]


def box_margin(y: np.ndarray, box) -> np.ndarray:
    """The robustness of ``y in box`` at each sample: min over outputs of min(y_j - lo_j, hi_j - y_j).

    Parameters
    ----------
    y : ndarray, shape (p, N)
        The output at N samples.
    box : sequence of [lo, hi]
        One interval per output.

    Returns
    -------
    ndarray, shape (N,)
    """
    b = np.asarray(box, dtype=float)
    y = np.atleast_2d(np.asarray(y, dtype=float))
    return np.minimum(y - b[:, :1], b[:, 1:] - y).min(axis=0)


class _RangeMin:
    """Minimum of a fixed array over index ranges [i, j), each in O(1) after an O(N log N) table (sparse table)."""

    def __init__(self, values: np.ndarray):
        self.levels = [np.asarray(values, dtype=float)]
        width = 1
        while 2 * width <= len(values):
            prev = self.levels[-1]
            self.levels.append(np.minimum(prev[:-width], prev[width:]))
            width *= 2

    def query(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """min(values[i:j]) for each pair (j > i)."""
        span = j - i
        k = np.floor(np.log2(np.maximum(span, 1))).astype(int)
        out = np.empty(len(i))
        for level in np.unique(k):
            sel = k == level
            table = self.levels[level]
            out[sel] = np.minimum(table[i[sel]], table[j[sel] - (1 << level)])
        return out


@dataclass
class TaskRobustness:
    """The task's robustness on one run.

    Attributes
    ----------
    robustness : float
        The smallest of the parts' (>= 0: the task is met).
    parts : dict of str to float
        ``always``, ``reach[k]``, ``avoid[k]``: the robustness of each part.
    reach_times : list of float
        Per reach, the first sample time (<= its deadline) from which y stays in the set for the hold; NaN if none.
    best_times : list of float
        Per reach, the start of the hold window that gives its robustness (the deepest hold).
    """

    robustness: float
    parts: dict[str, float] = field(default_factory=dict)
    reach_times: list[float] = field(default_factory=list)
    best_times: list[float] = field(default_factory=list)

    @property
    def satisfied(self) -> bool:
        """Whether the run meets the task (robustness >= 0)."""
        return bool(self.robustness >= 0)


def _window_ends(t: np.ndarray, starts: np.ndarray, length: float) -> np.ndarray:
    """Per start index i, one past the last sample with t <= t_i + length (discrete time: the samples in the window)."""
    return np.searchsorted(t, t[starts] + length * (1 + 1e-12) + 1e-12, side="right")


def robustness(task, t: np.ndarray, y: np.ndarray, margin: np.ndarray | None = None) -> TaskRobustness:
    """The task's robustness at t = 0 on the samples (t, y) of a run.

    Parameters
    ----------
    task : Task
        ``spec.task`` (``horizon``, ``always``, ``reach``, ``avoid``).
    t : ndarray, shape (N,)
        Sample times, increasing, from 0; they should cover the horizon.
    y : ndarray, shape (p, N)
        The output at those times.
    margin : ndarray, shape (N,), optional
        Taken off every predicate's robustness at each sample: the task on sets each deflated (reach, always) or
        grown (avoid) by margin(t) (an error-aware plan's sqrt(w(t) / alpha_h)) [default: 0].

    Returns
    -------
    TaskRobustness
    """
    t = np.asarray(t, dtype=float)
    y = np.atleast_2d(np.asarray(y, dtype=float))
    d = np.zeros(t.size) if margin is None else np.broadcast_to(np.asarray(margin, dtype=float), t.shape)
    within = t <= task.horizon * (1 + 1e-12) + 1e-12
    parts: dict[str, float] = {}
    if task.always is not None:
        parts["always"] = float((box_margin(y[:, within], task.always) - d[within]).min())
    times, best = [], []
    for k, reach in enumerate(task.reach):
        inside = _RangeMin(box_margin(y, reach.set) - d)
        starts = np.flatnonzero(t <= reach.by * (1 + 1e-12) + 1e-12)
        held = inside.query(starts, _window_ends(t, starts, reach.hold))
        parts[f"reach[{k}]"] = float(held.max())
        met = np.flatnonzero(held >= 0)
        times.append(float(t[starts[met[0]]]) if met.size else float("nan"))
        best.append(float(t[starts[int(np.argmax(held))]]))
    for k, avoid in enumerate(task.avoid):
        a, b = avoid.during
        sel = (t >= a - 1e-12) & (t <= b * (1 + 1e-12) + 1e-12)
        parts[f"avoid[{k}]"] = float((-box_margin(y[:, sel], avoid.set) - d[sel]).min()) if sel.any() else float("inf")
    return TaskRobustness(min(parts.values()), parts, times, best)
