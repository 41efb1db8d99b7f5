"""Build hook: MathJax served with the site, so that its equations typeset offline.

``pymdownx.arithmatex`` (generic mode) leaves each ``$...$`` and ``$$...$$`` of a page as TeX in
an ``arithmatex`` element; MathJax typesets those in the browser. Its script and fonts come from
the ``django-static-mathjax`` package of the ``docs`` extra (MathJax 3, as static files) and are
copied into the site under ``assets/mathjax/``: no page loads anything from another server.
After the build, a page with mathematics must hold the configuration and the script.
MkDocs is imported only inside the hooks, so that ``tests/test_docs.py`` checks this module
without the ``docs`` extra.
"""

import re
from pathlib import Path

#: Where the site serves MathJax from (``extra_javascript`` in ``mkdocs.yml`` names the script).
TARGET = "assets/mathjax"
#: The script, and the fonts it loads from ``output/chtml/fonts/woff-v2`` beside itself.
SCRIPT = "tex-chtml.js"
FONTS = "output/chtml/fonts/woff-v2"
MATH = re.compile(r'class="arithmatex"')
#: Mathematics in a page's Markdown (``$...$`` or ``$$``), once fenced blocks and code spans are removed.
WRITTEN = re.compile(r"\$\$|\$[^\s$][^$\n]*?[^\s$\\]\$")
_pages_with_math: set[str] = set()
_pages_writing_math: set[str] = set()


def writes_math(markdown: str) -> bool:
    """Whether a page's Markdown holds mathematics for arithmatex (outside code)."""
    prose = re.sub(r"^```.*?^```", "", markdown, flags=re.M | re.S)
    prose = re.sub(r"`[^`\n]*`", "", prose)
    return bool(WRITTEN.search(prose))


def source() -> Path:
    """The folder of MathJax's ES5 build in the installed package."""
    from mkdocs.exceptions import PluginError

    try:
        import mathjax
    except ImportError as error:
        raise PluginError('MathJax is not installed: pip install ".[docs]" (django-static-mathjax)') from error
    return Path(mathjax.__file__).resolve().parent / "static" / "mathjax" / "es5"


def on_files(files, config, **kwargs):
    """Add MathJax's script and fonts to the site's files."""
    from mkdocs.structure.files import File

    es5 = source()
    for path in [es5 / SCRIPT, *sorted((es5 / FONTS).glob("*.woff"))]:
        uri = f"{TARGET}/{path.relative_to(es5).as_posix()}"
        files.append(File.generated(config, uri, abs_src_path=str(path)))
    _pages_with_math.clear()
    _pages_writing_math.clear()
    return files


def on_page_markdown(markdown, page, **kwargs):
    """Note the pages whose Markdown holds mathematics."""
    if writes_math(markdown):
        _pages_writing_math.add(page.url)
    return markdown


def on_page_content(html, page, **kwargs):
    """Note the pages that hold mathematics."""
    if MATH.search(html):
        _pages_with_math.add(page.url)
    return html


def untypeset(pages: set[str], site: Path, written: set[str] = frozenset()) -> list[str]:
    """Pages of the built ``site`` with mathematics but not the MathJax configuration and script, and pages
    whose Markdown wrote mathematics (``written``) that the built page does not mark for MathJax."""
    if not (site / TARGET / SCRIPT).is_file():
        return [f"{TARGET}/{SCRIPT} is missing from the site"]
    bad = []
    for url in sorted(pages | written):
        page = site / (url + "index.html" if url.endswith("/") or not url else url)
        text = page.read_text() if page.is_file() else ""
        if f"{TARGET}/{SCRIPT}" not in text or "mathjax.js" not in text or not MATH.search(text):
            bad.append(url or "index")
    return bad


def on_post_build(config, **kwargs):
    """Fail the build when a page's mathematics could not be typeset offline."""
    from mkdocs.exceptions import PluginError

    bad = untypeset(_pages_with_math, Path(config["site_dir"]), _pages_writing_math)
    if bad:
        raise PluginError("mathematics that would not typeset: " + "; ".join(bad))
