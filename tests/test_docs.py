"""The documentation site's structure, checked without building it (CI builds it with ``mkdocs build --strict``).

Every page is in the navigation and every navigation entry exists; every file a page includes exists;
the benchmark pages are written by the ``bench/`` scripts, not by hand; the CLI reference names every
option the commands accept; the README stays a short front door that links the site.
"""

import argparse
import re
from pathlib import Path

import pytest

from symsbl._cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
#: The line ``bench/_report.write_page`` puts first on every benchmark page.
BENCH_MARKER = "<!-- Written by a bench/ script through bench/_report.py"


def _pages():
    return sorted(p.relative_to(DOCS).as_posix() for p in DOCS.rglob("*.md") if "_hooks" not in p.parts)


def _nav():
    config = (ROOT / "mkdocs.yml").read_text()
    nav = config[config.index("\nnav:") :]
    return re.findall(r"^\s*-\s+(?:[^:\n]+:\s+)?([\w./-]+\.md)\s*$", nav, flags=re.MULTILINE)


def test_every_nav_entry_exists_and_every_page_is_in_the_nav():
    nav = _nav()
    assert nav, "no pages found in the nav of mkdocs.yml"
    assert len(nav) == len(set(nav)), sorted({p for p in nav if nav.count(p) > 1})
    missing = [p for p in nav if not (DOCS / p).is_file()]
    assert not missing, f"in the nav of mkdocs.yml but not in docs/: {missing}"
    omitted = sorted(set(_pages()) - set(nav))
    assert not omitted, f"pages not in the nav of mkdocs.yml (add them): {omitted}"


def test_the_site_has_the_divio_sections():
    nav = _nav()
    for section in ("tutorials/", "how-to/", "explanation/", "reference/", "benchmarks/"):
        assert any(p.startswith(section) for p in nav), section
    for page in (
        "index.md",
        "extending.md",
        "architecture.md",
        "changelog.md",
        "reference/cli.md",
        "reference/model-file.md",
        "reference/exit-codes.md",
    ):
        assert page in nav, page


@pytest.mark.parametrize("page", _pages())
def test_every_included_file_exists(page):
    text = (DOCS / page).read_text()
    for included in re.findall(r'^--8<--\s+"([^"]+)"', text, flags=re.MULTILINE):
        assert (ROOT / included).is_file(), f"{page} includes {included}, which does not exist"


def test_every_example_named_by_a_page_exists():
    named = {m for page in _pages() for m in re.findall(r"examples/(\w+\.py)", (DOCS / page).read_text())}
    assert named
    missing = sorted(n for n in named if not (ROOT / "examples" / n).is_file())
    assert not missing, missing


def test_benchmark_pages_are_written_by_the_bench_scripts():
    pages = [p for p in (DOCS / "benchmarks").glob("*.md") if p.name != "index.md"]
    hand_written = [p.name for p in pages if not p.read_text().startswith(BENCH_MARKER)]
    assert not hand_written, f"benchmark pages not written by bench/_report.write_page: {hand_written}"
    index = (DOCS / "benchmarks" / "index.md").read_text()
    unlisted = [p.name for p in pages if f"({p.name})" not in index]
    assert not unlisted, f"benchmark pages not linked from docs/benchmarks/index.md: {unlisted}"


def test_the_changelog_page_includes_the_changelog():
    assert '--8<-- "CHANGELOG.md"' in (DOCS / "changelog.md").read_text()
    changelog = (ROOT / "CHANGELOG.md").read_text()
    for version in ("## [Unreleased]", "## [0.2.0]", "## [0.1.0]"):
        assert version in changelog, version


def _options(parser):
    """Every option string of a parser and its subcommands: ``{command: {"--states", ...}}``."""
    found = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                found.setdefault(name, set())
                found[name] |= {o for a in sub._actions for o in a.option_strings if a.help != argparse.SUPPRESS}
    return found


def test_the_cli_reference_names_every_option_of_every_command():
    reference = (DOCS / "reference" / "cli.md").read_text()
    commands = _options(build_parser())
    assert {"identify", "validate", "discrepancy", "demo"} <= set(commands)
    missing = {
        (command, option)
        for command, options in commands.items()
        for option in options
        if f"`{option}" not in reference
    }
    assert not missing, sorted(missing)
    for command in commands:
        assert f"symsbl {command}" in reference, command


def test_the_readme_is_a_short_front_door_that_links_the_site():
    readme = (ROOT / "README.md").read_text()
    assert readme.count("\n") <= 250, (
        f"README.md has {readme.count(chr(10))} lines (at most 250: move sections to docs/)"
    )
    assert "](docs/index.md)" in readme, "README.md does not link the documentation site (docs/index.md)"
    for section in ("## Install", "## Two commands", "## Quickstart"):
        assert section in readme, section


def test_every_public_name_has_a_reference_entry():
    """The API reference documents every name of the public surface (``::: symsbl.NAME`` on some page)."""
    import symsbl

    text = "\n".join(p.read_text() for p in (DOCS / "reference").glob("*.md"))
    documented = set(re.findall(r"^::: symsbl\.(\w+)", text, flags=re.M))
    public = {n for n in symsbl.__all__ if not n.startswith("__") and n not in ("systems",)}
    assert not public - documented, sorted(public - documented)


def _hook(name):
    """A build hook of ``docs/_hooks`` as a module (they import MkDocs only inside their hooks)."""
    import importlib.util
    import sys

    if str(DOCS / "_hooks") not in sys.path:  # as the build does for the hooks it loads
        sys.path.insert(0, str(DOCS / "_hooks"))
    spec = importlib.util.spec_from_file_location(f"_docs_hook_{name}", DOCS / "_hooks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


#: Pages a reader would rather look at than read: each draws its figures when the site is built.
FIGURE_PAGES = (
    "index.md",
    "gallery/paper-systems.md",
    "gallery/displacement-only.md",
    "gallery/hidden-friction.md",
    "gallery/bouc-wen.md",
    "gallery/emps.md",
    "tutorials/identify.md",
    "tutorials/displacement-only.md",
    "tutorials/discrepancy.md",
    "tutorials/hidden-states.md",
    "how-to/uncertainty.md",
)


def _prose(text):
    """A page's Markdown without its fenced blocks."""
    return re.sub(r"^```.*?^```", "", text, flags=re.M | re.S)


@pytest.mark.parametrize("page", _pages())
def test_a_page_that_promises_a_figure_draws_one(page):
    """Listed pages, and any page with a heading about figures, hold a block that draws one."""
    text = (DOCS / page).read_text()
    heading = re.search(r"^#+ .*\bfigures?\b", _prose(text), flags=re.M | re.I)
    if page in FIGURE_PAGES or heading:
        assert _hook("figures").promised(text), f"{page} promises a figure but no block draws one"


def test_the_build_fails_when_a_page_holds_fewer_figures_than_promised(tmp_path):
    figures = _hook("figures")
    block = 'print(html_figure(fig, "a response"))  # markdown-exec: hide'
    assert figures.promised(f"```python\n{block}\n{block}\n```") == 2
    assert figures.promised('html_figure(fig, "shown to the reader")') == 0
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "index.html").write_text('<img alt="x" src="data:image/png;base64,AAAA">')
    assert figures.missing_figures({"a/": 1}, tmp_path) == []
    assert figures.missing_figures({"a/": 2, "b/": 1}, tmp_path) == ["a/: 1 of 2 figures", "b/: 0 of 1 figures"]


def test_the_build_fails_when_maths_would_not_typeset_offline(tmp_path):
    maths = _hook("offline_maths")
    assert maths.untypeset({"a/"}, tmp_path) == ["assets/mathjax/tex-chtml.js is missing from the site"]
    (tmp_path / "assets" / "mathjax").mkdir(parents=True)
    (tmp_path / "assets" / "mathjax" / "tex-chtml.js").write_text("")
    (tmp_path / "a").mkdir()
    page = '<span class="arithmatex">\\(x\\)</span><script src="../javascripts/mathjax.js"></script>'
    (tmp_path / "a" / "index.html").write_text(page)
    assert maths.untypeset({"a/"}, tmp_path) == ["a/"]
    (tmp_path / "a" / "index.html").write_text(page + '<script src="../assets/mathjax/tex-chtml.js"></script>')
    assert maths.untypeset({"a/"}, tmp_path) == []
    # a page whose Markdown writes mathematics that the build left as text (arithmatex off) fails too
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "index.html").write_text("<p>$x$</p>")
    assert maths.untypeset(set(), tmp_path, {"b/"}) == ["b/"]
    assert maths.writes_math("the evidence $\\log p$ and\n$$\nx\n$$")
    assert not maths.writes_math("costs $5 or $10, `echo $PATH $HOME`\n```bash\necho $A$B\n```")


def test_a_page_as_the_browser_shows_it_must_hold_its_figures_and_typeset_maths():
    shots = _hook("screenshots")
    built = '<img src="a.png"><span class="arithmatex">\\(x\\)</span><span class="arithmatex">\\(y\\)</span>'
    typeset = '<img src="a.png"><span class="arithmatex"><mjx-container>x</mjx-container></span>' * 2
    assert shots.problems(built, typeset) == []
    assert shots.problems(built, '<img src="a.png"><span class="arithmatex">\\(x\\)</span>') == [
        "2 equations written, 0 typeset by MathJax"
    ]
    assert shots.problems(built, typeset.replace("<img", "<p").replace("x</mjx", "<mjx-merror>x</mjx")) == [
        "1 figures built, 0 in the browser's document",
        "MathJax reports a TeX error",
    ]
    assert set(shots.PAGES) == {"front", "tutorial", "explanation", "gallery", "benchmark"}
    for page in shots.PAGES.values():  # a page's folder in the site is its Markdown file, or its folder's index
        assert (DOCS / f"{page.rstrip('/')}.md").is_file() or (DOCS / page / "index.md").is_file(), page


def test_a_browser_that_hangs_once_is_tried_again_and_one_that_always_fails_fails_the_page(monkeypatch):
    shots = _hook("screenshots")
    outputs = iter([None, "<html></html>"])
    tries = []

    def flaky(chromium, profile, *args):
        tries.append(args)
        return next(outputs)

    monkeypatch.setattr(shots, "_chromium", flaky)
    assert shots._captured("chromium", "profile", "--dump-dom", "url") == "<html></html>"
    assert len(tries) == 2
    monkeypatch.setattr(shots, "_chromium", lambda *args: None)
    assert shots._captured("chromium", "profile", "--dump-dom", "url") is None
    assert shots.ATTEMPTS == 2


def test_the_explanations_typeset_their_equations():
    maths = _hook("offline_maths")
    for page in ("explanation/sparse-bayes.md", "explanation/weak-form.md", "explanation/latent-states.md"):
        assert maths.writes_math((DOCS / page).read_text()), page


def test_every_charted_benchmark_table_is_on_its_page():
    """A benchmark page's charts are drawn from its tables: a rewritten page must keep the columns charted."""
    benchmarks = _hook("benchmarks")
    assert benchmarks.CHARTS
    for page, charts in benchmarks.CHARTS.items():
        text = (DOCS / page).read_text()
        for chart in charts:
            found = benchmarks.find_table(text, chart.header)
            assert found, f"{page}: no table starts with {chart.header!r}"
            columns, rows, _ = found
            missing = {chart.x, *chart.ys, *([chart.group] if chart.group else [])} - set(columns)
            assert not missing and rows, (page, missing)
    assert benchmarks.number("0.30 (0.51 cold)") == 0.30
    assert benchmarks.number("1e+04") == 1e4
    assert benchmarks.number("82.9 ms") == 82.9


#: What the commands print when they doubt a result: each phrase is in the package's source and is
#: explained on "What the warnings mean" (docs/how-to/warnings.md).
DOUBTS_PRINTED = (
    "the residual depends on the input",
    "the record looks closed-loop",
    "the measured input is noisy",
    "coefficients disagree beyond their errors",
    "the residual is not measurement noise the noise model describes",
    "its likelihood is doubtful here",
    "the record is hypersensitive (chaotic-like)",
    "the equation-error model stands",
    "such functions run on CasADi's virtual machine instead",
    "RVM did not converge",
    "noise model: ",
    "innovations correlated",
    "over a white noise between periods",
    "feedback to ",
    "output error doubted: ",
    "fitted on segments of at most",
    "structure chosen from the model path",
    "the chosen structure leaves",
    "indistinguishable here from",
    "latent state ",
    "the record does not tell them apart",
    "is not a column of DATA: it is identified as a latent state",
    "where output error is biased; the equation-error",
    "ambiguous between",
    "does not predict held-out records",
    "nothing missing: no effect gains more than the threshold",
    "correlated measurement noise",
    "unexplained: no candidate gains more than the threshold",
    "this record cannot tell why",
    "removed ",
    "replaced ",
)


def test_every_doubt_the_commands_print_is_explained():
    source = "\n".join(p.read_text() for p in (ROOT / "symsbl").rglob("*.py"))
    page = " ".join((DOCS / "how-to" / "warnings.md").read_text().split())
    gone = [p for p in DOUBTS_PRINTED if p not in source]
    assert not gone, f"no longer printed by symsbl (update docs/how-to/warnings.md and this list): {gone}"
    unexplained = [p for p in DOUBTS_PRINTED if p not in page]
    assert not unexplained, f"printed but not explained on docs/how-to/warnings.md: {unexplained}"


#: Public docstrings that still name a private module, in modules under edit elsewhere: point them to a public
#: name or a documentation page, then remove them from here.
PRIVATE_NAMED: dict = {}


def test_the_api_reference_names_public_objects_only():
    """The reference is generated from the public objects' docstrings: they send readers to public names."""
    import inspect

    import symsbl

    found = {}
    for name in symsbl.__all__:
        obj = getattr(symsbl, name)
        docs = [inspect.getdoc(obj) or ""]
        if inspect.isclass(obj):
            for member, value in vars(obj).items():
                if (not member.startswith("_") or member == "__init__") and (
                    inspect.isfunction(value) or isinstance(value, property | classmethod | staticmethod)
                ):
                    docs.append(inspect.getdoc(value) or "")
        private = {m for d in docs for m in re.findall(r"symsbl\._[\w.]*", d)}
        if private:
            found[name] = private
    assert found == PRIVATE_NAMED, found
