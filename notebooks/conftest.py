"""The notebooks run in the test run (nbmake) with `JAXDYN_QUICK` set: they read it to run
fewer and shorter experiments (fewer refits, a coarser loss landscape, shorter horizons) with
the same code, so that every cell is executed at a fraction of the cost. Their committed
outputs come from full runs (without the variable). Their kernels inherit the environment,
and with it the test run's XLA settings (tests/compile_settings.py)."""

import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(__file__), os.pardir, "tests"))
from compile_settings import compile_fast  # noqa: E402

compile_fast()
os.environ.setdefault("JAXDYN_QUICK", "1")
