"""The notebooks run in the test run (nbmake) with `JAXDYN_QUICK` set: they read it to run
fewer and shorter experiments (fewer refits, a coarser loss landscape, shorter horizons) with
the same code, so that every cell is executed at a fraction of the cost. Their committed
outputs come from full runs (without the variable)."""

import os

os.environ.setdefault("JAXDYN_QUICK", "1")
