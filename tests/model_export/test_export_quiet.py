"""`xyzcyl export-model` prints none of torch's exporter messages that say nothing about our graphs, and only those are
silenced (export._EXPORTER_NOISE)."""

import logging

import pytest

torch = pytest.importorskip("torch")

from xyzcyl.model_export import export as export_mod


def _record(msg: str) -> logging.LogRecord:
    return logging.LogRecord("torch.onnx._internal.exporter._registration", logging.WARNING, __file__, 1, msg, None,
                             None)


def test_filter_drops_exactly_the_known_messages():
    f = export_mod._DropNoise()
    assert not f.filter(_record("torchvision is not installed. Skipping torchvision::nms"))
    assert f.filter(_record("Unsupported operator aten::foo"))   # anything else still shows


def test_export_of_a_small_module_prints_no_exporter_noise(tmp_path, capfd, recwarn):
    module = torch.nn.Sequential(torch.nn.Linear(4, 3), torch.nn.ReLU()).eval()
    path = tmp_path / "m.onnx"
    export_mod._export(module, (torch.rand(2, 4),), path, ["x"], ["y"], None)
    err = capfd.readouterr().err
    assert path.stat().st_size > 0
    for m in export_mod._EXPORTER_NOISE:
        assert m not in err
        assert not [w for w in recwarn if m in str(w.message)]
