"""Probe (issue 10, docs/results.md "Cars beside the ego"): does the depth head learn more when it trains alone?
In stage 2 its log-L1 stays flat (0.24-0.28 over 1,200 steps, log.csv `depth_head`): at weight 0.1 under the global
gradient clip the render loss dominates. Here only `depth_head` trains (everything else frozen, no rendering), on
the depth-head log-L1 (train.depth_head_loss) of the input cameras, with the checkpoint's own data augmentation.
The result is written as a stage-2 checkpoint with the new depth head, to export and measure like any other.
    .venv/bin/python docs/runs/cpu_2026-11-25_near/depth_only.py CKPT OUT.pt --data DIR [--data DIR] \
        [--steps 600] [--lr 1e-3] [--seed 5]"""
import argparse
import csv
import time
from pathlib import Path

import torch
from tqdm import tqdm
from xyzcyl.model_export.config import ModelConfig
from xyzcyl.model_export.dataset import SceneDataset
from xyzcyl.model_export.train import TrainConfig, _resize, build_model, depth_head_loss, load_checkpoint

ap = argparse.ArgumentParser()
ap.add_argument("checkpoint", type=Path)
ap.add_argument("out", type=Path)
ap.add_argument("--data", type=Path, action="append", required=True)
ap.add_argument("--steps", type=int, default=600)
ap.add_argument("--lr", type=float, default=1e-3)
ap.add_argument("--seed", type=int, default=5)
ap.add_argument("--threads", type=int, default=1)
args = ap.parse_args()
torch.set_num_threads(args.threads)
torch.manual_seed(args.seed)
ck = load_checkpoint(args.checkpoint)
cfg = ModelConfig.from_dict(ck["model_cfg"])
model = build_model(cfg)
model.load_state_dict(ck["model"])
model.eval()   # frozen modules keep their statistics; the depth head has no normalisation
for n, p in model.named_parameters():
    p.requires_grad_(n.startswith("depth_head."))
params = [p for p in model.parameters() if p.requires_grad]
opt = torch.optim.AdamW(params, lr=args.lr, weight_decay=1e-4)
sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=args.lr, total_steps=args.steps, pct_start=0.05)
tcfg = TrainConfig.from_dict(ck["train_cfg"])
ds = SceneDataset(args.data, tcfg.data, model_cfg=cfg)
log = args.out.with_suffix(".csv")
rows = []
order = torch.randperm(len(ds), generator=torch.Generator().manual_seed(args.seed)).tolist()
t0 = time.time()
for step in tqdm(range(args.steps), desc="depth head", unit="step"):
    i = order[step % len(order)]
    item = ds.item(i, step // len(order))
    images = _resize(item["images"], cfg)
    with torch.no_grad():
        feats = model.backbone(images)
    d, _ = model.depth_head(feats, focal=item["lifting"].get("focal_n"))
    loss = depth_head_loss(d, item["depth"], item["depth_valid"], item["sky"])
    opt.zero_grad()
    loss.backward()
    torch.nn.utils.clip_grad_norm_(params, 1.0)
    opt.step()
    sched.step()
    rows.append({"step": step + 1, "scene": ds.scenes[i].name, "depth_head": float(loss), "wall_s": time.time() - t0})
with log.open("w", newline="") as f:
    w = csv.DictWriter(f, fieldnames=list(rows[0]))
    w.writeheader()
    w.writerows(rows)
ck["model"] = {k: v.detach().clone() for k, v in model.state_dict().items()}
ck["depth_only"] = {"from": str(args.checkpoint), "data": [str(d) for d in args.data], "steps": args.steps,
                    "lr": args.lr, "seed": args.seed}
ck.pop("optimizer", None)
ck.pop("scheduler", None)
torch.save(ck, args.out)
n = max(1, len(rows) // 10)
print(f"depth-head log-L1: first {sum(r['depth_head'] for r in rows[:n]) / n:.4f}, "
      f"last {sum(r['depth_head'] for r in rows[-n:]) / n:.4f}; wrote {args.out} and {log}")
