"""Build hook: the built site as a reader's browser shows it, photographed and checked.

After the build, five pages (the front page, a tutorial, an explanation, the gallery and a
benchmark page) are served from the site folder on a local port and opened in headless Chromium:
each is saved as a screenshot under ``screenshots/`` in the site, and its document, once its
scripts have run, must hold every figure the built page holds and, where the page has
mathematics, as many typeset equations (MathJax's ``mjx-container``) as the page has
``arithmatex`` elements, with no TeX error (``mjx-merror``). A page that fails fails the build.
Without Chromium on the path the check is skipped with one line in the build's log.
MkDocs is imported only inside the hooks, so that ``tests/test_docs.py`` checks this module
without the ``docs`` extra.
"""

import functools
import http.server
import logging
import os
import shutil
import signal
import subprocess
import tempfile
import threading
from pathlib import Path

log = logging.getLogger("mkdocs.hooks.screenshots")

#: The pages photographed: name -> path in the site.
PAGES = {
    "front": "",
    "tutorial": "tutorials/identify/",
    "explanation": "explanation/output-error/",
    "gallery": "gallery/",
    "benchmark": "benchmarks/speed/",
}
#: Chromium's flags for a closed network: no background connections, no first-run, no sandbox as root.
FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--hide-scrollbars",
    "--disable-dev-shm-usage",  # a container's small /dev/shm crashes the renderer
    "--virtual-time-budget=10000",  # the page's scripts (MathJax) run to the end before the capture
]
BROWSERS = ("chromium", "chromium-browser", "google-chrome")


def browser() -> str | None:
    """The headless browser on the path, if any."""
    return next((path for name in BROWSERS if (path := shutil.which(name))), None)


def problems(built: str, rendered: str) -> list[str]:
    """What the page as the browser rendered it lacks against the page as built (empty: nothing)."""
    found = []
    figures, shown = built.count("<img"), rendered.count("<img")
    if shown < figures:
        found.append(f"{figures} figures built, {shown} in the browser's document")
    maths, typeset = built.count('class="arithmatex"'), rendered.count("<mjx-container")
    if typeset < maths:
        found.append(f"{maths} equations written, {typeset} typeset by MathJax")
    if "<mjx-merror" in rendered:
        found.append("MathJax reports a TeX error")
    return found


def _serve(site: Path) -> http.server.ThreadingHTTPServer:
    handler = functools.partial(_Quiet, directory=str(site))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server


class _Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):  # the build's log holds the verdicts, not every request
        pass


#: Seconds one page may take in the browser.
TIMEOUT = 120
#: Captures of a page tried before it fails: headless Chromium now and then hangs on a page that it renders at
#: the next try (two builds in four on one machine, a different page each time).
ATTEMPTS = 2


def _chromium(chromium: str, profile: str, *args: str) -> str | None:
    """The browser's standard output for ``args``; None when it failed or hung (its whole process group is
    ended: a renderer left behind would hold the profile)."""
    run = subprocess.Popen(
        [chromium, *FLAGS, f"--user-data-dir={profile}", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        start_new_session=True,
    )
    try:
        out, _ = run.communicate(timeout=TIMEOUT)
    except subprocess.TimeoutExpired:
        os.killpg(run.pid, signal.SIGKILL)
        run.communicate()
        return None
    return out if run.returncode == 0 else None


def _captured(chromium: str, profile: str, *args: str) -> str | None:
    """:func:`_chromium` tried up to :data:`ATTEMPTS` times: the first output it gives, None when every try failed."""
    for _ in range(ATTEMPTS):
        out = _chromium(chromium, profile, *args)
        if out is not None:
            return out
    return None


def _check(chromium: str, profile: str, site: Path, url: str, page: str, name: str) -> list[str]:
    """What is wrong with ``page`` as the browser shows it at ``url``, its screenshot saved (empty: nothing)."""
    built = site / page / "index.html"
    if not built.is_file():
        return ["not in the built site"]
    shot = site / "screenshots" / f"{name}.png"
    shot.unlink(missing_ok=True)  # a screenshot left by an earlier build is no evidence of this one
    if _captured(chromium, profile, "--window-size=1280,1800", f"--screenshot={shot}", url) is None:
        return ["the browser failed or hung taking its screenshot"]
    rendered = _captured(chromium, profile, "--dump-dom", url)
    if rendered is None or "</html>" not in rendered:
        return ["the browser failed or hung rendering it"]
    found = problems(built.read_text(), rendered)
    if not shot.is_file() or shot.stat().st_size < 10_000:
        found.append("no screenshot taken")
    return found


def on_post_build(config, **kwargs):
    """Photograph and check :data:`PAGES` in headless Chromium (skipped without it)."""
    from mkdocs.exceptions import PluginError

    chromium = browser()
    if chromium is None:
        log.info("screenshots skipped: no Chromium on the path (%s)", ", ".join(BROWSERS))
        return
    site = Path(config["site_dir"])
    (site / "screenshots").mkdir(exist_ok=True)
    server = _serve(site)
    failed = []
    try:
        with tempfile.TemporaryDirectory(ignore_cleanup_errors=True) as profile:
            for name, page in PAGES.items():
                url = f"http://127.0.0.1:{server.server_address[1]}/{page}"
                failed += [f"{page or 'index'}: {p}" for p in _check(chromium, profile, site, url, page, name)]
    finally:
        server.shutdown()
    if failed:
        raise PluginError("pages as a browser shows them: " + "; ".join(failed))
    log.info("screenshots of %d pages in %s, figures and equations as built", len(PAGES), site / "screenshots")
