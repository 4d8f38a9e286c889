"""What is built on a finished design: falsification and its attacks on sampled rows, the tolerance
trade-off, parameter sweeps over a Dask cluster, and the regression of the shipped specs' numbers.  Each
registers with :mod:`ashc_cli.design.pipeline` as a product (its artefact is cached like a stage's)."""

from ashc_cli.design.pipeline import register_product
from ashc_cli.products import falsify, synthesize, tradeoff

register_product(falsify)
register_product(tradeoff)
register_product(synthesize)
