"""Build hook: the figures a page's own code draws, and the check that the built site holds them.

A page's Python block (run by markdown-exec with ``html="true"``) draws a matplotlib figure and
prints ``html_figure(fig, alt)`` in a line the reader does not see (``# markdown-exec: hide``):
the figure goes into the page as an inline PNG, so the site needs no image files and every figure
is the one that run drew. After the build, each page must hold at least as many figures as its
blocks promise (calls of ``html_figure``): a block that printed none fails the build.
MkDocs is imported only inside the hooks, so that ``tests/test_docs.py`` checks this module
without the ``docs`` extra.
"""

import base64
import contextlib
import html
import io
import re
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
#: A figure a page's source promises: a hidden call of :func:`html_figure`.
PROMISE = re.compile(r"^\s*print\(html_figure\(.*#\s*markdown-exec:\s*hide\s*$", flags=re.MULTILINE)
#: A figure the built page holds, or the note that stands for it when the data it needs are not here.
FIGURE = re.compile(r'<img [^>]*src="data:image/png;base64,|<div class="symsbl-figure-skipped">')
#: The examples, which the gallery's pages run and import from.
EXAMPLES = HERE.parents[1] / "examples"
_promised: dict[str, int] = {}


def html_figure(fig, alt: str, *, dpi: int = 110) -> str:
    """``fig`` as an HTML figure holding an inline PNG, with the text ``alt`` for readers who cannot see it."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi, bbox_inches="tight")
    data = base64.b64encode(buffer.getvalue()).decode("ascii")
    return f'<figure class="symsbl-figure"><img alt="{html.escape(alt)}" src="data:image/png;base64,{data}"></figure>'


def html_skipped(reason: str) -> str:
    """What a page shows instead of a figure whose data are missing (a data set not next to the repository)."""
    return f'<div class="symsbl-figure-skipped"><p><em>{html.escape(reason)}</em></p></div>'


def html_text(text: str) -> str:
    """Printed text as a block of program output."""
    return f'<div class="language-text highlight"><pre><code>{html.escape(text.rstrip())}</code></pre></div>'


def printed(fn, *args, **kwargs):
    """``fn(*args, **kwargs)`` and what it printed: an example's own ``print`` is not a page's."""
    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer):
        result = fn(*args, **kwargs)
    return result, buffer.getvalue()


def promised(markdown: str) -> int:
    """How many figures a page's Markdown source promises."""
    return len(PROMISE.findall(markdown))


def missing_figures(promises: dict[str, int], site: Path) -> list[str]:
    """Pages of the built ``site`` (``{page url: figures promised}``) holding fewer figures than promised."""
    short = []
    for url, count in sorted(promises.items()):
        page = site / (url + "index.html" if url.endswith("/") or not url else url)
        held = len(FIGURE.findall(page.read_text())) if page.is_file() else 0
        if held < count:
            short.append(f"{url or 'index'}: {held} of {count} figures")
    return short


def on_config(config, **kwargs):
    """Let the pages' code import this module (``from figures import html_figure``) and the examples."""
    for folder in (HERE, EXAMPLES):
        if str(folder) not in sys.path:
            sys.path.insert(0, str(folder))
    _promised.clear()
    return config


def on_page_markdown(markdown, page, **kwargs):
    """Count the figures the page promises."""
    if count := promised(markdown):
        _promised[page.url] = count
    return markdown


def on_post_build(config, **kwargs):
    """Fail the build when a page holds fewer figures than its code promises."""
    from mkdocs.exceptions import PluginError

    short = missing_figures(_promised, Path(config["site_dir"]))
    if short:
        raise PluginError("pages without the figures their code draws: " + "; ".join(short))
