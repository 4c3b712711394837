"""The picture of docs/results.md "Real-camera depth": 1.3.1 and 1.4.0 on the real PandaSet rig (PandaSet © Scale AI
and Hesai, CC BY 4.0) with the images as posted and 1.5x as bright. Columns: the input with its LiDAR points
(coloured by depth), then the rendered depth in the same colours of 1.3.1 as posted, 1.3.1 at x1.5, 1.4.0 as
posted and 1.4.0 at x1.5. Takes the `xyzcyl lidar-eval --picture` sheets that appearance_probe.py writes:

    for m in base final; do   # base: models/xyzcyl-cpu-v1 at 1.3.1; final: norm_chain.sh's model exported
      .venv/bin/python docs/runs/cpu_2026-11-25_final/appearance_probe.py --model DIR_$m \\
          --rig ../shared/data/real/pandaset_002_00/rig.json --kinds none,exposure_1.5 --pictures runs/cpu8/pics_$m
    done
    .venv/bin/python docs/runs/cpu_2026-11-25_final/norm_picture.py runs/cpu8 OUT.jpg
"""

import sys
from pathlib import Path

import cv2
import numpy as np

HEADER = 20   # rows of the lidar-eval sheet's caption strip
root, out = Path(sys.argv[1]), sys.argv[2]
sheets = {(m, k): cv2.imread(str(root / f"pics_{m}" / f"pandaset_002_00_{k}.jpg"))
          for m in ("base", "final") for k in ("none", "exposure_1.5")}
w = sheets["base", "none"].shape[1] // 3   # input | rendered depth | error
cols = [sheets["base", "none"][:, :w]] + [sheets[m, k][:, w:2 * w] for m in ("base", "final")
                                          for k in ("none", "exposure_1.5")]
sheet = np.concatenate(cols, axis=1)
sheet[:HEADER] = 0
for i, text in enumerate(("input + LiDAR (red near, blue far)", "1.3.1 depth, as posted", "1.3.1 depth, x1.5 bright",
                          "1.4.0 depth, as posted", "1.4.0 depth, x1.5 bright")):
    cv2.putText(sheet, text, (i * w + 4, HEADER - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
small = cv2.resize(sheet, None, fx=0.6, fy=0.6, interpolation=cv2.INTER_AREA)
cv2.imwrite(out, small, [cv2.IMWRITE_JPEG_QUALITY, 85])
print(f"wrote {out} {small.shape[1]}x{small.shape[0]}")
