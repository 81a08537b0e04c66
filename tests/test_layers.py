"""The package layers import only downward (the contract is in pyproject.toml,
[tool.importlinter]): model -> measurement -> problem -> solve -> analysis -> outputs -> cli,
with volcal.base below everything."""
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_layers_import_only_downward():
    exe = shutil.which("lint-imports") or str(Path(sys.executable).parent / "lint-imports")
    if not Path(exe).exists():
        pytest.fail("import-linter is part of the test extras (pip install -e '.[test]')")
    run = subprocess.run([exe, "--no-cache"], cwd=ROOT, capture_output=True, text=True)
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-2000:]
    assert "0 broken" in run.stdout


def test_no_python_callback_in_the_numerics():
    """No ca.Callback anywhere in src/: every CasADi Function can be expanded, serialised
    and code-generated."""
    hits = [str(p.relative_to(ROOT)) for p in (ROOT / "src").rglob("*.py")
            if "ca.Callback" in p.read_text() or "casadi.Callback" in p.read_text()]
    assert not hits, hits

