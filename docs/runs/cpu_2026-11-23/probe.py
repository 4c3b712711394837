"""Where is the colour lost? Linear probes from the frozen ImageNet EfficientNet-Lite0 features to the colour.

Fits ridge regressions (closed form, numpy) on the input cameras of TRAIN scenes and scores them (R^2) on the
input cameras of VAL scenes, at the backbone's stride-8 resolution (the colour target is the image area-pooled
to that grid, exactly what the RGB path concatenates):

- ``trunk``: the three trunk taps the backbone reads (stride 8/16/32, 40+112+320 channels, the coarser ones
  bilinearly upsampled to stride 8), as the frozen network gives them;
- ``trunk_groupnorm``: the same taps after a per-image GroupNorm (8 groups, no affine): the backbone's output
  block normalises per image like this, so what survives it is relative, not absolute, colour;
- targets: RGB, luminance Y, chroma (R - Y, B - Y), and the per-image MEAN colour (regressed from the per-image
  mean features: the white balance / exposure of a whole image).

    .venv/bin/python docs/runs/cpu_2026-11-23/probe.py data/train data/val [--train-scenes 20 --val-scenes 10]

Prints one JSON object. R^2 = 1 - SS_res / SS_tot per target channel, averaged over its channels.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch
import torch.nn.functional as F
from xyzcyl.model_export.backbone import _TAPS, EfficientLiteBackbone
from xyzcyl.model_export.config import BackboneConfig
from xyzcyl.model_export.dataset import list_scenes
from xyzcyl.runtime.rig import load_rig

LUMA = np.array([0.299, 0.587, 0.114], np.float32)


def taps(net: EfficientLiteBackbone, images: torch.Tensor) -> torch.Tensor:
    """[N, 3, H, W] 0..1 -> [N, 472, H/8, W/8]: the frozen trunk's taps at stride 8."""
    x = (images - net.mean) / net.std
    h, w = images.shape[-2] // 8, images.shape[-1] // 8
    x = net.stem(x)
    idx = {v[0]: s for s, v in _TAPS.items()}
    out = []
    for i, blk in enumerate(net.blocks):
        x = blk(x)
        if i in idx:
            out.append(F.interpolate(x, size=(h, w), mode="bilinear", align_corners=False) if x.shape[-2:] != (h, w)
                       else x)
    return torch.cat(out, 1)


def collect(root, n_scenes, net):
    feats, gfeats, cols = [], [], []
    for folder in list_scenes(root)[:n_scenes]:
        rig = load_rig(folder / "rig.json", check_images=True)
        imgs = torch.from_numpy(np.stack(rig.load_images())).permute(0, 3, 1, 2).contiguous()
        with torch.no_grad():
            f = taps(net, imgs)
            g = F.group_norm(f, 8)
            c = F.adaptive_avg_pool2d(imgs, f.shape[-2:])
        feats.append(f.permute(0, 2, 3, 1).numpy())
        gfeats.append(g.permute(0, 2, 3, 1).numpy())
        cols.append(c.permute(0, 2, 3, 1).numpy())
    return np.concatenate(feats), np.concatenate(gfeats), np.concatenate(cols)    # [I, h, w, C]


def targets(c: np.ndarray) -> dict[str, np.ndarray]:
    y = c @ LUMA
    return {"rgb": c, "luma": y[..., None], "chroma": np.stack([c[..., 0] - y, c[..., 2] - y], -1)}


def ridge(x: np.ndarray, y: np.ndarray, lam: float = 1e-3):
    mu, sd = x.mean(0), x.std(0) + 1e-6
    xs = np.concatenate([(x - mu) / sd, np.ones((len(x), 1), x.dtype)], 1).astype(np.float64)
    a = xs.T @ xs + lam * len(x) * np.eye(xs.shape[1])
    w = np.linalg.solve(a, xs.T @ y.astype(np.float64))
    return lambda z: np.concatenate([(z - mu) / sd, np.ones((len(z), 1), z.dtype)], 1) @ w


def r2(pred: np.ndarray, y: np.ndarray) -> float:
    res = ((pred - y) ** 2).sum(0)
    tot = ((y - y.mean(0)) ** 2).sum(0)
    return float(np.mean(1 - res / tot))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("train")
    ap.add_argument("val")
    ap.add_argument("--train-scenes", type=int, default=20)
    ap.add_argument("--val-scenes", type=int, default=10)
    args = ap.parse_args()
    torch.manual_seed(0)
    net = EfficientLiteBackbone(BackboneConfig()).eval()
    tr = collect(args.train, args.train_scenes, net)
    va = collect(args.val, args.val_scenes, net)
    out = {"train_images": int(tr[0].shape[0]), "val_images": int(va[0].shape[0]),
           "positions_per_image": int(tr[0].shape[1] * tr[0].shape[2]), "r2": {}}
    for name, k in (("trunk", 0), ("trunk_groupnorm", 1)):
        xt, xv = tr[k].reshape(-1, tr[k].shape[-1]), va[k].reshape(-1, va[k].shape[-1])
        res = {}
        for t, (yt, yv) in zip(targets(tr[2]), zip(targets(tr[2]).values(), targets(va[2]).values())):
            f = ridge(xt, yt.reshape(len(xt), -1))
            res[t] = r2(f(xv), yv.reshape(len(xv), -1))
        # per-image mean colour from per-image mean features
        mt, mv = tr[k].mean((1, 2)), va[k].mean((1, 2))
        ct, cv = tr[2].mean((1, 2)), va[2].mean((1, 2))
        res["image_mean_rgb"] = r2(ridge(mt, ct, lam=1e-1)(mv), cv)
        out["r2"][name] = res
    print(json.dumps(out))


if __name__ == "__main__":
    main()
