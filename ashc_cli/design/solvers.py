"""cvxpy (with the Clarabel solver), imported on its first use.

Importing cvxpy pulls in scipy.stats: 0.65 s of the 2.0 s every ``ashc`` command took to start, though only the
stages that solve an LMI or a quadratic program use it.  ``cp`` is the cvxpy module behind the standard library's
lazy loader (:class:`importlib.util.LazyLoader`): ``import`` costs nothing, the first attribute read runs cvxpy's import.
"""

from __future__ import annotations

import importlib.util
import sys

__all__ = ["cp"]


def _lazy(name: str):
    """The module ``name``, executed on its first attribute access (the recipe of the importlib documentation).

    Parameters
    ----------
    name : str
        A top-level module name.

    Returns
    -------
    module
    """
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.find_spec(name)
    loader = importlib.util.LazyLoader(spec.loader)
    spec.loader = loader
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    loader.exec_module(module)
    return module


cp = _lazy("cvxpy")
