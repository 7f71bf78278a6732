"""Static checks in the test run: pyright over the package (configured in pyproject.toml:
basic mode, Python 3.10), which ships py.typed, so that its public API type-checks."""

import pathlib
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parent.parent


def test_pyright_finds_nothing():
    check = subprocess.run([sys.executable, "-m", "pyright"], cwd=ROOT, capture_output=True,
                           text=True, timeout=600)
    assert check.returncode == 0, check.stdout + check.stderr
