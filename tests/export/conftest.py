"""One ONNX export of the tiny test config per pytest session (through `xyzcyl export`, which is thereby
tested), shared by every test of tests/export: the export takes about a minute whatever the config's size."""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
EXAMPLE_RIG = REPO / "examples" / "synth_nuscenes" / "rig.json"
sys.path.insert(0, str(REPO / "tests" / "model_export"))   # net_helpers (tiny_config, overlap_rig)


@dataclass
class TinyExport:
    model: object          # the torch XYZCylinder (eval mode) the graphs were exported from
    dir: Path              # the model folder
    checkpoint: Path


def tiny_export_config():
    """tiny_config with at most 300 voxels (the 20x20x4 grid's random occupancy head selects ~half of its 1600
    voxels, so the top-k branch of the selection runs), the focal-aware depth head (the graphs then take each
    camera's focal_n: the 5-, 6- and 8-camera test rigs have three different focal lengths) and the standardised
    backbone input (input_norm: its per-image reductions are in the encode graph)."""
    from net_helpers import tiny_config

    cfg = tiny_config()
    return cfg.replace(volume=cfg.volume.replace(max_voxels=300),
                       backbone=cfg.backbone.replace(depth_focal_ref=0.9, input_norm="standardize"))


@pytest.fixture(scope="session")
def tiny_export(tmp_path_factory) -> TinyExport:
    import torch
    from xyzcyl.clients import cli
    from xyzcyl.model_export.model import XYZCylinder

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        torch.manual_seed(0)
        cfg = tiny_export_config()
        model = XYZCylinder(cfg).eval()
        with torch.no_grad():
            # random weights give the occupancy head margins of one sign (no voxel selected); spread them and
            # centre them on a 6-camera example so that about half of the voxels are occupied (volume Gaussians to
            # compare, the top-k branch of the selection to exercise)
            from net_helpers import overlap_rig
            from xyzcyl.model_export.lifting import rig_inputs

            last = model.occ_head[-1]
            last.weight.normal_(0.0, 1.0)
            last.bias.zero_()
            occ = model(torch.rand(6, 3, 64, 128), rig_inputs(overlap_rig(6), cfg))["occ_logits"]
            last.bias[1] -= float((occ[1] - occ[0]).median())
        # XYZCYL_TINY_EXPORT=DIR (development only): export into DIR once and reuse it in later sessions
        reuse = os.environ.get("XYZCYL_TINY_EXPORT")
        root = Path(reuse) if reuse else tmp_path_factory.mktemp("tiny_export")
        root.mkdir(parents=True, exist_ok=True)
        ck = root / "tiny.pt"
        out = root / "tiny-model"
        if reuse and (out / "model.json").is_file():
            return TinyExport(model=model, dir=out, checkpoint=ck)
        torch.save({"model": model.state_dict(), "model_cfg": cfg.to_dict(), "step": 0,
                    "train_cfg": {"stage": "render", "steps": 0}}, ck)
        rc = cli.main(["export", "--checkpoint", str(ck), "--out", str(out), "--name", "tiny-test",
                       "--version", "0.0.1", "--threads", "1", "--quiet"])
        assert rc == 0
    finally:
        torch.set_num_threads(threads)
    return TinyExport(model=model, dir=out, checkpoint=ck)
