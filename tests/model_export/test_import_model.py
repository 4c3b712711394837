"""`xyzcyl import-model` (model_export/recover.py): the tiny test model's folder back to a checkpoint whose weights
equal the exported model's exactly, for every module its graphs use; CLI refusals exit 2 naming the flag."""

from __future__ import annotations

import pytest
import torch
from xyzcyl import cli

pytestmark = pytest.mark.slow   # the session's ONNX export (tests/conftest.py) and one pattern export


@pytest.mark.heavy
def test_import_model_recovers_the_exported_weights(tiny_export, tmp_path, capsys):
    out = tmp_path / "back.pt"
    # --no-verify: the comparison with the original weights below is the stronger check (and saves an export)
    assert cli.main(["import-model", str(tiny_export.dir), "--out", str(out), "--no-verify", "--threads", "1",
                     "--quiet"]) == 0
    assert "back.pt: tiny-test 0.0.1" in capsys.readouterr().out
    ck = torch.load(out, weights_only=False)
    orig = torch.load(tiny_export.checkpoint, weights_only=False)["model"]
    skipped = set(ck["recovered_from"]["not_in_graphs"])
    assert {k for k in orig if k.startswith(("bev_head", "bev_proj"))} <= skipped    # training-only heads
    assert set(ck["model"]) == set(orig)
    # every weight equals the exported model's: the recovered ones bit for bit, and the ones found in no graph
    # (the BEV head; this random-weight model's constant norm scales and biases, which the exporter folds) because
    # recovery starts from the same seeded initialisation as the tiny model
    differ = [k for k in orig if not torch.equal(ck["model"][k], orig[k])]
    assert differ == []
    # and nothing else was left out: each is a BEV-head weight or a constant tensor the exporter folded away or
    # merged with its equals (this untrained model's norm scales are all 1 and its biases all 0)
    assert all(k.startswith(("bev_head", "bev_proj")) or bool((orig[k] == orig[k].flatten()[0]).all())
               for k in skipped)
    # the graphs' anonymous constants (GroupNorm affines and others) were among the recovered ones
    assert any(".gn." in k or ".n1." in k for k in orig if k not in skipped)
    assert ck["model_cfg"]["backbone"]["depth_focal_ref"] == 0.9 and ck["model_cfg"]["volume"]["max_voxels"] == 300
    assert ck["train_cfg"]["stage"] == "render" and ck["recovered_from"]["version"] == "0.0.1"


def test_import_model_refusals(tiny_export, tmp_path, capsys):
    assert cli.main(["import-model", str(tmp_path), "--out", str(tmp_path / "x.pt")]) == 2
    assert "no model.json" in capsys.readouterr().err
    assert cli.main(["import-model", str(tiny_export.dir), "--out", str(tmp_path / "x.ckpt")]) == 2
    assert "--out" in capsys.readouterr().err
    (tmp_path / "x.pt").write_bytes(b"")
    assert cli.main(["import-model", str(tiny_export.dir), "--out", str(tmp_path / "x.pt")]) == 2
    assert "--force" in capsys.readouterr().err
    assert cli.main(["import-model", str(tiny_export.dir), "--out", str(tmp_path / "no" / "x.pt")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_mismatched_initializers_by_hand():
    import numpy as np
    from xyzcyl.model_export.recover import mismatched_initializers

    a = {("encode", "w"): np.ones(3, np.float32), ("encode", "b"): np.zeros(2, np.float32)}
    assert mismatched_initializers(a, {k: v.copy() for k, v in a.items()}) == []
    b = dict(a)
    b[("encode", "w")] = np.array([1, 1, np.nextafter(np.float32(1), np.float32(2))], np.float32)   # one ulp
    assert mismatched_initializers(a, b) == ["encode.onnx:w"]
    b = dict(a)
    b[("encode", "b")] = np.zeros(2, np.float64)                                        # same values, other dtype
    assert mismatched_initializers(a, b) == ["encode.onnx:b"]
    assert mismatched_initializers(a, {("encode", "w"): a[("encode", "w")]}) == ["encode.onnx:b"]
