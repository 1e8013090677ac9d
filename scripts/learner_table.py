"""Write the table of learners into every docs page that marks its place (``learners.catalog``).

Usage: ``python scripts/learner_table.py`` rewrites the marked tables; ``--check`` writes nothing
and exits 1, naming the pages whose table differs from the learners of ``conf/learner/``.
"""

from __future__ import annotations

import sys
from pathlib import Path

from mrta_rl.learners.catalog import TABLE_START, learner_table, with_learner_table
from mrta_rl.runners import cli

DOCS = Path(__file__).resolve().parents[1] / "docs"


def main() -> None:
    table = learner_table()
    stale = []
    for page in sorted(DOCS.rglob("*.md")):
        text = page.read_text()
        if TABLE_START in text and (new := with_learner_table(text, table)) != text:
            stale.append(str(page.relative_to(DOCS.parent)))
            if "--check" not in sys.argv[1:]:
                page.write_text(new)
    if stale and "--check" in sys.argv[1:]:
        print(
            f"error: stale table of learners in {', '.join(stale)}: python {__file__}",
            file=sys.stderr,
        )
        sys.exit(1)
    print("\n".join(f"wrote {p}" for p in stale) or "the tables of learners are current")


if __name__ == "__main__":
    cli.run(main)
