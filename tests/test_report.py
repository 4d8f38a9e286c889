"""Tests of the review page (ashc_cli.outputs.report): every stored value in full, a layout that fits a laptop screen,
and (where Chromium is installed) the page as a real browser renders it."""

from __future__ import annotations

import html
import json
import os
import re
import shutil
import subprocess

import matplotlib.image as mpimg
import matplotlib.pyplot as plt
import numpy as np
import pytest

from ashc_cli.outputs import plots
from ashc_cli.paper import LABELS
from ashc_cli.design.pipeline import load_all
from ashc_cli.outputs.query import readable, summary
from ashc_cli.outputs.report import CSS, _figure_html, render
from ashc_cli.problem.spec import load_spec
from ashc_cli.design.verdict import verdict

from .conftest import CUK, SPECS, ashc

#: A laptop screen's width in CSS pixels.
LAPTOP = 1366


@pytest.fixture(scope="module")
def cuk_page(cli_run, tmp_path_factory):
    """The page of the Cuk design (its 4 x 4 M and its long formula b), figures included, rendered in-process."""
    out = cli_run["out"]
    arts = load_all(out)
    figures = plots.write_all(load_spec(CUK), arts, tmp_path_factory.mktemp("cuk_plots"))
    page = render(CUK.read_text(encoding="utf-8"), "cuk_converter", arts, verdict(arts), figures)
    path = tmp_path_factory.mktemp("cuk_page") / "report.html"
    path.write_text(page, encoding="utf-8")
    return page, arts, path


@pytest.fixture(scope="module")
def two_input_page(tmp_path_factory):
    """`ashc report` of the two-output design: a two-column figure and a falsification section."""
    out = tmp_path_factory.mktemp("two_input_report")
    ashc("report", str(SPECS / "bilinear_two_input.yaml"), "--out", str(out), "--runs", "6", "--t-final", "2", check=True)
    return out / "report.html"


def stored_lists(arts):
    """Every list value of the summary (formulas, matrices, vectors) by (stage, key)."""
    return {(stage, k): v for stage, entry in summary(arts).items() for k, v in entry.items()
            if isinstance(v, list) and k not in ("checks", "provenance")}


def test_every_formula_in_full_and_every_number_to_five_digits(cuk_page):
    page, arts, _ = cuk_page
    assert "..." not in page and "\u2026" not in page                 # nothing cut short
    M = np.asarray(arts["stabilise"].value("M"), dtype=float)
    for row in M.tolist():                                            # the 4 x 4 M: every row, 5 digits each
        assert html.escape(readable(row)) in page
    assert "0.93585, 0.016732" in page and "0.935846241161949" not in page   # M[0, :2] for people, not 16 digits
    lists = stored_lists(arts)
    b = lists[("delta", "b")]
    assert len(b[0]) > 300                                            # the case that used to be cut at 300
    for (stage, key), value in lists.items():
        for item in value:
            text = item if isinstance(item, str) else readable(item)
            assert html.escape(text) in page, (stage, key)
    assert html.escape(arts["stabilise"].provenance["sha256"]) in page   # the artefact's whole hash too


def test_long_values_sit_in_scroll_boxes(cuk_page):
    page, arts, _ = cuk_page
    b = stored_lists(arts)[("delta", "b")][0]
    boxes = re.findall(r'<pre class="box(?: matrix)?">(.*?)</pre>', page, flags=re.S)
    assert any(html.escape(b) in box for box in boxes)
    assert any(html.escape(readable(np.asarray(arts["stabilise"].value("M")).tolist()[0])) in box for box in boxes)
    rule = re.search(r"pre\.box \{([^}]*)\}", CSS).group(1)
    assert "overflow: auto" in rule and "max-height" in rule and "overflow-wrap: anywhere" in rule


def test_figures_are_shown_by_their_column_width(tmp_path):
    shown = {}
    for width in (plots.COLUMN_WIDTH, plots.DOUBLE_WIDTH):
        fig = plt.figure(figsize=(width, 2))
        path = plots.save(fig, tmp_path / f"w{width}.png")
        assert mpimg.imread(path).shape[1] == round(width * plots.STYLE["savefig.dpi"])
        shown[width] = int(re.search(r'width="(\d+)"', _figure_html(path)).group(1))
    assert shown[plots.COLUMN_WIDTH] == 420
    assert abs(shown[plots.DOUBLE_WIDTH] / shown[plots.COLUMN_WIDTH] - 7.16 / 3.5) < 0.01
    assert "max-width: 100%" in re.search(r"figure img \{([^}]*)\}", CSS).group(1)  # never wider than the page


# --- in a real browser -------------------------------------------------------------------------------------

def _chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable", "chrome"):
        found = shutil.which(name)
        if found:
            return found
    return None


#: Appended to a copy of the page (the report itself has no script): on load it writes what the browser
#: measured into the DOM, which --dump-dom prints.
PROBE = r"""<script>window.addEventListener('load', function () {
  var imgs = Array.prototype.slice.call(document.images);
  var root = document.documentElement;
  var r = {images: imgs.length,
           broken: imgs.filter(function (i) { return !(i.complete && i.naturalWidth > 0); }).length,
           scrollWidth: root.scrollWidth, clientWidth: root.clientWidth, innerWidth: window.innerWidth,
           rightmost: Math.max.apply(null, Array.prototype.map.call(document.querySelectorAll('body *'),
                                     function (e) { return e.getBoundingClientRect().right; })),
           text: document.body.innerText, narrow: []};
  // every table cell (but the scroll boxes) at least as wide as its longest word: nothing broken mid-word
  var ctx = document.createElement('canvas').getContext('2d');
  Array.prototype.forEach.call(document.querySelectorAll('td, th'), function (c) {
    if (c.querySelector('pre')) { return; }
    var cs = getComputedStyle(c);
    var inner = c.clientWidth - parseFloat(cs.paddingLeft) - parseFloat(cs.paddingRight);
    ctx.font = (c.querySelector('b, strong, .pass, .fail') || cs.fontWeight >= 600 ? 'bold ' : '') + cs.fontSize + ' ' + cs.fontFamily;
    c.innerText.split(/\s+/).forEach(function (w) {
      var width = ctx.measureText(w).width;
      if (w && width > inner + 0.5) { r.narrow.push(w + ' (' + Math.round(width) + ' px in ' + Math.round(inner) + ' px)'); }
    });
  });
  var p = document.createElement('pre'); p.id = 'ashc-probe'; p.textContent = JSON.stringify(r);
  document.body.appendChild(p);
});</script>"""


def _browser(exe: str, tmp_path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([exe, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", "--mute-audio",
                           "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run",
                           f"--user-data-dir={tmp_path / 'profile'}", "--virtual-time-budget=10000", *args],
                          capture_output=True, text=True, timeout=180)


@pytest.mark.parametrize("which", ["cuk", "two_input"])
def test_the_page_renders_in_chromium_without_broken_images_or_sideways_scrolling(which, request, tmp_path):
    exe = _chromium()
    if exe is None:
        # .ci/run installs Chromium and sets ASHC_REQUIRE_BROWSER: on CI this check is never skipped.
        assert not os.environ.get("ASHC_REQUIRE_BROWSER"), "ASHC_REQUIRE_BROWSER is set but no Chromium is on PATH"
        pytest.skip("Chromium is not installed (e.g. `apt-get install chromium`): the rendered-page check is skipped")
    path = request.getfixturevalue("cuk_page")[2] if which == "cuk" else request.getfixturevalue("two_input_page")
    page = path.read_text(encoding="utf-8")
    probed = tmp_path / "probed.html"
    probed.write_text(page.replace("</body>", PROBE + "</body>"), encoding="utf-8")
    proc = _browser(exe, tmp_path, f"--window-size={LAPTOP},900", "--dump-dom", probed.as_uri())
    found = re.search(r'<pre id="ashc-probe">(.*?)</pre>', proc.stdout, flags=re.S)
    assert found, f"Chromium printed no measurement (exit {proc.returncode}): {proc.stderr[-2000:]}"
    got = json.loads(html.unescape(found.group(1)))
    assert got["innerWidth"] == LAPTOP
    assert got["images"] == page.count("<img ") >= 6
    assert got["broken"] == 0
    assert got["scrollWidth"] <= got["clientWidth"], got               # no horizontal scrolling at 1366 px
    assert got["rightmost"] <= got["clientWidth"] + 1, got["rightmost"]  # nothing drawn past the right edge
    assert "..." not in got["text"] and "Problem 1 solved: proved" in got["text"]
    assert got["narrow"] == [], got["narrow"]                          # no column narrower than its longest word
    raw = sorted(label for label in LABELS if ":" not in label and re.search(r"[a-z][A-Z]", label)
                 and re.search(rf"\b{re.escape(label)}\b", got["text"]))
    assert raw == [], raw                                              # the paper's numbers, never its LaTeX labels
    # and a screenshot, for a person to look at: the page's width, not blank
    shot = tmp_path / "page.png"
    proc = _browser(exe, tmp_path, f"--window-size={LAPTOP},2400", f"--screenshot={shot}", path.as_uri())
    assert shot.exists(), proc.stderr[-2000:]
    img = mpimg.imread(shot)
    assert img.shape[1] == LAPTOP and np.std(img[..., :3]) > 0.05
