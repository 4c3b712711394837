"""The encode graph split in two where the depth input enters: ``encode_image.onnx`` (everything that does not
depend on ``depth`` / ``depth_mask``: the backbone, the occupancy logits, the appearance plane, and the tensors the
rest reads) and ``encode_depth.onnx`` (the depth head and what follows it: the pixel Gaussians). Run in turn they
compute exactly ``encode.onnx``'s outputs (the same nodes on the same tensors; tests/model_export/test_split.py
compares the bits); a reconstruction with LiDAR runs the encode graph twice with the same images and another depth
(runtime.inference.Reconstructor.keyframe), and the second run needs only ``encode_depth`` (a PandaSet frame's
second pass: 0.55 -> 0.14 s, docs/results.md).

    from xyzcyl.model_export.split import split_encode, add_split
    split_encode("encode.onnx", "encode_image.onnx", "encode_depth.onnx")   # False: nothing to split
    add_split("models/xyzcyl-cpu-v1")        # an existing model folder: the two files and model.json's entries

``python -m xyzcyl.model_export.split MODEL_DIR`` does ``add_split``. Needs the ``onnx`` package (the train extra);
the runtime only reads the files.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

DEPTH_INPUTS = ("depth", "depth_mask")
IMAGE_GRAPH, DEPTH_GRAPH = "encode_image", "encode_depth"


def _depth_dependent(graph) -> set[str]:
    """The tensors of ``graph`` computed from the depth inputs (a Shape node's output excepted: it reads only the
    tensor's shape, see split_encode)."""
    tainted = set(DEPTH_INPUTS)
    for node in graph.node:                 # ONNX lists the nodes in topological order
        if node.op_type != "Shape" and any(i in tainted for i in node.input):
            tainted.update(node.output)
    return tainted


def split_encode(src: str | Path, image_out: str | Path, depth_out: str | Path) -> bool:
    """Write the two halves of the encode graph ``src`` (module docstring). A Shape of ``depth_mask`` (or of
    ``depth``) that reads the camera count N, its first dimension, reads it from ``images`` instead (the same N: the
    runtime makes all three for the same cameras, Reconstructor.prepare); a graph that reads any other dimension of
    them, that lacks one of the three inputs, or in which no output depends on the depth is not split: returns False
    and writes nothing."""
    import onnx
    from onnx.utils import Extractor

    model = onnx.load(str(src))
    g = model.graph
    for node in g.node:
        if node.op_type == "Shape" and node.input[0] in DEPTH_INPUTS:
            attrs = {a.name: onnx.helper.get_attribute_value(a) for a in node.attribute}
            if attrs.get("start", 0) != 0 or attrs.get("end") != 1:
                return False
            node.input[0] = "images"
    tainted = _depth_dependent(g)
    inits = {i.name for i in g.initializer}
    inputs = {i.name for i in g.input}
    if any(name not in inputs for name in ("images", *DEPTH_INPUTS)):
        return False
    late = [n for n in g.node if n.op_type != "Shape" and any(i in tainted for i in n.input)]
    made_late = {o for n in late for o in n.output}
    # what the depth part reads that the image part makes (or a graph input gives), in a stable order
    crossing = sorted({i for n in late for i in n.input
                       if i and i not in made_late and i not in inits and i not in DEPTH_INPUTS})
    outputs = [o.name for o in g.output]
    early_out = [o for o in outputs if o not in tainted]
    late_out = [o for o in outputs if o in tainted]
    if not late or not late_out:
        return False
    # the halves' inputs and outputs need their types (value_info): the exporter writes them, a hand-made graph
    # may not
    ex = Extractor(onnx.shape_inference.infer_shapes(model))
    image = ex.extract_model(sorted(inputs - set(DEPTH_INPUTS)),   # (an output the depth half reads too: once)
                             list(dict.fromkeys([c for c in crossing if c not in inputs] + early_out)))
    depth = ex.extract_model(crossing + list(DEPTH_INPUTS), late_out)
    for part in (image, depth):             # only the inputs a half reads (the extractor keeps all it was given)
        used = {i for n in part.graph.node for i in n.input}
        kept = [i for i in part.graph.input if i.name in used]
        del part.graph.input[:]
        part.graph.input.extend(kept)
        onnx.checker.check_model(part)
    onnx.save(image, str(image_out))
    onnx.save(depth, str(depth_out))
    return True


def add_split(model_dir: str | Path) -> bool:
    """Add the split of a model folder's encode graph (split_encode) to the folder: ``encode_image.onnx``,
    ``encode_depth.onnx`` and their entries in model.json's ``graphs`` and ``files`` (sha256, bytes). Returns False
    (the folder unchanged) when the graph does not split. An existing split is written again."""
    from .export import graph_io, sha256_file

    folder = Path(model_dir)
    meta = json.loads((folder / "model.json").read_text())
    src = folder / meta["graphs"]["encode"]["file"]
    paths = {IMAGE_GRAPH: folder / f"{IMAGE_GRAPH}.onnx", DEPTH_GRAPH: folder / f"{DEPTH_GRAPH}.onnx"}
    tmp = {k: p.with_suffix(".onnx.tmp") for k, p in paths.items()}
    if not split_encode(src, tmp[IMAGE_GRAPH], tmp[DEPTH_GRAPH]):
        return False
    for k, p in paths.items():
        tmp[k].replace(p)
        meta["graphs"][k] = {"file": p.name, **graph_io(p)}
        meta["files"][p.name] = {"sha256": sha256_file(p), "bytes": p.stat().st_size}
    meta["files"] = dict(sorted(meta["files"].items()))
    out = folder / "model.json.tmp"
    out.write_text(json.dumps(meta, indent=1, allow_nan=False) + "\n")
    out.replace(folder / "model.json")
    return True


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m xyzcyl.model_export.split MODEL_DIR", file=sys.stderr)
        return 2
    if not (Path(args[0]) / "model.json").is_file():
        print(f"MODEL_DIR: no model.json in {args[0]!r}", file=sys.stderr)
        return 2
    done = add_split(args[0])
    print(f"{args[0]}: " + ("encode_image.onnx and encode_depth.onnx written" if done
                            else "the encode graph does not split (unchanged)"))
    return 0 if done else 1


__all__ = ["DEPTH_GRAPH", "DEPTH_INPUTS", "IMAGE_GRAPH", "add_split", "main", "split_encode"]

if __name__ == "__main__":
    raise SystemExit(main())
