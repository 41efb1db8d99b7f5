"""Helpers shared by the benchmark scripts: the one timer, Markdown tables and the documentation page.

Every script times through :func:`timed` (one function) or :func:`timed_together` (several
competitors run in turn, so that a change of machine load hits all of them alike; use it for
ratios). The machine these run on is shared: report ratios measured in one process, with the
best of several repeats (``statistic="min"``) unless the spread itself matters.

What a script prints is also kept (standard output is copied from the moment this module is
imported), and :func:`write_page` writes it to ``docs/benchmarks/<name>.md`` with the command, the
date and the machine: the documentation's benchmark pages are the scripts' output, never numbers
pasted by hand.
"""

import contextlib
import datetime
import os
import platform
import shlex
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: Where :func:`write_page` puts the pages (each listed once under ``Benchmarks`` in ``mkdocs.yml``).
PAGES = ROOT / "docs" / "benchmarks"
#: The first line of every written page; ``tests/test_docs.py`` checks that each page carries it.
MARKER = "<!-- Written by a bench/ script through bench/_report.py: run its command to refresh; do not edit. -->"
_START = time.perf_counter()
#: Titles printed by :func:`table`, which become headings on the page.
_TITLES = set()


class _Copy:
    """Standard output that also keeps what passes through it, for :func:`write_page`."""

    def __init__(self, stream):
        self.stream, self.kept = stream, []

    def write(self, text):
        self.kept.append(text)
        return self.stream.write(text)

    def __getattr__(self, name):
        return getattr(self.stream, name)


if not isinstance(sys.stdout, _Copy):
    sys.stdout = _Copy(sys.stdout)

_STATISTICS = {"min": min, "median": statistics.median}


def timed(fn, repeats=3, *, warmup=False, statistic="min"):
    """Run ``fn`` ``repeats`` times; return its last result and the best (or median) wall time (s).

    ``warmup`` runs it once more first, untimed (page faults, JIT compilation, caches)."""
    if warmup:
        fn()
    out, times = None, []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, _STATISTICS[statistic](times)


def timed_together(fns, repeats=5, *, warmup=True, statistic="min"):
    """Time several competitors in turn, round-robin; return ``{name: (last result, seconds)}``.

    ``fns`` maps names to zero-argument callables. Interleaving makes ratios robust to the
    load of a shared machine changing during the run."""
    if warmup:
        for fn in fns.values():
            fn()
    out = {name: None for name in fns}
    times = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            out[name] = fn()
            times[name].append(time.perf_counter() - t0)
    return {name: (out[name], _STATISTICS[statistic](times[name])) for name in fns}


def table(title, header, rows):
    """Print ``rows`` as a Markdown table under ``title`` (a heading on the documentation page)."""
    _TITLES.add(title.strip())

    def cells(values):  # a "|" inside a cell (x|x|) is escaped, or it would split the cell
        return "| " + " | ".join(str(c).replace("|", "\\|") for c in values) + " |"

    print(f"\n{title}\n")
    print(cells(header))
    print("|" + "|".join("---" for _ in header) + "|")
    for r in rows:
        print(cells(r))


def one_blas_thread():
    """A context limiting every BLAS library in the process to one thread (the setting of the
    README's figures). numpy and scipy each ship their own OpenBLAS; on a machine with few
    cores, code that alternates between them (pysindy, scikit-learn) can run 50x slower with
    their default threads, as each library's idle threads spin while the other works.
    Without threadpoolctl (installed with scikit-learn) it does nothing."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api="blas")


def _machine():
    cpu = platform.processor() or platform.machine()
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    versions = [
        f"{name} {getattr(sys.modules[name], '__version__', '?')}"
        for name in ("symsbl", "casadi", "numpy", "scipy")
        if name in sys.modules
    ]
    load = f", load average {os.getloadavg()[0]:.1f}" if hasattr(os, "getloadavg") else ""
    return (
        f"{platform.system()} {platform.release()}, {cpu}, {os.cpu_count()} CPUs{load}; "
        f"Python {platform.python_version()}" + "".join(f", {v}" for v in versions)
    )


def _markdown(lines):
    """The printed lines as Markdown: tables stay tables, :func:`table` titles become headings,
    everything else is kept verbatim in text blocks."""
    blocks, text = [], []

    def close_text():
        if text:
            blocks.append("```text\n" + "\n".join(text) + "\n```")
            text.clear()

    for line in lines:
        stripped = line.strip()
        if stripped.startswith("|"):
            close_text()
            row = stripped.replace("*", "\\*")  # x1**3 is a term, not emphasis
            if blocks and blocks[-1].startswith("|"):
                blocks[-1] += "\n" + row
            else:
                blocks.append(row)
        elif stripped in _TITLES:
            close_text()
            blocks.append(f"### {stripped}")
        elif stripped:
            text.append(line.rstrip())
        else:
            close_text()
    close_text()
    return blocks


def write_page(name, doc):
    """Write ``docs/benchmarks/<name>.md`` from what this run printed; return its path.

    The page holds the title (the first paragraph of ``doc``, the script's docstring), the command
    that produced it, the date, the machine and the run time, the rest of ``doc`` (the setup), then
    the printed output. A script with parts writes one page per part (``"discrepancy-detection"``).
    A new page is listed once under ``Benchmarks`` in ``mkdocs.yml``."""
    title, _, setup = doc.strip().partition("\n\n")
    script = Path(sys.argv[0]).resolve()
    with contextlib.suppress(ValueError):
        script = script.relative_to(ROOT)
    command = shlex.join(["python", str(script), *sys.argv[1:]])
    elapsed = time.perf_counter() - _START
    facts = {
        "command": f"`{command}`",
        "date": datetime.date.today().isoformat(),
        "machine": _machine(),
        "run time": f"{elapsed:.0f} s" if elapsed < 600 else f"{elapsed / 60:.0f} min",
    }
    printed = "".join(sys.stdout.kept).splitlines() if isinstance(sys.stdout, _Copy) else []
    parts = [
        MARKER,
        "# " + " ".join(title.split()).rstrip("."),
        "\n".join(f"- **{k}**: {v}" for k, v in facts.items()),
        setup.strip(),
        "## Results",
        *_markdown(printed),
    ]
    PAGES.mkdir(parents=True, exist_ok=True)
    path = PAGES / f"{name}.md"
    path.write_text("\n\n".join(p for p in parts if p) + "\n")
    print(f"\nwrote {path.relative_to(ROOT)}")
    return path
