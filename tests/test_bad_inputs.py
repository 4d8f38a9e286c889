"""Every bad input of the catalogue (tests/bad_inputs.py) gets its one-line message and exit code."""

import pytest

from .bad_inputs import CASES, ROOT, diagnose


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input_answered_clearly(case, tmp_path):
    code, message = diagnose(case, tmp_path / "out")
    assert code == case.code, message
    assert case.fragment in message
    assert "\n" not in message
    assert not (tmp_path / "pwned").exists()


def test_docs_table_lists_every_case():
    # docs/bad-inputs.md is written by `make docs`; regenerate it when a case is added.
    page = (ROOT / "docs" / "bad-inputs.md").read_text()
    for case in CASES:
        assert f"| `{case.id}` |" in page, f"docs/bad-inputs.md lacks {case.id}: run make docs"
