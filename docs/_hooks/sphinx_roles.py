"""Build hook: Sphinx roles in the numpydoc docstrings become links in the API reference.

The docstrings are read by Sphinx users and IDEs too, so they keep ``:func:`symsbl.refine```;
mkdocstrings renders that as the text ``:func:`` before a code span. This hook turns each such
span into a cross-reference that mkdocs-autorefs resolves when the target is documented (a
private path such as ``symsbl._model.IdentifiedModel`` falls back to the public
``symsbl.IdentifiedModel``) and leaves as plain code otherwise.
"""

import re

_ROLE = re.compile(r":(?:py:)?(?:func|class|meth|mod|attr|data|obj|exc|const|math):<code>(~?)([^<]+)</code>")


def _link(match: re.Match) -> str:
    short, target = match[1] == "~", match[2].strip()
    target = target[:-2] if target.endswith("()") else target
    title = target.rsplit(".", 1)[-1] if short else target
    if not target.startswith("symsbl"):
        return f"<code>{title}</code>"
    public = "symsbl." + target.rsplit(".", 1)[-1]
    return f'<autoref identifier="{target}" slug="{public}" optional><code>{title}</code></autoref>'


def on_page_content(html, **kwargs):
    """Replace ``:role:`target``` spans in a rendered page by optional cross-references."""
    return _ROLE.sub(_link, html)
