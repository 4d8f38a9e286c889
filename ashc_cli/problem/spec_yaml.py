"""The YAML reading of a spec (:func:`load_yaml`): PyYAML's safe loader, refusing aliases (no billion laughs),
duplicate keys (a typo must not hide) and numbers with more digits than a double holds (exact decisions read the
digits written)."""

from __future__ import annotations

from typing import Any

import yaml

from ashc_cli.errors import SpecError

__all__ = ["load_yaml"]


class _SafeStrictLoader(yaml.SafeLoader):
    """SafeLoader that refuses aliases (no billion-laughs) and duplicate keys (a typo must not hide)."""

    def compose_node(self, parent, index):  # noqa: D401 - PyYAML hook
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.MarkedYAMLError("while composing", None, "aliases (*name) are not allowed in a spec", event.start_mark)
        return super().compose_node(parent, index)

    def construct_document(self, node):
        _refuse_duplicate_keys(node, "")
        return super().construct_document(node)

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if not isinstance(key, str):
                raise yaml.MarkedYAMLError("while constructing a mapping", node.start_mark, f"key {key!r} is not a name (every key of a spec is text)", key_node.start_mark)
            if key in seen:
                raise yaml.MarkedYAMLError("while constructing a mapping", node.start_mark, f"duplicate key '{key}'", key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


def _refuse_duplicate_keys(node: yaml.Node, path: str) -> None:
    """Refuse a key written twice in one mapping, naming the field it is in (``concrete.input_bounds``)."""
    if isinstance(node, yaml.MappingNode):
        seen = set()
        for key_node, value_node in node.value:
            key = key_node.value if isinstance(key_node, yaml.ScalarNode) else None
            if key in seen:
                shown = key if len(key) <= 40 else key[:37] + "..."
                raise yaml.MarkedYAMLError("while constructing a mapping", node.start_mark,
                                           f"duplicate key '{shown}'" + (f" in {path}" if path else ""), key_node.start_mark)
            if key is not None:
                seen.add(key)
            _refuse_duplicate_keys(value_node, f"{path}.{key}" if path else str(key))
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            _refuse_duplicate_keys(item, f"{path}[{i}]")
    elif isinstance(node, yaml.ScalarNode) and node.tag in (_FLOAT_TAG, _INT_TAG) and not path.startswith(("stabilisability.M", "stabilisability.K")):
        _refuse_unheld_digits(node, path)


_FLOAT_TAG, _INT_TAG = "tag:yaml.org,2002:float", "tag:yaml.org,2002:int"


def _refuse_unheld_digits(node: yaml.ScalarNode, path: str) -> None:
    """Refuse a number written with more digits than a double holds (2.99999999999999999 reads as 3.0).

    Exact decisions (l(V) inside U, kappa(V) covering Y, identities) read each number as the decimal it is
    written as; that is only the number the tool computes with when the double holds every written digit.
    """
    import decimal

    text = node.value.replace("_", "")
    try:
        written = decimal.Decimal(text)
    except decimal.InvalidOperation:
        return   # .inf, .nan and the like: the validators say what is wrong with them
    if not written.is_finite():
        return
    value = float(written)
    if value in (float("inf"), float("-inf")) or decimal.Decimal(repr(value)) != written:
        raise SpecError(path or f"line {node.start_mark.line + 1}", f"{node.value} has more significant digits than a double holds (it would be read as {value!r})",
                        "the number written with at most 17 significant digits (every exact decision reads the digits written)")


def load_yaml(text: str, source: str) -> Any:
    """The YAML document of a spec, read safely: no aliases, no key twice, no number with more digits than a double
    holds; a malformed document is a one-line SpecError naming the line and column.

    Parameters
    ----------
    text : str
        The document.
    source : str
        Its name in messages (the file, or "spec").

    Returns
    -------
    object
        What the document holds (the caller checks it is a mapping).
    """
    try:
        return yaml.load(text, Loader=_SafeStrictLoader)  # noqa: S506 - a SafeLoader subclass
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark
        where = f"{source}:{mark.line + 1}:{mark.column + 1}" if mark else source
        duplicate = str(exc.problem).startswith("duplicate key")
        raise SpecError(where, f"malformed YAML ({exc.problem})",
                        "every key once in a mapping" if duplicate else "a YAML mapping written to docs/spec-format.md") from None
    except (yaml.YAMLError, RecursionError) as exc:
        raise SpecError(source, f"malformed YAML ({type(exc).__name__})", "a YAML mapping written to docs/spec-format.md") from None
