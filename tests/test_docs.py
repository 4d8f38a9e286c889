"""The pages in docs/ against the code they describe: none may drift.

* docs/spec-format.md documents every key of the spec models (walked recursively) and no key that is gone;
  its minimal example is a valid spec;
* docs/cli.md is exactly what docs/generate_cli.py writes from the typer app (``make docs``);
* every relative link in README.md and docs/*.md resolves (file, and heading anchor where one is given);
* every docs/... path and every .md page named in README.md or the package's source exists;
* docs/labels.json and the label table of docs/theory.md agree.
"""

from __future__ import annotations

import importlib.util
import json
import re
import typing
from pathlib import Path

from pydantic import BaseModel

from ashc_cli.problem.spec import Spec, parse_spec_text

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PAGES = sorted(DOCS.glob("*.md"))
SOURCES = sorted((ROOT / "ashc_cli").glob("*.py")) + sorted((ROOT / "ashc_cli" / "stages").glob("*.py"))


# --- the spec format ------------------------------------------------------------------------------------


def _models_in(annotation) -> list[type[BaseModel]]:
    """The pydantic models an annotation refers to (through Optional, Union, Annotated, list, dict)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    found = []
    for arg in typing.get_args(annotation):
        found += _models_in(arg)
    return found


def spec_keys(model: type[BaseModel] = Spec, prefix: str = "") -> list[str]:
    """Every key a spec may hold, as a dotted path (``simulate.tracking.abstract_controller.gain``)."""
    keys = []
    for name, field in model.model_fields.items():
        path = prefix + name
        keys.append(path)
        for sub in _models_in(field.annotation):
            keys += [key for key in spec_keys(sub, path + ".") if key not in keys]   # a union's members share keys (kind, gain)
    return keys


def test_the_walk_reaches_every_level_of_the_models():
    keys = spec_keys()
    assert {"name", "concrete.state_box", "stabilisability.structure", "abstract.manifold_guess",
            "interface.saturate", "simulate.m_relation.u", "simulate.tracking.abstract_controller.v_max"} <= set(keys)
    assert len(keys) == len(set(keys)) > 40


def test_every_spec_key_is_documented():
    page = (DOCS / "spec-format.md").read_text(encoding="utf-8")
    missing = [key for key in spec_keys() if f"`{key}`" not in page]
    assert not missing, f"docs/spec-format.md does not document {', '.join(missing)} (see the models in ashc_cli/problem/spec.py)"


def test_every_documented_key_exists():
    # The first column of the key tables: a key that is documented but no longer accepted is drift too.
    page = (DOCS / "spec-format.md").read_text(encoding="utf-8")
    documented = re.findall(r"^\| `([a-z_][a-z0-9_.]*)` \|", page, re.M | re.I)
    assert len(documented) > 40
    unknown = sorted(set(documented) - set(spec_keys()))
    assert not unknown, f"docs/spec-format.md documents keys the loader does not accept: {', '.join(unknown)}"


def test_the_minimal_example_is_a_valid_spec():
    page = (DOCS / "spec-format.md").read_text(encoding="utf-8")
    first = re.search(r"```yaml\n(.*?)```", page, re.S).group(1)
    spec = parse_spec_text(first, "docs/spec-format.md")
    assert spec.name == "first_order" and spec.interface.q == "least_squares" and spec.abstract.delta == "identity"


# --- the command-line reference --------------------------------------------------------------------------


def _generator():
    loaded = importlib.util.spec_from_file_location("generate_cli", DOCS / "generate_cli.py")
    module = importlib.util.module_from_spec(loaded)
    loaded.loader.exec_module(module)
    return module


def test_cli_md_is_generated_from_the_app():
    expected = _generator().render()
    actual = (DOCS / "cli.md").read_text(encoding="utf-8")
    assert actual == expected, "docs/cli.md differs from what docs/generate_cli.py writes from the typer app: run `make docs`"


def test_cli_md_has_every_command_and_option():
    import typer

    from ashc_cli.cli import app

    text = _generator().render()
    group = typer.main.get_command(app)
    for name, command in group.commands.items():
        assert f"## `ashc {name}`" in text
        for param in command.params:
            for flag in getattr(param, "opts", []):
                if flag.startswith("--"):
                    assert flag in text, f"{name} {flag}"


# --- links and paths -----------------------------------------------------------------------------------


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    text = re.sub(r"```.*?```", "", page.read_text(encoding="utf-8"), flags=re.S)
    return {_slug(h) for h in re.findall(r"^#+ (.+)$", text, re.M)}


def _links(page: Path) -> list[str]:
    text = re.sub(r"```.*?```", "", page.read_text(encoding="utf-8"), flags=re.S)  # code blocks hold no links
    return re.findall(r"\]\(([^)\s]+)\)", text)


def test_relative_links_resolve():
    broken = []
    for page in [ROOT / "README.md", *PAGES]:
        for link in _links(page):
            if re.match(r"[a-z]+:", link):  # http:, https:, mailto:
                continue
            path, _, anchor = link.partition("#")
            target = (page.parent / path).resolve() if path else page
            if not target.exists():
                broken.append(f"{page.relative_to(ROOT)}: {link} (no such file)")
            elif anchor and target.suffix == ".md" and anchor not in _anchors(target):
                broken.append(f"{page.relative_to(ROOT)}: {link} (no such heading)")
    assert not broken, "broken links:\n" + "\n".join(broken)


def test_docs_paths_named_in_readme_and_source_exist():
    missing = []
    for source in [ROOT / "README.md", *SOURCES]:
        for path in set(re.findall(r"\bdocs/[\w.-]*\w", source.read_text(encoding="utf-8"))):
            if not (ROOT / path).exists():
                missing.append(f"{source.relative_to(ROOT)}: {path}")
    assert not missing, "paths that do not exist:\n" + "\n".join(missing)


def test_pages_named_in_the_source_exist():
    # Help texts and messages name pages ("see spec-format.md"): each must be in docs/ or at the top level.
    missing = []
    for source in SOURCES:
        for name in set(re.findall(r"[\w-]+\.md\b", source.read_text(encoding="utf-8"))):
            if not ((DOCS / name).exists() or (ROOT / name).exists()):
                missing.append(f"{source.relative_to(ROOT)}: {name}")
    assert not missing, "pages that do not exist in docs/:\n" + "\n".join(missing)


# --- the paper's numbering -----------------------------------------------------------------------------


def test_labels_json_matches_the_table_of_theory_md():
    labels = json.loads((DOCS / "labels.json").read_text(encoding="utf-8"))
    table = dict(re.findall(r"^\| `([a-z]+:\w+)` \| ([^|]+?) \|", (DOCS / "theory.md").read_text(encoding="utf-8"), re.M))
    full = {k: v for k, v in labels.items() if ":" in k}
    assert len(full) > 80 and full == table
    # A bare name is its full label's number; for a name used twice, the theorem or definition's.
    for key, value in labels.items():
        if ":" not in key:
            assert value in {v for k, v in full.items() if k.split(":", 1)[1] == key}, key
    for value in labels.values():
        assert re.fullmatch(r"eq\. \(\d+[a-z]?\)|(Theorem|Lemma|Assumption|Problem|Remark|Corollary|Proposition|Definition|Fig\.) \d+|"
                            r"Table [IVX]+|Section [IVX]+(-[A-Z])?", value), value


def test_readme_tour_shows_the_real_output(tmp_path):
    """README's tour quotes `ashc design` and `ashc check` on the Cuk spec: they must be what the code prints."""
    from .conftest import CUK, ashc

    readme = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```\n(.*?)```", readme, flags=re.S)
    out = tmp_path / "cuk_converter"
    design = ashc("design", str(CUK), "--out", str(out), check=True).stdout
    check = ashc("check", str(CUK), "--out", str(out), check=True).stdout
    assert check in blocks, "README's `ashc check` block differs from the real output"
    assert design.strip().replace(str(out), "outputs/cuk_converter") + "\n" in blocks, "README's `ashc design` line differs"


def test_readme_states_the_suite_size_that_is_collected():
    import subprocess
    import sys

    def collected(*extra: str) -> int:
        proc = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider", "-p", "no:xdist", *extra],
                              capture_output=True, text=True, cwd=ROOT, timeout=300)
        return int(re.search(r"(\d+)(?:/\d+)? tests? (?:collected|selected)", proc.stdout).group(1))

    text = (ROOT / "README.md").read_text()
    assert int(re.search(r"the whole suite \((\d+) tests\)", text).group(1)) == collected()
    assert int(re.search(r"leaves out the (\d+) tests marked", text).group(1)) == collected("-m", "slow")


def test_what_users_read_cites_the_papers_numbers_not_its_labels():
    """README, the docs (but theory.md, the one page that maps numbers to labels), the example specs, the bench
    script and every --help (docs/cli.md is generated from them): no LaTeX label of the paper."""
    from ashc_cli.paper import LABELS, cite

    camel = re.compile(r"\b(" + "|".join(sorted((re.escape(k) for k in LABELS if re.search(r"[a-z][A-Z]", k) and ":" not in k),
                                                key=len, reverse=True)) + r")\b")
    read = [ROOT / "README.md", ROOT / "CHANGELOG.md", ROOT / "outputs" / "README.md", *PAGES,
            *sorted((ROOT / "specs").glob("*.yaml")), *sorted((ROOT / "bench").glob("*.py"))]
    labelled = {}
    for path in read:
        if path.name == "theory.md":
            continue
        text = path.read_text(encoding="utf-8")
        found = sorted(set(camel.findall(text)))
        if found or cite(text) != text:
            labelled[str(path.relative_to(ROOT))] = found
    assert not labelled, f"LaTeX labels of the paper in {labelled}: write the paper's numbers (ashc_cli.paper.cite)"
