"""The problem: what a spec says (the pydantic contract), how its expressions are parsed (a whitelist, never
``eval``), the concrete and abstract systems it describes (symbolic and lambdified), the scalable example
families, and the sample grids of its boxes.  Imports nothing else of ashc but :mod:`ashc_cli.errors`."""
