"""`xyzcyl train`: one training stage of XYZCylinder on a synthetic data set (docs/training.md).

    xyzcyl train --preset cpu --data DIR --stage occ --out RUN_OCC --steps 2000
    xyzcyl train --data DIR --stage render --init RUN_OCC/occ.pt --out RUN_RENDER --steps 4000
    xyzcyl train --data DIR --stage depth --init RUN_RENDER/render.pt --out RUN_DEPTH --steps 800 --lr 1e-3
    xyzcyl train ... --resume          # continue RUN_DIR from last.pt
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from xyzcyl.model_export.commands.common import add_runtime_arguments, set_threads

ABLATIONS = {"none": {}, "no-volume": {"volume_branch": False}, "no-pixel": {"pixel_branch": False},
             "no-background": {"separate_background": False}, "no-rgb": {"rgb_path": False}}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--preset", default=None, help="model preset: cpu or paper (default: cpu, or the --init "
                                                       "checkpoint's config)")
    parser.add_argument("--data", required=True, type=Path, action="append",
                        help="training data set (xyzcyl data synth output); repeat to mix data sets (e.g. rigs "
                             "with different camera counts): their scenes are drawn as one set")
    parser.add_argument("--val", type=Path, default=None, help="validation data set (metrics + sheets)")
    parser.add_argument("--stage", required=True, choices=("occ", "render", "depth"),
                        help="occ: stage 1; render: stage 2; depth: the depth head alone on its log-L1, from a "
                             "stage-2 --init (no rendering; about 0.5 s a step)")
    parser.add_argument("--out", required=True, type=Path, help="run folder (checkpoints, logs, curves)")
    parser.add_argument("--resume", action="store_true", help="continue the run in --out from last.pt")
    parser.add_argument("--init", type=Path, default=None, help="start from this checkpoint's weights "
                                                                 "(stage render: the stage-1 occ.pt; stage depth: a "
                                                                 "render.pt)")
    parser.add_argument("--steps", type=int, default=2000, help="optimiser steps of this stage (one scene each)")
    parser.add_argument("--setting", default="ego-forward", choices=("ego-forward", "ego-inward", "both"),
                        help="target views that supervise stage render (both: drawn from either setting)")
    parser.add_argument("--targets", type=int, default=4, help="T, random target views per step")
    parser.add_argument("--target-scale", type=float, default=1.0,
                        help="render and supervise the targets at this fraction of their size (e.g. 0.5: 4x "
                             "fewer pixels per step; evaluation stays at full size)")
    parser.add_argument("--lr", type=float, default=1e-4,
                        help="peak learning rate of AdamW (linear warm-up, then cosine decay; default 1e-4)")
    parser.add_argument("--warmup", type=int, default=None,
                        help="warm-up steps (default: min(1000, steps // 10), the paper uses 1000 of 100k)")
    parser.add_argument("--ckpt-every", type=int, default=50, help="steps between checkpoints")
    parser.add_argument("--val-every", type=int, default=0, help="steps between validation passes (0: at the end)")
    parser.add_argument("--val-scenes", type=int, default=4,
                        help="validation scenes per pass, the first N of --val (default 4)")
    parser.add_argument("--voxel-size", type=float, default=None, help="occupancy voxel (default: the preset's)")
    parser.add_argument("--ablation", default="none", choices=sorted(ABLATIONS),
                        help="train without one part of the network: the volume or pixel Gaussians, the separate "
                             "background, or the RGB path (default none)")
    parser.add_argument("--volume-selection", default=None, choices=("predicted", "ground_truth"),
                        help="voxels that carry volume Gaussians in stage render (default: the preset's, "
                             "predicted); evaluation always uses the predicted occupancy")
    parser.add_argument("--pixel-upsample", type=int, default=None,
                        help="k_o: pixel Gaussians on a k_o-times finer cylinder lattice (2: 56x512, 4: 112x1024 at "
                             "the cpu preset's 28x256; default: the preset's)")
    parser.add_argument("--placement", default=None, choices=("cylinder_ray", "camera_ray"),
                        help="pixel-Gaussian anchor (docs/architecture.md; default: the preset's)")
    parser.add_argument("--depth-focal-ref", default=None, metavar="F|off",
                        help="focal-aware depth: the depth head's output is scaled by each camera's normalised focal "
                             "sqrt(fx/W * fy/H) over F ('nuscenes': 1.0553, the nuScenes front camera's); 'off': "
                             "focal-blind (docs/architecture.md; default: the preset's, or the --init checkpoint's)")
    parser.add_argument("--input-norm", default=None, choices=("none", "standardize"),
                        help="what the backbone sees: the images as posted (none) or each image moved to the "
                             "synthetic inputs' per-channel mean and spread (standardize: exposure and white "
                             "balance do not reach the features; docs/architecture.md; default: the preset's, or "
                             "the --init checkpoint's)")
    parser.add_argument("--max-voxels", type=int, default=None,
                        help="cap on occupied voxels per scene (default: the preset's)")
    parser.add_argument("--occupancy-labels", default="solid", choices=("solid", "surface", "surface+ego"),
                        help="stage-1 targets: every occupied voxel (solid) or only those an input camera sees "
                             "(surface; hidden ones are ignored), or surface plus the ego car's voxels, which no "
                             "input camera sees but are always there (surface+ego; docs/training.md)")
    parser.add_argument("--flip-prob", type=float, default=0.5, help="scene mirror (y -> -y) probability")
    parser.add_argument("--jitter", type=float, default=0.1, help="colour jitter strength (brightness, contrast, "
                                                                  "saturation), 0 disables")
    parser.add_argument("--camera-aug", type=float, default=0.0,
                        help="real-camera effects on the input images only, S in [0, 1] scales the preset "
                             "(per camera: exposure 0.3S, white balance 0.1S, vignetting 0.4S, blur prob. 0.3S, "
                             "JPEG prob. 0.5S, noise sigma 0.02S; docs/training.md); 0 disables")
    parser.add_argument("--camera-drop", type=float, default=0.0,
                        help="probability that a training scene loses 1-2 input cameras adjacent in azimuth (a rig "
                             "with a blind side; targets kept; docs/training.md); 0 disables")
    parser.add_argument("--lens-zoom", type=float, default=0.0,
                        help="probability per input camera of a narrower lens (its image, depth and sky cropped by "
                             "a zoom of U(1, 1.4) and resampled, K to match; targets kept; docs/training.md): "
                             "lenses the rig does not have, for the focal-aware depth head; 0 disables")
    parser.add_argument("--lidar-input", type=float, default=0.0,
                        help="probability that a training scene's inputs carry a simulated LiDAR sweep, made into "
                             "the depth input as the runtime makes a real one (stage render; docs/training.md): the "
                             "model learns to use LiDAR depth; 0 disables")
    parser.add_argument("--seed", type=int, default=0,
                        help="seed of the weights' initialisation, the scene order and the augmentations (default 0)")
    parser.add_argument("--device", default="cpu",
                        help="cpu or cuda (cuda:N): where the network and its losses run; the splatting renderer "
                             "stays on the host CPU (default cpu)")
    add_runtime_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from xyzcyl.model_export.config import ConfigError, ModelConfig, parse_focal_ref, preset
    from xyzcyl.model_export.dataset import DataError, DatasetConfig, camera_aug_fields
    from xyzcyl.model_export.losses import LPIPSUnavailable, OptimConfig, RenderLossConfig, TrainLossConfig
    from xyzcyl.model_export.train import TrainConfig, load_checkpoint, resolve_device, train
    from xyzcyl.runtime.rig import RigError

    try:
        set_threads(args.threads)
        device = resolve_device(args.device)
        for d in args.data:
            if not d.is_dir():
                raise ValueError(f"data: {d} is not a folder")
        if args.steps < 1:
            raise ValueError(f"steps: must be >= 1, got {args.steps}")
        if args.resume and not (args.out / "last.pt").is_file():
            raise ValueError(f"resume: no checkpoint {args.out / 'last.pt'}")
        if args.preset is not None or (args.init is None and not args.resume):
            model_cfg = preset(args.preset or "cpu")
        else:       # the config of the checkpoint this run starts from (or continues)
            src = args.out / "last.pt" if args.resume else args.init
            model_cfg = ModelConfig.from_dict(load_checkpoint(src)["model_cfg"])
        model_cfg = model_cfg.replace(ablation=model_cfg.ablation.replace(**ABLATIONS[args.ablation]))
        if args.voxel_size is not None:
            model_cfg = model_cfg.replace(grid=model_cfg.grid.replace(voxel_size=args.voxel_size))
        if args.volume_selection is not None:
            model_cfg = model_cfg.replace(volume_selection=args.volume_selection)
        if args.pixel_upsample is not None:
            model_cfg = model_cfg.replace(pixel=model_cfg.pixel.replace(k_out=args.pixel_upsample))
        if args.placement is not None:
            model_cfg = model_cfg.replace(pixel=model_cfg.pixel.replace(placement=args.placement))
        if args.max_voxels is not None:
            model_cfg = model_cfg.replace(volume=model_cfg.volume.replace(max_voxels=args.max_voxels))
        if args.depth_focal_ref is not None:
            model_cfg = model_cfg.replace(backbone=model_cfg.backbone.replace(
                depth_focal_ref=parse_focal_ref(args.depth_focal_ref)))
        if args.input_norm is not None:
            model_cfg = model_cfg.replace(backbone=model_cfg.backbone.replace(input_norm=args.input_norm))
        voxel = model_cfg.grid.voxel_size
        warm = args.warmup if args.warmup is not None else min(1000, max(1, args.steps // 10))
        j = args.jitter
        tcfg = TrainConfig(
            stage=args.stage, steps=args.steps, ckpt_every=args.ckpt_every, val_every=args.val_every,
            val_scenes=args.val_scenes, seed=args.seed,
            data=DatasetConfig(setting=args.setting, num_targets=args.targets, voxel_size=voxel, seed=args.seed,
                               brightness=j, contrast=j, saturation=j, flip_prob=args.flip_prob,
                               occupancy_labels=args.occupancy_labels,
                               **camera_aug_fields(args.camera_aug), camera_drop=args.camera_drop,
                               lens_zoom=args.lens_zoom, lidar_input=args.lidar_input,
                               target_scale=args.target_scale),
            loss=TrainLossConfig(
                render=RenderLossConfig(lpips_net=args.lpips_net, lpips_backbone_path=args.lpips_backbone,
                                        lpips_lin_path=args.lpips_lin),
                optim=OptimConfig(lr=args.lr, warmup_steps=warm, total_steps=args.steps)))
        data = args.data if len(args.data) > 1 else args.data[0]     # one folder: recorded as before
        summary = train(data, args.out, model_cfg, tcfg, resume=args.resume, init=args.init,
                        val_dir=args.val, progress=not args.quiet, device=device)
    except (ValueError, ConfigError, DataError, RigError, LPIPSUnavailable, FileNotFoundError) as exc:
        print(f"xyzcyl train: {exc}", file=sys.stderr)
        return 2
    state = "interrupted at" if summary["interrupted"] else "finished at"
    print(f"{state} step {summary['steps']}; run folder {summary['run_dir']}")
    if summary.get("val"):
        print("validation: " + ", ".join(f"{k}={v}" for k, v in summary["val"].items()))
    return 130 if summary["interrupted"] else 0
