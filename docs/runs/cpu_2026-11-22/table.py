"""Combined validation table of the run's `xyzcyl eval` reports (docs/results.md).

    .venv/bin/python docs/runs/cpu_2026-11-22/table.py runs/cpu1/eval > docs/runs/cpu_2026-11-22/table.md
"""

import json
import sys
from pathlib import Path

from xyzcyl.model_export.evaluate import summary_markdown

ORDER = ["model", "model-gt-occupancy", "model-no-volume-branch", "model-no-pixel-branch",
         "model-no-separate-background", "unproject", "unproject-gt-depth"]

folder = Path(sys.argv[1])
reports = {p.stem.split("_")[0]: json.loads(p.read_text()) for p in sorted(folder.glob("*.json"))}
print(summary_markdown([reports[k] for k in ORDER if k in reports] +
                       [v for k, v in reports.items() if k not in ORDER]), end="")
