"""Where the element-wise (straight-line scalar) evaluation of the equations stops paying: every
multibody system of the test suite simulated with jaxdyn's threshold on the unrolled program's
size (`jaxdyn._unroll.MAX_ELEMENTS`, default 2000 scalar operations) and with a higher one.

Run: python benchmarks/bench_unroll_threshold.py [threshold ...]   (default: 2000 10000;
about 6 minutes; one process per threshold, so that every first call compiles afresh)

Per system and formulation: the first `simulate` (compile included) and a repeated one, Tsit5
at rtol = atol = 1e-8 over 0.5 s from the suite's first state. Systems whose unrolled program
exceeds the threshold run as written (array operations); where those arrays are 3-vectors and
3 × 3 rotations, each operation is a kernel launch on a few numbers.
"""

import os
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))


def measure(threshold):
    sys.path.insert(0, os.path.join(HERE, "..", "tests"))
    import conftest  # noqa: F401  (float64, strict promotion: as the tests run)
    import jaxdyn._unroll as unroll
    from multibody_systems import SYSTEMS
    from test_multibody import formulations

    import jaxdyn

    unroll.MAX_ELEMENTS = threshold
    for name, ref in SYSTEMS.items():
        for label, dynamics in formulations(name).items():
            q0, u0 = ref.states[0]
            kw = dict(t1=0.5, rtol=1e-8, atol=1e-8)
            start = time.perf_counter()
            jaxdyn.simulate(dynamics, q0, u0, ref.params, **kw)
            first = time.perf_counter() - start
            start = time.perf_counter()
            for _ in range(5):
                jaxdyn.simulate(dynamics, q0, u0, ref.params, **kw)
            print(f"{name}\t{label}\t{first:.2f}\t{(time.perf_counter() - start) / 5 * 1e3:.3f}",
                  flush=True)


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--one":
        measure(int(sys.argv[2]))
        sys.exit()
    thresholds = [int(x) for x in sys.argv[1:]] or [2000, 10000]
    rows = {}
    for threshold in thresholds:
        out = subprocess.run([sys.executable, __file__, "--one", str(threshold)], check=True,
                             capture_output=True, text=True).stdout
        for line in out.splitlines():
            name, label, first, run = line.split("\t")
            rows.setdefault((name, label), []).append((float(first), float(run)))
    header = " | ".join(f"first / run at {t}" for t in thresholds)
    print(f"| system | formulation | {header} |")
    print("|---|---|" + "---|" * len(thresholds))
    for (name, label), cells in rows.items():
        print(f"| {name} | {label} | " + " | ".join(f"{f:.1f} s / {r:.2f} ms" for f, r in cells)
              + " |")
