"""The release a user installs: a wheel and an sdist built from this tree install into a fresh
environment (its dependencies taken from this one) and run the README's quickstart there, away
from the source tree. Slow (a build and two installs): `python -m pytest -m slow`."""

import pathlib
import re
import subprocess
import sys
import zipfile

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent


def _run(*command, cwd=None):
    done = subprocess.run(command, cwd=cwd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, f"{command}:\n{done.stdout}\n{done.stderr}"
    return done.stdout


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["wheel", "sdist"])
def test_the_package_installs_and_runs_the_quickstart(kind, tmp_path):
    dist = tmp_path / "dist"
    if kind == "wheel":
        _run(sys.executable, "-m", "pip", "wheel", "--no-deps", "-w", str(dist), str(ROOT))
        (package,) = dist.glob("jaxdyn-*.whl")
        names = zipfile.ZipFile(package).namelist()
        assert "jaxdyn/py.typed" in names and "jaxdyn/_fit/fit.py" in names
        assert not any(name.startswith(("tests/", "notebooks/")) for name in names)
    else:
        _run(sys.executable, "-m", "build", "--sdist", "--outdir", str(dist), str(ROOT))
        (package,) = dist.glob("jaxdyn-*.tar.gz")
    env = tmp_path / "env"
    _run(sys.executable, "-m", "venv", "--system-site-packages", str(env))
    python = str(env / "bin" / "python")
    _run(python, "-m", "pip", "install", "--no-deps", str(package))
    quickstart = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S)[0]
    script = tmp_path / "quickstart.py"
    script.write_text("import jaxdyn, pathlib\n"
                      f"assert not pathlib.Path(jaxdyn.__file__).is_relative_to({str(ROOT)!r})\n"
                      + quickstart)
    out = _run(python, str(script), cwd=tmp_path)
    assert re.search(r"\d+ \d\.\d+e-\d+", out), out  # steps and the energy error
