"""Write docs/cli.md, the command-line reference, from the typer app itself.

    .venv/bin/python docs/generate_cli.py docs/cli.md      (``make docs`` runs it)

Every command's section is click's own ``--help`` text for it (``typer.main.get_command(ashc_cli.cli.app)``;
typer 0.29 carries its own copy of click, so the command's own ``context_class`` formats it), at a fixed
width so the page does not depend on the terminal.  The contract section before them
(calling convention, output layout, JSON shapes, exit codes) reads what it can from the code: the stage
names, the commands and their options, the names ``ashc eval`` knows, the fields of a verdict row and the
exit code of each error class.  ``tests/test_docs.py`` fails when docs/cli.md differs from :func:`render`.
"""

from __future__ import annotations

import dataclasses
import re
import sys
from pathlib import Path

import typer

from ashc_cli import errors
from ashc_cli.cli import app
from ashc_cli.cli.common import engine
from ashc_cli.design.pipeline import DESIGN, PRODUCTS, STAGES
from ashc_cli.outputs.query import EVALUABLE
from ashc_cli.design.verdict import Row

#: Width click wraps the help to: what `ashc CMD --help` prints in a terminal of 80 columns or more (click's default),
#: fixed so the page does not depend on the terminal it is generated in.
WIDTH = 78

#: Commands the contract (scripts rely on it) names; any this version lacks is listed as not provided.
CONTRACT_SPEC_COMMANDS = ("stabilise", "manifold", "kappa", "inverse", "delta", "bound", "simulate", "design", "check",
                          "plot", "report", "falsify", "tradeoff")
CONTRACT_OTHER_COMMANDS = ("export", "summary", "eval")
CONTRACT_EVAL_NAMES = ("p", "kappa", "m", "delta", "b", "c", "theta", "u_w")


def _context(command, name: str, parent=None):
    """A click context for ``command`` (its own context class) that wraps help at :data:`WIDTH`."""
    return command.context_class(command, info_name=name, parent=parent, terminal_width=WIDTH, max_content_width=WIDTH)


def _params(command) -> tuple[list[str], set[str]]:
    """The command's positional arguments (names) and its option flags."""
    args = [p.name for p in command.params if p.param_type_name == "argument"]
    flags = {flag for p in command.params if p.param_type_name == "option" for flag in (*p.opts, *p.secondary_opts)}
    return args, flags


def _first_paragraph(command) -> str:
    return " ".join((command.help or "").strip().split("\n\n")[0].split())


def _code_list(names) -> str:
    return ", ".join(f"`{n}`" for n in names)


def _exit_codes() -> list[str]:
    rows = ["| code | when | raised as |", "| --- | --- | --- |",
            "| 0 | the command did what it says (`check`: only when Problem 1 is solved) | - |",
            "| 1 | internal error, a bug: rerun with `--debug` and report it | any other exception |"]
    for cls in sorted((errors.SpecError, errors.DesignError, errors.NumericalError, errors.ArtefactError), key=lambda c: c.exit_code):
        doc = " ".join(cls.__doc__.strip().split("\n\n")[0].split())
        doc = re.sub(r"\s*\(exit code \d+\)", "", doc).rstrip(".")
        rows.append(f"| {cls.exit_code} | {doc[0].lower() + doc[1:]} | `{cls.__name__}` |")
    rows.append("| 130 | interrupted (Ctrl-C); artefacts written before the interruption are intact | `KeyboardInterrupt` |")
    return rows


def _contract(group) -> list[str]:
    commands = group.commands
    spec_first = [n for n, c in commands.items() if _params(c)[0][:1] == ["spec"]]
    without_out = [n for n in spec_first if "--out" not in _params(commands[n])[1]]
    with_json = [n for n, c in commands.items() if "--json" in _params(c)[1]]
    missing = [n for n in (*CONTRACT_SPEC_COMMANDS, *CONTRACT_OTHER_COMMANDS) if n not in commands]
    eval_missing = [n for n in CONTRACT_EVAL_NAMES if n not in EVALUABLE]
    row_keys = [f.name for f in dataclasses.fields(Row)]
    stage_files = "  ".join(f"{name}.h5" for name in STAGES)
    engine()   # the products register with the pipeline when the machinery is loaded (the CLI loads it lazily)
    extra_files = "  ".join(f"{name}.h5" for name in PRODUCTS)

    out = [
        "## The contract",
        "",
        "Scripts and CI runs rely on these shapes (the project's command-line contract); options may be added, these stay.",
        "",
        "**Calling convention.** " + _code_list(spec_first) + " take the spec path first, then options; "
        + ("each takes `--out DIR`" if not without_out else f"all but {_code_list(without_out)} take `--out DIR`")
        + " (default `outputs/<name>`, with `<name>` the spec's `name` key, relative to the working directory). "
        "A command that needs upstream stages runs the stale ones first; with `--frozen` it fails instead (exit 5, "
        "naming the stale stage): stage commands, `simulate` and `falsify` still compute their own result, `design`, "
        "`check`, `plot` and `report` compute nothing. `summary DIR` and `eval DIR NAME --at ...` read a finished "
        "artefact folder and need no spec. `--debug` is accepted anywhere on the line (it is not a click option, so "
        "it is not in the help below): it shows the traceback and library warnings.",
        "",
        f"The stages, in flow-chart order: {_code_list(STAGES)}. `design` runs {_code_list(DESIGN)}; "
        "the commands that work on a design in the folder first run the stale stages they need (`summary` and `eval` "
        "only read the folder).",
        "",
        "**Output layout** (`<out>` is the `--out` folder):",
        "",
        "```text",
        "<out>/",
        f"  {stage_files}",
        "      one HDF5 artefact per stage (layout: the docstring of ashc_cli/design/artefacts.py)",
        f"  {extra_files}",
        "      written by falsify, and by report when there is none for this design or it was made with other --runs/--seed/--t-final than report is given",
        "  plots/*.png",
        "      written by plot and report",
        "  report.html",
        "      written by report",
        "  sweep.h5  sweep/<k>/  plots/sweep.png",
        "      written by sweep (sweep/<k>/ is the design folder of combination k)",
        "```",
        "",
        "**Output streams.** Results go to stdout; errors go to stderr. Each stage prints one progress line, "
        "`<stage> <status> <seconds> s  <headline>` with status `ran` or `up to date` (an `up to date` line once per "
        "command, though `report` consults the design three times). It goes to stderr for "
        "every command (stdout carries only results: a summary line or table, JSON, file paths; a stage command "
        "prints its artefact's path); when stderr is a terminal a live display (spinner, or a bar with runs/s for "
        "`falsify`) shows while a step runs and is erased after. "
        f"With `--json` ({_code_list(with_json)}), stdout holds exactly one JSON document.",
        "",
        "**`ashc summary DIR --json`** prints one JSON object whose keys are the stage names present in the folder. "
        "Each value is that stage's headline numbers and formulas (strings, with the parameters as symbols), plus "
        "`checks` (`{name: {value, passed, description, evidence}}`) and `provenance` "
        "(`spec_sha256`, `created`, `ashc_version`, `sha256`). A check value that is not finite is the string `inf` or `nan`; "
        "a headline number that is not finite is JSON `Infinity` (e.g. `bound.w0_max_certified` when the bound is global).",
        "",
        f"**`ashc eval DIR NAME --at a=1,b=2`** prints `NAME(a=1, b=2) = [v1, v2, ...]` for NAME in {_code_list(EVALUABLE)}, "
        "with the spec's own variable names (a scalar prints as a one-element list). `m`, `b` and `c` are evaluated only "
        "at states whose output lies in the set where m is certified (`inverse.m_domain`); elsewhere the error names the set (exit 2).",
        "",
        "**`ashc check SPEC --json`** prints `{spec, solved, verdict, sampled, rows, simulated}`: `verdict` is `proved` "
        "(every row that enters Problem 1, G and the certified region is proved), `sampled` (every row passes, some only "
        "on samples: `sampled` names them) or `fails`; `solved` is true for the first two. Each row is "
        "`{" + ", ".join(row_keys) + "}` with `status` `pass`, `fail` or `not reached` and `evidence` `proved`, "
        "`sampled` or `simulated` (`-` when not reached). `simulated` lists the checks of the last `simulate` run on "
        "this spec (`{check, status, value, detail, evidence}`; empty with `--force`), outside the verdict. "
        "`ashc check` exits 0 for `proved` and `sampled`, 3 for `fails`; with `--require proved` a verdict on samples "
        "exits 3 too.",
        "",
        "**Errors** are one line on stderr, `error: <where>: <what>; expected <what>`, where `<where>` is the spec "
        "field (`concrete.f_bar[1]`) or the stage. No traceback unless `--debug`.",
        "",
        "**Exit status:**",
        "",
        *_exit_codes(),
        "",
        "Code 3 also covers `check` answering no (or holding on samples only with `--require proved`), `falsify` finding a "
        "violation or a counter-example to a sampled row, and `regress` finding a difference. "
        "`simulate` exits 0 when a scenario check fails: it prints `FAILED (simulated)` and `check` lists it.",
    ]
    if missing or eval_missing:
        gaps = []
        if missing:
            gaps.append(f"the commands {_code_list(missing)}")
        if eval_missing:
            gaps.append(f"`eval` of {_code_list(eval_missing)}")
        out += ["", "**Named by the contract, not provided by this version:** " + "; ".join(gaps) + "."]
    return out


def render() -> str:
    """The whole of docs/cli.md."""
    group = typer.main.get_command(app)
    root = _context(group, "ashc")
    out = [
        "# The ashc command line",
        "",
        "<!-- Generated by docs/generate_cli.py from ashc_cli.cli.app: do not edit by hand, run `make docs`. -->",
        "",
        "The reference for every command and option, generated from the program itself: each section below is "
        "the command's `--help`. The spec format is [spec-format.md](spec-format.md); the theory behind each stage "
        "is [theory.md](theory.md).",
        "",
        *_contract(group),
        "",
        "## Commands",
        "",
        "| command | what it does |",
        "| --- | --- |",
    ]
    for name, command in group.commands.items():
        out.append(f"| [`{name}`](#ashc-{name}) | {_first_paragraph(command)} |")
    out += ["", "## `ashc`", "", "```text", group.get_help(root).rstrip(), "```"]
    for name, command in group.commands.items():
        out += ["", f"## `ashc {name}`", "", "```text", command.get_help(_context(command, name, root)).rstrip(), "```"]
    return "\n".join(out) + "\n"


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: python docs/generate_cli.py docs/cli.md", file=sys.stderr)
        return 2
    target = Path(argv[0])
    target.write_text(render(), encoding="utf-8")
    print(f"{target}: {len(typer.main.get_command(app).commands)} commands")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
