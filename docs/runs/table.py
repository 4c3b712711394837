"""Combined validation table of a run's `xyzcyl eval` reports (docs/results.md).

    .venv/bin/python docs/runs/table.py runs/cpu1/eval > docs/runs/cpu_2026-11-22/table.md
    .venv/bin/python docs/runs/table.py runs/cpu2/eval/full "k_o 2=runs/cpu2/eval/k2" ... > table.md

Reads every report JSON in the given folders, in the order given (within a folder: the model first, then its
oracle and ablation rows in the order below, then anything else by name). LABEL=FOLDER replaces the row label
of that folder's reports (for variants the label does not tell apart, e.g. another pixel lattice).
"""

import json
import sys
from pathlib import Path

from xyzcyl.model_export.evaluate import summary_markdown

ORDER = ["model", "model-gt-occupancy", "model-no-volume-branch", "model-no-pixel-branch",
         "model-no-separate-background", "unproject", "unproject-gt-depth"]

reports = []
for arg in sys.argv[1:]:
    label, _, folder = arg.rpartition("=")
    found = {p.name.split("_")[0]: json.loads(p.read_text()) for p in sorted(Path(folder).glob("*.json"))}
    for rep in found.values():
        rep["label"] = label or rep["label"]
    reports += [found[k] for k in ORDER if k in found] + [v for k, v in found.items() if k not in ORDER]
print(summary_markdown(reports), end="")
