import pytest
import torch
from xyzcyl.model_export.backbone import BackboneError, EfficientLiteBackbone, ExternalBackbone
from xyzcyl.model_export.config import BackboneConfig, preset


def test_folded_frozen_trunk_matches_batchnorm_trunk():
    """The frozen trunk folds BatchNorm into the convs; the trainable one keeps the package's modules. Same
    ImageNet weights, same output (the unfolded model is the reference)."""
    cfg = preset("cpu").backbone.replace(input_height=64, input_width=128)
    torch.manual_seed(0)
    ref = EfficientLiteBackbone(cfg.replace(trainable=True)).eval()
    torch.manual_seed(0)
    fast = EfficientLiteBackbone(cfg).eval()
    fast.lat.load_state_dict(ref.lat.state_dict())  # the heads are randomly initialised: share them
    fast.out.load_state_dict(ref.out.state_dict())
    x = torch.rand(2, 3, 64, 128, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        a, b = ref(x), fast(x)
    assert a.shape == (2, cfg.feature_dim, 8, 16)
    # float32: folding reorders a multiply-add per layer over ~16 layers; outputs are O(1)
    torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4)
    assert all(not p.requires_grad for n, p in fast.named_parameters() if n.startswith(("stem", "blocks")))
    assert all(p.requires_grad for n, p in ref.named_parameters())


def test_frozen_trunk_stays_in_eval_mode():
    fast = EfficientLiteBackbone(preset("cpu").backbone).train()
    assert not fast.stem.training and not fast.blocks.training and fast.out.training


def test_external_backbone_missing_path_is_a_clear_error(tmp_path):
    cfg = BackboneConfig(kind="external", external_path=str(tmp_path / "radio.pt"))
    with pytest.raises(BackboneError, match="external_path"):
        ExternalBackbone(cfg)


def test_external_backbone_exported(tmp_path):
    """Any exported encoder [N,3,H,W] -> [N,C,h,w] plugs in (stand-in for a RADIO/DINOv2 export)."""
    net = torch.nn.Sequential(torch.nn.Conv2d(3, 12, 14, stride=14))
    path = tmp_path / "enc.pt2"
    torch.export.save(torch.export.export(net, (torch.rand(2, 3, 64, 128),)), str(path))
    cfg = BackboneConfig(kind="external", external_path=str(path), external_dim=12, input_height=64,
                         input_width=128, feature_dim=16)
    y = ExternalBackbone(cfg)(torch.rand(2, 3, 64, 128))
    assert y.shape == (2, 16, 8, 16)

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/model_export/conftest.py
