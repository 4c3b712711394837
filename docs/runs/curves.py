"""Stage-2 training curves of a run's models in one figure (docs/results.md).

    .venv/bin/python docs/runs/curves.py OUT.png "full model=runs/cpu1/render_none" "no volume=runs/cpu1/render_no-volume"

Each argument after OUT.png is LABEL=RUN_DIR (its log.csv); missing logs are skipped.
"""

import csv
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

TERMS = [("loss", "weighted total"), ("l1", "image L1"), ("sky", "sky-alpha L1"), ("pearson", "1 - depth PCC")]


def ema(y: np.ndarray, k: float = 0.95) -> np.ndarray:
    out, acc = np.empty_like(y), y[0]
    for i, v in enumerate(y):
        acc = k * acc + (1 - k) * v
        out[i] = acc
    return out


dest = Path(sys.argv[1])
RUNS = dict(a.split("=", 1) for a in sys.argv[2:])
fig, axes = plt.subplots(1, len(TERMS), figsize=(16, 3.8), dpi=90)
for label, sub in RUNS.items():
    path = Path(sub) / "log.csv"
    if not path.is_file():
        continue
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    step = np.array([float(r["step"]) for r in rows])
    for ax, (key, title) in zip(axes, TERMS):
        ax.plot(step, ema(np.array([float(r[key]) for r in rows])), label=label, lw=1.3)
        ax.set_title(title)
        ax.set_xlabel("step")
        ax.grid(alpha=0.3)
axes[0].legend(fontsize=8)
fig.suptitle("stage 2 (render), training losses (one scene per step, EMA 0.95), unweighted terms beside the weighted total", fontsize=10)
fig.tight_layout()
fig.savefig(dest)
