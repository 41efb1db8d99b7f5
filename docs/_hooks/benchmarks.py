"""Build hook: a benchmark page's title is its own first heading, and its tables are drawn as charts.

``bench/_report.write_page`` puts a comment line first on every page it writes (the mark
``tests/test_docs.py`` checks); MkDocs takes a page's title from its heading only when the heading
comes first, so the comment is dropped from what MkDocs renders.

The pages hold what the scripts printed, as tables. :data:`CHARTS` names, per page, the tables a
reader would rather see (time against size, a rate against the signal, error per case) by their
header row; each is drawn from the numbers in the table itself and placed under it. A table that
is no longer on its page fails the build, so a script that changes its columns changes its chart.
"""

import re
from dataclasses import dataclass

from figures import html_figure  # the build puts docs/_hooks on the path of the hooks it loads

MARKER = "<!-- Written by a bench/ script through bench/_report.py"


@dataclass(frozen=True)
class Chart:
    """One table drawn as a chart.

    ``header`` is the start of the table's header row. ``kind="line"``: the columns ``ys`` (or all
    but ``x``) against column ``x``; ``kind="barh"``: one bar per row, the value of column ``ys[0]``,
    labelled by the ``x`` column (an empty label cell repeats the one above) and the ``group`` column.
    """

    header: str
    x: str
    ys: tuple[str, ...] = ()
    kind: str = "line"
    group: str = ""
    xlabel: str = ""
    ylabel: str = ""
    log: str = ""  # "x", "y" or "xy": which axes are logarithmic
    alt: str = ""


CHARTS = {
    "benchmarks/profile.md": [
        Chart(
            "| N | reading + derivatives |",
            "N",
            ("reading + derivatives", "dictionary", "support search", "refinement", "total"),
            xlabel="samples N",
            ylabel="seconds",
            log="xy",
            alt="Seconds per stage of identify_stream against the number of samples",
        )
    ],
    "benchmarks/scale.md": [
        Chart(
            "| N | total (s) |",
            "N",
            ("total (s)", "statistics (s)", "fit (s)", "statistics, n_jobs=2 (s)"),
            xlabel="samples N",
            ylabel="seconds",
            log="xy",
            alt="Streaming identification time against the number of samples",
        ),
        Chart(
            "| N samples | rows x terms |",
            "N samples",
            ("RVM (ms)", "ARD (ms)"),
            xlabel="samples N",
            ylabel="milliseconds",
            log="xy",
            alt="RVM against ARDRegression time on the same weak-form rows",
        ),
    ],
    "benchmarks/rvm-detection.md": [
        Chart(
            "| z | None |",
            "z",
            xlabel="projected signal-to-noise ratio z of the extra term",
            ylabel="detection rate",
            alt="Detection rate of an extra term against its signal-to-noise ratio, per penalty rule",
        )
    ],
    "benchmarks/simulate.md": [
        Chart(
            "| method | time | ratio |",
            "method",
            ("time",),
            kind="barh",
            xlabel="milliseconds",
            log="x",
            alt="Simulation time per method",
        )
    ],
    "benchmarks/evaluator.md": [
        Chart(
            "| method | M | time (ms) |",
            "method",
            ("time (ms)",),
            kind="barh",
            xlabel="milliseconds",
            log="x",
            alt="Evaluation time of the dictionary per method",
        )
    ],
    "benchmarks/harder.md": [
        Chart(
            "| case | fit | support |",
            "case",
            ("held-out NRMSE",),
            kind="barh",
            group="fit",
            xlabel="held-out NRMSE (%)",
            log="x",
            alt="Held-out error of the equation error and the output error per case",
        )
    ],
}


def number(cell: str) -> float:
    """The leading number of a table cell ("0.30 (0.51 cold)", "82.9 ms", "1e+04"); NaN when there is none."""
    match = re.match(r"\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)", cell.replace("%", ""))
    return float(match[1]) if match else float("nan")


def find_table(markdown: str, header: str) -> tuple[list[str], list[list[str]], int] | None:
    """The first table whose header row starts with ``header``: its columns, rows and end (a character offset)."""
    lines = markdown.split("\n")
    for i, line in enumerate(lines):
        if line.startswith(header):
            end = i + 2
            while end < len(lines) and lines[end].startswith("|"):
                end += 1

            def cells(row):
                return [c.strip().replace("\\|", "|").replace("\\*", "*") for c in re.split(r"(?<!\\)\|", row)[1:-1]]

            offset = sum(len(x) + 1 for x in lines[:end])
            return cells(line), [cells(r) for r in lines[i + 2 : end]], offset
    return None


def draw(chart: Chart, columns: list[str], rows: list[list[str]]):
    """The chart of one table, as a matplotlib Figure (a zero on a log axis is left out)."""
    from matplotlib.figure import Figure

    col = {name: j for j, name in enumerate(columns)}
    ys = chart.ys or tuple(c for c in columns if c != chart.x)
    tall = chart.kind == "barh"
    fig = Figure(figsize=(9, 0.9 + 0.32 * len(rows)) if tall else (7, 4), layout="constrained")
    ax = fig.subplots()
    ax.set_xscale("log" if "x" in chart.log else "linear")
    ax.set_yscale("log" if "y" in chart.log else "linear")

    def values(name):
        v = [number(r[col[name]]) for r in rows]
        return [float("nan") if x == 0 and chart.log else x for x in v]

    if tall:
        labels, last = [], ""
        for r in rows:
            last = r[col[chart.x]] or last
            labels.append(f"{last} ({r[col[chart.group]]})" if chart.group else last)
        groups = [r[col[chart.group]] for r in rows] if chart.group else [""] * len(rows)
        kinds = sorted(set(groups), key=groups.index)
        at = list(range(len(rows)))[::-1]
        for g in kinds:
            ax.barh(
                [a for a, h in zip(at, groups) if h == g],
                [v for v, h in zip(values(ys[0]), groups) if h == g],
                color=f"C{kinds.index(g)}",
                label=g or None,
            )
        ax.set_yticks(at, labels, fontsize="small")
        if chart.group:
            ax.legend(fontsize="small")
    else:
        xs = [number(r[col[chart.x]]) for r in rows]
        for name in ys:
            ax.plot(xs, values(name), "o-", label=name)
        ax.legend(fontsize="small")
        ax.set_ylabel(chart.ylabel)
    ax.set_xlabel(chart.xlabel)
    ax.grid(True, alpha=0.3)
    return fig


def on_page_markdown(markdown, page, **kwargs):
    """Drop the writer's mark that precedes a benchmark page's heading; draw the page's charts."""
    if markdown.startswith(MARKER):
        markdown = markdown.split("\n", 1)[1].lstrip("\n")
    for chart in CHARTS.get(page.file.src_uri, []):
        found = find_table(markdown, chart.header)
        if found is None:
            from mkdocs.exceptions import PluginError

            raise PluginError(f"{page.file.src_uri}: no table starts with {chart.header!r} to chart")
        columns, rows, end = found
        figure = html_figure(draw(chart, columns, rows), chart.alt)
        markdown = f"{markdown[:end]}\n{figure}\n\n{markdown[end:]}"
    return markdown
