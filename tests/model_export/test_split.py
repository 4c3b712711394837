"""model_export.split: the encode graph split where the depth enters gives the whole graph's bits; graphs that
cannot be split are left whole; add_split on a model folder."""

from __future__ import annotations

import json
import shutil

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from onnx import TensorProto, helper
from xyzcyl.model_export.split import DEPTH_GRAPH, IMAGE_GRAPH, add_split, split_encode
from xyzcyl.runtime.inference import verify_model


def _run(path, feed):
    s = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    names = [o.name for o in s.get_outputs()]
    return dict(zip(names, s.run(names, {i.name: feed[i.name] for i in s.get_inputs()})))


def _toy():
    """images [N, 2] -> feat = relu(images @ W); out_img = feat summed; out_px = feat * depth + depth_mask[:, None],
    reshaped to [N, -1] with N from Shape(depth_mask) (as the exported graph reads the camera count)."""
    W = helper.make_tensor("W", TensorProto.FLOAT, [2, 3], np.arange(6, dtype=np.float32).tolist())
    nodes = [helper.make_node("MatMul", ["images", "W"], ["mm"]),
             helper.make_node("Relu", ["mm"], ["feat"]),
             helper.make_node("ReduceSum", ["feat"], ["out_img"], keepdims=0),
             helper.make_node("Mul", ["feat", "depth"], ["fd"]),
             helper.make_node("Unsqueeze", ["depth_mask", "ax"], ["dm"]),
             helper.make_node("Add", ["fd", "dm"], ["px"]),
             helper.make_node("Shape", ["depth_mask"], ["n"], start=0, end=1),
             helper.make_node("Concat", ["n", "minus1"], ["shp"], axis=0),
             helper.make_node("Reshape", ["px", "shp"], ["out_px"])]
    inits = [W, helper.make_tensor("ax", TensorProto.INT64, [1], [1]),
             helper.make_tensor("minus1", TensorProto.INT64, [1], [-1])]
    g = helper.make_graph(nodes, "toy",
                          [helper.make_tensor_value_info("images", TensorProto.FLOAT, ["N", 2]),
                           helper.make_tensor_value_info("depth", TensorProto.FLOAT, ["N", 3]),
                           helper.make_tensor_value_info("depth_mask", TensorProto.FLOAT, ["N"])],
                          [helper.make_tensor_value_info("out_img", TensorProto.FLOAT, []),
                           helper.make_tensor_value_info("out_px", TensorProto.FLOAT, ["N", 3])], inits)
    return helper.make_model(g, opset_imports=[helper.make_opsetid("", 20)])


def test_a_toy_graph_splits_and_its_halves_give_its_outputs(tmp_path):
    onnx.save(_toy(), tmp_path / "e.onnx")
    assert split_encode(tmp_path / "e.onnx", tmp_path / "a.onnx", tmp_path / "b.onnx")
    a, b = onnx.load(tmp_path / "a.onnx"), onnx.load(tmp_path / "b.onnx")
    assert {i.name for i in a.graph.input} == {"images"}                 # Shape(depth_mask) reads images' N
    assert {o.name for o in a.graph.output} == {"feat", "shp", "out_img"}      # shp: [N, -1], made from images
    assert {i.name for i in b.graph.input} == {"feat", "shp", "depth", "depth_mask"}
    assert [o.name for o in b.graph.output] == ["out_px"]
    rng = np.random.default_rng(0)
    feed = {"images": rng.normal(size=(4, 2)).astype(np.float32),
            "depth": rng.uniform(1, 9, (4, 3)).astype(np.float32), "depth_mask": np.ones(4, np.float32)}
    whole = _run(tmp_path / "e.onnx", feed)
    early = _run(tmp_path / "a.onnx", feed)
    late = _run(tmp_path / "b.onnx", {**feed, **early})
    np.testing.assert_array_equal(early["out_img"], whole["out_img"])
    np.testing.assert_array_equal(late["out_px"], whole["out_px"])


def test_graphs_that_do_not_split_are_left_whole(tmp_path):
    # a Shape that reads more of a depth input than the camera count: not split
    bad = _toy()
    for node in bad.graph.node:
        if node.op_type == "Shape":
            del node.attribute[:]
            node.attribute.extend([helper.make_attribute("start", 0), helper.make_attribute("end", 2)])
    onnx.save(bad, tmp_path / "shape.onnx")
    assert not split_encode(tmp_path / "shape.onnx", tmp_path / "a.onnx", tmp_path / "b.onnx")
    # no output depends on the depth: nothing to split
    g = helper.make_graph([helper.make_node("Relu", ["images"], ["out"])], "nodepth",
                          [helper.make_tensor_value_info(n, TensorProto.FLOAT, ["N", 2])
                           for n in ("images", "depth", "depth_mask")],
                          [helper.make_tensor_value_info("out", TensorProto.FLOAT, ["N", 2])])
    onnx.save(helper.make_model(g, opset_imports=[helper.make_opsetid("", 20)]), tmp_path / "nodepth.onnx")
    assert not split_encode(tmp_path / "nodepth.onnx", tmp_path / "a.onnx", tmp_path / "b.onnx")
    assert not (tmp_path / "a.onnx").exists() and not (tmp_path / "b.onnx").exists()


@pytest.mark.slow
def test_add_split_writes_the_halves_into_a_model_folder(tiny_export, tmp_path):
    """A folder exported before the split (its entries removed) gets them back from add_split: the same graphs'
    inputs and outputs as the export wrote, sha256s that verify_model accepts."""
    dst = tmp_path / "m"
    shutil.copytree(tiny_export.dir, dst)
    exported = json.loads((dst / "model.json").read_text())
    meta = json.loads((dst / "model.json").read_text())
    for g in (IMAGE_GRAPH, DEPTH_GRAPH):
        name = meta["graphs"].pop(g)["file"]
        del meta["files"][name]
        (dst / name).unlink()
    (dst / "model.json").write_text(json.dumps(meta, indent=1))
    assert add_split(dst)
    info = verify_model(dst)
    for g in (IMAGE_GRAPH, DEPTH_GRAPH):
        assert info.meta["graphs"][g] == exported["graphs"][g]
    assert set(info.meta["files"]) == set(exported["files"])
