"""The habits that keep the code base clean run with the tests (and so in CI): ruff lint
on src/ and tests/, ruff's formatter on src/, mypy on src/.  The configuration is in
pyproject.toml ([tool.ruff], [tool.mypy])."""
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _tool(name: str) -> str:
    exe = shutil.which(name) or str(Path(sys.executable).parent / name)
    if not Path(exe).exists():
        pytest.fail(f"{name} is part of the test extras (pip install -e '.[test]')")
    return exe


def _run(*cmd: str) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)


def test_ruff_lint_is_clean():
    run = _run(_tool("ruff"), "check", "--no-cache", "src", "tests")
    assert run.returncode == 0, run.stdout[-6000:] + run.stderr[-2000:]


def test_ruff_format_is_clean():
    run = _run(_tool("ruff"), "format", "--check", "--no-cache", "src")
    assert run.returncode == 0, run.stdout[-6000:] + run.stderr[-2000:]


def test_mypy_is_clean():
    run = _run(_tool("mypy"))
    assert run.returncode == 0, run.stdout[-8000:] + run.stderr[-2000:]
