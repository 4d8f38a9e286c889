"""ashc: approximate simulation-based hierarchical control design for nonlinear input-affine systems.

The package follows the design flow chart of the paper (Fig. 3), one module per stage under
:mod:`ashc_cli.design.stages`; :mod:`ashc_cli.design.pipeline` runs them in order and :mod:`ashc_cli.cli` is the
command line.
"""

__version__ = "0.1.0"
