"""Print the Markdown table of each Monte Carlo metrics file given (docs/montecarlo.md).

    python scripts/mc_tables.py results/mc_stress_metrics.json [...]

Each table is preceded by a line naming the scenario, trials, data sets and seed, so a table
in the docs is pasted from a result file, never typed.
"""

from __future__ import annotations

import json
import sys

from safestab.montecarlo.report import markdown_table


def main(paths: list[str]) -> None:
    """Print the table of each metrics file in ``paths``."""
    for path in paths:
        with open(path) as fh:
            doc = json.load(fh)
        s = doc["settings"]
        print(
            f"**{doc['scenario']}** ({s['trials']} trials, {s['datasets']} data sets, seed "
            f"{s['seed']}; from {path})\n"
        )
        print(markdown_table(doc))


if __name__ == "__main__":
    main(sys.argv[1:])
