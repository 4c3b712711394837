"""A model folder back to a training checkpoint (`xyzcyl import-model`): the exact weights of every module the ONNX
graphs use, so a shipped model can be trained further (`xyzcyl train --init CKPT`) when its checkpoint is gone.

The dynamo exporter keeps most parameters as initializers named after them (`m.<state-dict key>`); the rest (the
GroupNorm affines and others it reshapes) become anonymous constants (`val_123`). Those are found by exporting the
same config once more with each such parameter filled with a distinct integer pattern (element i of the k-th
tensor = its global index, exact in float32 below 2^24): a pattern initializer says, element by element, which
parameter element the same-named initializer of the shipped graph holds, whatever reshape or transpose the
exporter applied. Initializers that hold the same values in both exports are graph constants, not weights, and
are skipped. Parameters found in no graph keep the fresh initialisation and are listed in the checkpoint
(`not_in_graphs`): modules no graph uses (training-only heads such as the BEV head, an ablated branch), and
constant weights the exporter folded away or merged with equal ones (an untrained model's all-one norm scales and
all-zero biases); the verification below says whether that matters. With ``verify`` the recovered model is exported again and
every initializer of every graph must equal the shipped one bit for bit.
"""

from __future__ import annotations

import hashlib
import json
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .config import ModelConfig

PATTERN_LIMIT = 2 ** 24   # float32 holds every integer below this exactly


class RecoverError(ValueError):
    """The model folder cannot be turned back into a checkpoint; the message names the file or tensor."""


def _initializers(folder: Path, graphs) -> dict[tuple[str, str], np.ndarray]:
    import onnx
    from onnx import numpy_helper

    out = {}
    for g, desc in graphs.items():
        path = folder / desc["file"] if isinstance(desc, dict) and "file" in desc else folder / f"{g}.onnx"
        if not path.is_file():
            raise RecoverError(f"model: graph file {str(path)!r} is missing")
        for init in onnx.load(str(path)).graph.initializer:
            out[(g, init.name)] = numpy_helper.to_array(init)
    return out


def _key(name: str) -> str:
    return name.removeprefix("m.")


def recover_state(model_dir: str | Path, verify: bool = True, progress=None) -> dict[str, Any]:
    """{"state": state dict, "model_cfg": dict, "meta": model.json, "not_in_graphs": [keys]} of a model folder
    written by `xyzcyl export-model` (same torch version: the exporter's anonymous names must match; ``verify``
    proves it)."""
    from .export import export_graphs
    from .train import build_model

    say = progress or (lambda msg: None)
    folder = Path(model_dir)
    try:
        meta = json.loads((folder / "model.json").read_text())
    except (OSError, ValueError) as e:
        raise RecoverError(f"model: cannot read {str(folder / 'model.json')!r} ({e})") from None
    cfg = ModelConfig.from_dict(meta["config"])
    shipped = _initializers(folder, meta["graphs"])
    torch.manual_seed(0)
    model = build_model(cfg).eval()
    fresh = {k: v.clone() for k, v in model.state_dict().items()}   # copies: the pattern is loaded into the model
    by_name = {_key(n): a for (_, n), a in shipped.items()}
    state: dict[str, torch.Tensor] = {}
    unnamed = []
    for k, v in fresh.items():
        a = by_name.get(k)
        if a is not None and tuple(a.shape) == tuple(v.shape):
            state[k] = torch.from_numpy(np.array(a)).to(v.dtype)
        elif v.is_floating_point():
            unnamed.append(k)
        else:
            state[k] = v.clone()
    starts, off = [], 1
    for k in unnamed:
        starts.append(off)
        off += fresh[k].numel()
    if off >= PATTERN_LIMIT:
        raise RecoverError(f"model: {off} unnamed weights, more than the pattern holds exactly ({PATTERN_LIMIT})")
    patterned = dict(state)
    for k, s in zip(unnamed, starts):
        patterned[k] = torch.arange(s, s + fresh[k].numel(), dtype=torch.float32).reshape(fresh[k].shape)
    model.load_state_dict({**fresh, **patterned})
    got = {k: np.full(fresh[k].numel(), np.nan, np.float32) for k in unnamed}
    with tempfile.TemporaryDirectory(prefix="xyzcyl-recover-") as tmp:
        say(f"pattern export ({len(unnamed)} unnamed tensors)")
        export_graphs(model, tmp, n_cameras=6)
        pattern = _initializers(Path(tmp), {g: {"file": f"{g}.onnx"} for g in meta["graphs"]})
    s_arr = np.array(starts)
    for key, p in pattern.items():
        if p.dtype != np.float32 or key not in shipped or np.array_equal(p, shipped[key]):
            continue      # not a weight: a constant both graphs hold (or an integer index array)
        v = p.astype(np.float64).ravel()
        if v.size == 0 or v.min() < 1 or v.max() >= off or not np.all(v == np.round(v)):
            continue
        if shipped[key].size != v.size:
            raise RecoverError(f"model: initializer {key[1]!r} of {key[0]}.onnx has {shipped[key].size} values, "
                               f"the pattern export {v.size} (another torch version or config?)")
        s = shipped[key].astype(np.float32).ravel()
        t = np.searchsorted(s_arr, v, side="right") - 1
        for ti in np.unique(t):
            m = t == ti
            k = unnamed[ti]
            got[k][(v[m] - starts[ti]).astype(np.int64)] = s[m]
    not_in_graphs = []
    for k in unnamed:
        holes = np.isnan(got[k])
        if holes.all():
            not_in_graphs.append(k)
            state[k] = fresh[k].clone()
        elif holes.any():
            raise RecoverError(f"model: tensor {k!r}: {int(holes.sum())} of {holes.size} values not found in the "
                               "graphs")
        else:
            state[k] = torch.from_numpy(got[k].reshape(tuple(fresh[k].shape))).to(fresh[k].dtype)
    if verify:
        model.load_state_dict(state)
        with tempfile.TemporaryDirectory(prefix="xyzcyl-recover-") as tmp:
            say("verifying: exporting the recovered weights")
            export_graphs(model, tmp, n_cameras=6)
            again = _initializers(Path(tmp), {g: {"file": f"{g}.onnx"} for g in meta["graphs"]})
        bad = mismatched_initializers(shipped, again)
        if bad:
            raise RecoverError(f"model: the recovered weights do not export to the same graphs ({len(bad)} "
                               f"initializers differ, e.g. {bad[:3]}; another torch version?)")
    return {"state": state, "model_cfg": cfg.to_dict(), "meta": meta, "not_in_graphs": not_in_graphs}


def mismatched_initializers(a: dict[tuple[str, str], np.ndarray], b: dict[tuple[str, str], np.ndarray]) -> list[str]:
    """'graph.onnx:name' of every initializer that is in only one of ``a``, ``b`` or differs in shape, dtype or any
    value (bit for bit: NaN equals NaN only as the same bits)."""
    out = []
    for key in sorted(set(a) | set(b)):
        x, y = a.get(key), b.get(key)
        if x is None or y is None or x.shape != y.shape or x.dtype != y.dtype or x.tobytes() != y.tobytes():
            out.append(f"{key[0]}.onnx:{key[1]}")
    return out


def import_model(model_dir: str | Path, out: str | Path, verify: bool = True, progress=None) -> dict[str, Any]:
    """Write the training checkpoint of a model folder to ``out`` (train.py's format: model, model_cfg, train_cfg,
    step, plus `recovered_from`). Returns the `recover_state` result."""
    from .train import save_atomic

    r = recover_state(model_dir, verify=verify, progress=progress)
    meta = r["meta"]
    ck = meta.get("checkpoint") or {}
    model_json = Path(model_dir) / "model.json"
    save_atomic({"model": r["state"], "model_cfg": r["model_cfg"], "train_cfg": ck.get("train") or {"stage": "render"},
                 "step": ck.get("step"),
                 "recovered_from": {"model": str(model_dir), "name": meta.get("name"), "version": meta.get("version"),
                                    "model_json_sha256": hashlib.sha256(model_json.read_bytes()).hexdigest(),
                                    "checkpoint_sha256": ck.get("sha256"), "verified": verify,
                                    "not_in_graphs": r["not_in_graphs"]}}, Path(out))
    return r


__all__ = ["RecoverError", "import_model", "mismatched_initializers", "recover_state"]
