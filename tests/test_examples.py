"""Every script in examples/ runs to its final assertions, and the README and the docs show them."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: Runnable scripts; modules starting with "_" hold what several scripts share.
EXAMPLES = sorted(p for p in (ROOT / "examples").glob("*.py") if not p.name.startswith("_"))
#: Exit code of an example whose data are missing.
SKIPPED = 77


def test_examples_exist():
    assert EXAMPLES, f"no example scripts found in {ROOT / 'examples'}"


@pytest.mark.slow
@pytest.mark.parametrize("script", EXAMPLES, ids=[p.name for p in EXAMPLES])
def test_example_runs(script, tmp_path):
    env = dict(os.environ, MPLBACKEND="Agg", PYTHONWARNINGS="error")
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    result = subprocess.run(
        [sys.executable, str(script)], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300
    )
    if result.returncode == SKIPPED:  # the example's data are missing: say so, do not pass vacuously
        pytest.skip(result.stdout.strip().splitlines()[-1])
    assert result.returncode == 0, f"{script.name} failed:\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"


def test_readme_quickstart_is_the_example_verbatim():
    readme = (ROOT / "README.md").read_text()
    block = readme.split("## Quickstart", 1)[1].split("```python\n", 1)[1].split("```", 1)[0]
    assert block == (ROOT / "examples" / "quickstart.py").read_text()


def test_the_docs_show_every_example():
    pages = "\n".join(p.read_text() for p in (ROOT / "docs").rglob("*.md"))
    missing = [p.name for p in EXAMPLES if f'--8<-- "examples/{p.name}"' not in pages]
    assert not missing, f'examples no documentation page includes (--8<-- "examples/NAME.py"): {missing}'
