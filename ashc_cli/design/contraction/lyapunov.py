"""Large plants: the Lyapunov equation instead of an SDP where one matrix A is all there is, and a memory estimate
before any SDP.

A linear plant with a constant input matrix has one A for every u (the vertices of U coincide).  Then eq. (28) at a
rate lambda below lambda_sup = -2 max Re eig(A) has the solution M of

    (A + lambda/2 I)^T M + M (A + lambda/2 I) = -I                                  (so A^T M + M A + lambda M = -I)

(scipy.linalg.solve_continuous_lyapunov, O(n^3), no SDP): 10 s and 0.5 GiB at n = 200 where the full-M SDP needed
more than 24 GiB.  With several distinct vertices the Lyapunov M of their mean is tried first (it often certifies
them all); the SDP runs only when it does not, and only when its memory estimate fits the machine.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla

from ashc_cli.errors import DesignError

__all__ = ["distinct", "lyapunov_M", "sdp_memory_estimate", "refuse_if_too_large", "available_memory"]

#: Peak memory of the full-M SDP (cvxpy + Clarabel), measured on the 2-core machine: about A_BYTES (n / 60)^3.6 per
#: vertex set of two (1.26 GB at n = 60, 8.25 GB at n = 100); with V vertices the cones grow linearly.
SDP_BYTES_AT_60 = 1.26e9
SDP_GROWTH = 3.6


def distinct(matrices: list[np.ndarray], rtol: float = 0.0) -> list[np.ndarray]:
    """The vertex matrices without repeats (a constant A gives 2^m equal vertices).

    Parameters
    ----------
    matrices : list of ndarray
    rtol : float
        0: exact equality; otherwise ``np.allclose`` with this relative tolerance (and atol 0).

    Returns
    -------
    list of ndarray
        The first of each group of equal matrices, in their order.
    """
    out: list[np.ndarray] = []
    for A in matrices:
        if not any(np.array_equal(A, B) if rtol == 0 else np.allclose(A, B, rtol=rtol, atol=0) for B in out):
            out.append(A)
    return out


def lyapunov_M(A: np.ndarray, lam: float) -> np.ndarray | None:
    """M > 0 with A^T M + M A + lam M = -I, scaled to trace(M) = n (the margin is then -n / trace of the raw M), or None
    if A + lam/2 I is not Hurwitz (no M certifies lam).

    Parameters
    ----------
    A : ndarray (n, n)
    lam : float
        The decay rate, in the units of A.

    Returns
    -------
    ndarray (n, n) or None
        Also None when the solution is not finite or not positive definite.
    """
    n = A.shape[0]
    shifted = A + 0.5 * lam * np.eye(n)
    if np.linalg.eigvals(shifted).real.max() >= 0:
        return None
    M = sla.solve_continuous_lyapunov(shifted.T, -np.eye(n))
    M = 0.5 * (M + M.T)
    if not np.all(np.isfinite(M)) or np.linalg.eigvalsh(M).min() <= 0:
        return None
    return n * M / np.trace(M)


def sdp_memory_estimate(n: int, vertices: int, structure: str) -> float:
    """Bytes the SDP of eq. (28) is expected to take (full M: grows like n^3.6; diagonal M: like n^2 per vertex).

    Parameters
    ----------
    n : int
        The number of states.
    vertices : int
        The number of (distinct) vertex matrices.
    structure : {"full", "diagonal"}
        The form of M (anything but ``diagonal`` is estimated as full).

    Returns
    -------
    float
    """
    if structure == "diagonal":
        return 2e8 + 400.0 * n * n * max(1, vertices)
    return 2e8 + SDP_BYTES_AT_60 * (n / 60.0) ** SDP_GROWTH * max(1, vertices) / 2.0


def available_memory() -> float:
    """Bytes this process may still use: the machine's available memory (psutil), or 4 GiB when it is unknown."""
    try:
        import psutil

        return float(psutil.virtual_memory().available)
    except Exception:   # noqa: BLE001 (psutil missing or unreadable: a conservative default)
        return 4.0 * 2**30


def refuse_if_too_large(n: int, vertices: int, structure: str) -> None:
    """Refuse, before it starts, an SDP that would not fit in memory (instead of being killed by the kernel).

    Parameters
    ----------
    n, vertices, structure
        As for :func:`sdp_memory_estimate`.

    Raises
    ------
    DesignError
        Naming ``stabilisability.structure`` when the estimate exceeds 80% of :func:`available_memory`.
    """
    need, have = sdp_memory_estimate(n, vertices, structure), 0.8 * available_memory()
    if need > have:
        raise DesignError("stabilisability.structure", f"the {structure}-M SDP of eq. (28) for n = {n} states and {vertices} vertices would "
                          f"need about {need / 2**30:.1f} GiB, more than the {have / 2**30:.1f} GiB available",
                          "structure: diagonal (n unknowns), a given M (method: given, e.g. from the Lyapunov equation), or a linear "
                          "plant with a constant input matrix (then the Lyapunov equation is used, no SDP)", check="lmi_margin")
