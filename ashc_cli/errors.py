"""The exceptions ashc raises, one class per exit code.

Every error the tool means to report derives from :class:`AshcError`.  The CLI turns one into a single
line on stderr, ``error: <where>: <what>; expected <what>``, and exits with the class's ``exit_code``.
Anything else that escapes is a bug and exits with code 1 (traceback only with ``--debug``).

=====  ==========================  ==========================================================
code   class                       meaning
=====  ==========================  ==========================================================
1      (any other exception)       an internal bug: please report it with ``--debug`` output
2      :class:`SpecError`          the spec (or a command-line argument) is malformed
3      :class:`DesignError`        a design condition of the paper does not hold for this spec
4      :class:`NumericalError`     a solver or integrator failed, or a self-check did not pass
5      :class:`ArtefactError`      an artefact is missing, stale, foreign or unreadable
=====  ==========================  ==========================================================
"""

from __future__ import annotations

__all__ = [
    "AshcError",
    "SpecError",
    "DesignError",
    "ScenarioStopped",
    "NumericalError",
    "ArtefactError",
    "FitError",
    "CoverError",
    "EXIT_CODES",
    "INTERRUPTED",
]

#: The line printed on Ctrl-C, by the console script (while the libraries load) and by the CLI's guard (exit 130).
INTERRUPTED = "error: interrupted; artefacts written before the interruption are intact"


class AshcError(Exception):
    """Base class of every error ashc reports to the user.

    Parameters
    ----------
    where : str
        The place the problem is, e.g. a spec field (``concrete.f_bar[2]``) or a stage name.
    what : str
        What is wrong, naming the offending value where there is one.
    expected : str, optional
        What would have been right.
    """

    exit_code = 1

    def __init__(self, where: str, what: str, expected: str | None = None):
        self.where = where
        self.what = what
        self.expected = expected
        super().__init__(self.line())

    def line(self) -> str:
        """The one-line message the CLI prints (without the ``error:`` prefix)."""
        from ashc_cli.paper import cite   # the paper's numbers, not its LaTeX labels

        text = f"{self.where}: {self.what}" if self.where else self.what
        if self.expected:
            text += f"; expected {self.expected}"
        return cite(" ".join(text.split()))  # one line, whatever the parts held


class SpecError(AshcError):
    """The spec file or a command-line value is malformed (exit code 2)."""

    exit_code = 2


class DesignError(AshcError):
    """A condition of the paper's design procedure does not hold (exit code 3).

    Examples: the LMI is infeasible, p is not injective on V, kappa(V) does not cover Y, delta loses rank.
    ``check`` names the stage check the failure is about (for the Problem 1 verdict), if there is one.
    """

    exit_code = 3

    def __init__(self, where: str, what: str, expected: str | None = None, *, check: str | None = None):
        self.check = check
        super().__init__(where, what, expected)


class ScenarioStopped(DesignError):
    """A simulated scenario stopped part-way (exit code 3): its run left the set where the design holds (the
    m-relation's y leaving where m is certified).  An observation of one run, not of the design: when the spec has
    another scenario, simulate keeps that one's results and records this one as a failing simulated check."""


class NumericalError(AshcError):
    """A solver or integrator failed, or a stage's own residual check did not pass (exit code 4)."""

    exit_code = 4


class ArtefactError(AshcError):
    """An artefact is missing, stale, made from another spec or schema, or unreadable (exit code 5)."""

    exit_code = 5


# Internal refusals: caught inside ashc, where a slower or sampled path takes over; never reach the user.

class UnsupportedExpression(ValueError):
    """A sympy node :func:`compile_interval` cannot enclose rigorously.

    Parameters
    ----------
    node : sympy.Basic
        The offending node.
    why : str, optional
        Why it is refused, if more can be said than its type.
    """

    def __init__(self, node: object, why: str | None = None):
        self.node = node
        name = type(node).__name__
        text = str(node)
        text = text if len(text) <= 60 else text[:57] + "..."
        msg = f"cannot enclose the sympy node {name} ({text})"
        super().__init__(msg + (f": {why}" if why else ""))


class Unsupported(Exception):
    """The compiled closed loop cannot run this design (numba is missing, or an expression has no numba form).

    simulate and falsify turn it into a one-line NumericalError, exit 4 (there is no other integrator; a missing
    integrator is no design condition, and exit 3 from falsify means a broken bound).
    """


class FitError(ValueError):
    """:func:`ashc_cli.numerics.chebyshev.fit_adaptive` found no piecewise series meeting its test; the stage that
    asked turns it into a DesignError naming where.

    Parameters
    ----------
    interval : (float, float)
        Where the fit failed.
    measure : float
        The best value the test returned there.
    reason : str
        Why splitting stopped (too many pieces, or pieces too narrow).
    """

    def __init__(self, interval: tuple[float, float], measure: float, reason: str):
        super().__init__(reason)
        self.interval, self.measure, self.reason = interval, measure, reason


class CoverError(ValueError):
    """Newton finds no xi in V with kappa(xi) = y for some y of Y (kappa(V) does not cover Y, eq. (10), or kappa
    is not invertible there); the inverse stage turns it into a DesignError naming the output.

    Parameters
    ----------
    y : ndarray (p,)
        The first such output.
    residual : float
        The best max |kappa(xi) - y| / max(1, |Y|) Newton reached.
    excursion : float
        How far outside V the solution found lies (<= 0 inside).
    """

    def __init__(self, y, residual: float, excursion: float):
        super().__init__("no preimage in V")
        self.y, self.residual, self.excursion = y, residual, excursion


class Untranslatable(ValueError):
    """A law that ``ashc export`` prints (:mod:`ashc_cli.outputs.translate`) uses a construct outside the subset the
    printer reads; the message names the function, its file and line.  A developer's error: the tests print every
    law, so it never reaches a user."""


EXIT_CODES = {cls.__name__: cls.exit_code for cls in (SpecError, DesignError, NumericalError, ArtefactError)}
