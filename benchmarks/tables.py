"""Rewrite the tables of the README, the guides and benchmarks/README.md from the results the
benchmark scripts recorded (`benchmarks/results/*.csv`, written by a script run with
`--record`): every region between `<!-- results: NAME -->` and `<!-- /results -->`.

Run: python benchmarks/tables.py            (rewrite the pages)
     python benchmarks/tables.py --check    (exit 1 where a page and its results disagree)
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from _results import PAGES, regenerated  # noqa: E402

ROOT = Path(__file__).parent.parent


def main():
    check = "--check" in sys.argv
    stale = []
    for page in PAGES:
        path = ROOT / page
        text = path.read_text()
        new = regenerated(text)
        if new != text:
            stale.append(page)
            if not check:
                path.write_text(new)
    verb = "disagree with their results" if check else "rewritten"
    print(f"{len(stale)} pages {verb}: {', '.join(stale) or 'none'}")
    sys.exit(1 if check and stale else 0)


if __name__ == "__main__":
    main()
