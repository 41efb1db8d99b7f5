"""Build hook: a benchmark page's title is its own first heading.

``bench/_report.write_page`` puts a comment line first on every page it writes (the mark
``tests/test_docs.py`` checks); MkDocs takes a page's title from its heading only when the heading
comes first, so the comment is dropped from what MkDocs renders.
"""

MARKER = "<!-- Written by a bench/ script through bench/_report.py"


def on_page_markdown(markdown, page, **kwargs):
    """Drop the writer's mark that precedes a benchmark page's heading."""
    if markdown.startswith(MARKER):
        markdown = markdown.split("\n", 1)[1].lstrip("\n")
    return markdown
