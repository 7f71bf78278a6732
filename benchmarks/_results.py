"""One source for every published figure: the benchmark scripts write their results here, and
the tables of the docs are generated from them.

A script run with `--record` writes `benchmarks/results/<name>.csv`: a header of `# key: value`
lines (the date, the machine, JAX's version and the exact command) and one row per figure
(row, system, value, unit, target, met). `python benchmarks/tables.py` rewrites every region

    <!-- results: NAME -->
    ...
    <!-- /results -->

of the README, the guides and benchmarks/README.md as the table of `results/NAME.csv`, and
tests/test_docs.py fails when a published table and its results disagree.
"""

import csv
import datetime
import io
import os
import platform
import re
import sys
from pathlib import Path

RESULTS = Path(__file__).parent / "results"
FIELDS = ("row", "system", "value", "unit", "target", "met")
REGION = re.compile(r"(<!-- results: (?P<name>[\w-]+) -->\n)(?P<body>.*?)(<!-- /results -->)",
                    re.S)


def machine() -> str:
    """This machine in a few words: CPU model (or architecture), cores, OS."""
    model = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as info:
            names = [line.split(":", 1)[1].strip() for line in info
                     if line.startswith("model name")]
        model = names[0] if names else model
    except OSError:
        pass
    return f"{model}, {os.cpu_count()} cores, {platform.system()}"


class Recorder:
    """The figures of one run of a benchmark script, written to `results/<name>.csv` by
    `write()` when the script was run with `--record`."""

    def __init__(self, name: str):
        self.name = name
        self.rows: list[dict] = []

    def add(self, row: str, system: str, value: float, unit: str = "×",
            target: float | None = None):
        """One figure: a ratio to its baseline (unit "×"), or a time ("s", "µs"); `target`
        the most it may be."""
        met = "" if target is None else ("yes" if value <= target else "no")
        self.rows.append(dict(row=row, system=system, value=f"{value:.3g}", unit=unit,
                              target="" if target is None else f"{target:g}", met=met))

    def write(self, path: Path | None = None) -> Path:
        import jax

        path = RESULTS / f"{self.name}.csv" if path is None else path
        path.parent.mkdir(exist_ok=True)
        command = "python " + " ".join(
            [os.path.relpath(sys.argv[0], Path(__file__).parent.parent), *sys.argv[1:]])
        with open(path, "w", newline="") as out:
            out.write(f"# date: {datetime.date.today().isoformat()}\n")
            out.write(f"# machine: {machine()}\n")
            out.write(f"# jax: {jax.__version__}, {jax.devices()[0].platform}, float64\n")
            out.write(f"# command: {command}\n")
            writer = csv.DictWriter(out, FIELDS)
            writer.writeheader()
            writer.writerows(self.rows)
        print(f"results written to {path}")
        return path


def read(name: str) -> tuple[dict, list[dict]]:
    """(the header's `key: value` pairs, the rows) of `results/<name>.csv`."""
    text = (RESULTS / f"{name}.csv").read_text()
    meta = dict(line[2:].split(": ", 1) for line in text.splitlines() if line.startswith("# "))
    body = "\n".join(line for line in text.splitlines() if not line.startswith("# "))
    return meta, list(csv.DictReader(io.StringIO(body)))


def table(name: str) -> str:
    """The Markdown table of `results/<name>.csv`, with the date, machine and command: one row
    per figure, one column per system (✗ marks a figure above its target)."""
    meta, rows = read(name)
    systems = list(dict.fromkeys(r["system"] for r in rows))
    figures: dict[str, dict] = {}
    for r in rows:
        figure = figures.setdefault(r["row"], {"target": _with_unit(r["target"], r["unit"])})
        figure[r["system"]] = _with_unit(r["value"], r["unit"]) + (
            " ✗" if r["met"] == "no" else "")
    columns = [s or "value" for s in systems]
    lines = [f"*{meta['date']}, {meta['machine']}, jax {meta['jax']}: "
             f"`{meta['command']}`*", "",
             "| figure | target | " + " | ".join(columns) + " |",
             "| --- | --- | " + " | ".join("---" for _ in columns) + " |"]
    for row, cells in figures.items():
        target = f"≤ {cells['target']}" if cells["target"] else ""
        lines.append(f"| {row} | {target} | "
                     + " | ".join(cells.get(system, "") for system in systems) + " |")
    return "\n".join(lines) + "\n"


def _with_unit(value: str, unit: str) -> str:
    if not value:
        return ""
    return f"{value}{unit}" if unit == "×" else f"{value} {unit}"


def regenerated(text: str) -> str:
    """`text` with every results region replaced by its table."""
    return REGION.sub(lambda m: m.group(1) + table(m.group("name")) + m.group(4), text)


# The pages whose tables are generated here.
PAGES = ("README.md", "benchmarks/README.md", "docs/guides/speed.md", "docs/guides/trees.md",
         "docs/guides/identification.md")
