"""The design stages, one module per box of the paper's flow chart (Fig. 3), in order.

Each module has the same small interface: ``NAME``, ``UPSTREAM`` (the stages whose artefacts it reads),
``run(model, upstream) -> Artefact`` (a pure function), ``summarise(artefact) -> dict`` and
``headline(artefact) -> str``.
"""

from ashc_cli.design.stages import bound, delta, inverse, kappa, manifold, simulate, stabilise

#: Every stage in the order the flow chart walks them.
ORDER = (stabilise, manifold, kappa, inverse, delta, bound, simulate)
#: The stages ``ashc design`` runs.
DESIGN = ("stabilise", "manifold", "kappa", "inverse", "delta", "bound")
