"""Numbers as people and JSON read them: no sign on a zero, a fixed number of significant digits for people.

Light on purpose (numpy only): the command line formats with it before any design machinery is imported.
"""

from __future__ import annotations

import numpy as np

__all__ = ["no_negative_zero", "number_text", "readable", "PEOPLE_DIGITS"]


def no_negative_zero(obj):
    """``obj`` with every float -0.0 replaced by 0.0, through dicts, lists, tuples and numpy arrays.

    Printed, -0.0 reads as "-0" or "-0.0": a sign that means nothing (a product with a zero, a rounding).

    Parameters
    ----------
    obj : object
        A number or a JSON-like structure of them (other objects are returned as they are).

    Returns
    -------
    object
        The same structure (new containers), with 0.0 for -0.0.
    """
    if isinstance(obj, bool):
        return obj
    if isinstance(obj, (float, np.floating)):
        return obj + 0.0 if obj == 0 else obj   # -0.0 + 0.0 is +0.0; NaN and inf are left alone
    if isinstance(obj, dict):
        return {k: no_negative_zero(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [no_negative_zero(v) for v in obj]
    if isinstance(obj, tuple):
        return tuple(no_negative_zero(v) for v in obj)
    if isinstance(obj, np.ndarray) and obj.dtype.kind == "f":
        return obj + 0.0
    return obj


def number_text(value: float, spec: str = ".6g") -> str:
    """``format(value, spec)`` with -0.0 shown as 0 (see :func:`no_negative_zero`).

    Parameters
    ----------
    value : float
        The number.
    spec : str
        A format specification (``.4g``, ``g``, ...).

    Returns
    -------
    str
    """
    return format(no_negative_zero(value), spec)


#: Significant digits of a number shown to a person (``ashc summary``, the report); ``--json`` and the artefacts
#: keep every digit.
PEOPLE_DIGITS = 5


def readable(value, digits: int = PEOPLE_DIGITS) -> str:
    """A stored value as a person reads it: every float to ``digits`` significant digits, through lists and mappings.

    Parameters
    ----------
    value : object
        A number, a string, or a JSON-like structure of them.
    digits : int
        Significant digits of each float.

    Returns
    -------
    str
        ``[-126.19, 0]`` for ``[-126.18750466976748, 0.0]``; strings (formulas) are left as they are.
    """
    if isinstance(value, bool) or value is None:
        return str(value)
    if isinstance(value, (float, np.floating)):
        return number_text(float(value), f".{digits}g")
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k}: {readable(v, digits)}" for k, v in value.items()) + "}"
    if isinstance(value, (list, tuple, np.ndarray)):
        return "[" + ", ".join(readable(v, digits) for v in value) + "]"
    return str(value)
