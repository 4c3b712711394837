"""Building blocks of the cylinder-plane networks (YNet_occ, XNet_vol, YNet_pix).

All 2-D maps here are cylinder planes ``[B, C, H_u, W_u]``: W is the angle theta and wraps around, so every
3x3 convolution pads W circularly and H with zeros (``CylConv``). Flipping a plane along W (``flip_w``)
reverses the direction of theta and keeps it periodic, so the circular padding stays correct after a flip.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from .config import UNetConfig


def flip_w(x: torch.Tensor) -> torch.Tensor:
    """Horizontal flip kappa(.) of a cylinder plane [B, C, H, W] (theta -> -theta)."""
    return torch.flip(x, dims=[-1])


def groups_for(c: int, max_groups: int = 8) -> int:
    g = min(max_groups, c)
    while c % g:
        g -= 1
    return g


class CylConv(nn.Module):
    """k x k convolution on a cylinder plane: circular padding along W (theta), zero padding along H."""

    def __init__(self, cin: int, cout: int, k: int = 3, stride: int = 1, bias: bool = True):
        super().__init__()
        self.p = k // 2
        self.conv = nn.Conv2d(cin, cout, k, stride=stride, padding=(self.p, 0), bias=bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.p:
            x = torch.cat([x[..., -self.p:], x, x[..., : self.p]], dim=-1)  # circular along W (ONNX-friendly)
        return self.conv(x)


class ResBlock(nn.Module):
    """Pre-activation ResNet block (GroupNorm, SiLU, cylinder convs) with a 1x1 skip when widths differ."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.n1 = nn.GroupNorm(groups_for(cin), cin)
        self.c1 = CylConv(cin, cout)
        self.n2 = nn.GroupNorm(groups_for(cout), cout)
        self.c2 = CylConv(cout, cout)
        self.skip = nn.Conv2d(cin, cout, 1) if cin != cout else nn.Identity()

    def forward(self, x):
        h = self.c1(F.silu(self.n1(x)))
        h = self.c2(F.silu(self.n2(h)))
        return self.skip(x) + h


class EMA(nn.Module):
    """Efficient Multi-scale Attention (Ouyang et al., ICASSP 2023), written from the paper's description.

    Channels are split into ``groups`` sub-features. Branch 1: 1-D average pools along H and along W, a shared
    1x1 conv, sigmoid gates re-weighting the input (coordinate-attention style), then GroupNorm. Branch 2: a
    3x3 conv. Cross-spatial learning: each branch's globally pooled channel descriptor (softmax over channels)
    is matched against the other branch's spatial map; the sum of both matchings, through a sigmoid, is a
    per-pixel weight applied to the group's input.
    """

    def __init__(self, channels: int, groups: int = 8):
        super().__init__()
        if channels % groups:
            raise ValueError(f"EMA: channels {channels} not divisible by groups {groups}")
        self.g = groups
        c = channels // groups
        self.conv1 = nn.Conv2d(c, c, 1)
        self.conv3 = CylConv(c, c, 3)
        self.gn = nn.GroupNorm(c, c)

    def forward(self, x):
        b, ch, h, w = x.shape
        gx = x.reshape(b * self.g, ch // self.g, h, w)
        xh = gx.mean(dim=3, keepdim=True)                       # [bg, c, h, 1]
        xw = gx.mean(dim=2, keepdim=True).transpose(2, 3)       # [bg, c, w, 1]
        hw = self.conv1(torch.cat([xh, xw], dim=2))
        ah, aw = torch.split(hw, [h, w], dim=2)
        x1 = self.gn(gx * ah.sigmoid() * aw.transpose(2, 3).sigmoid())
        x2 = self.conv3(gx)
        c = ch // self.g
        d1 = torch.softmax(x1.mean(dim=(2, 3)), dim=-1).unsqueeze(1)   # [bg, 1, c]
        d2 = torch.softmax(x2.mean(dim=(2, 3)), dim=-1).unsqueeze(1)
        m = d1 @ x2.reshape(-1, c, h * w) + d2 @ x1.reshape(-1, c, h * w)   # [bg, 1, hw]
        wgt = m.reshape(-1, 1, h, w).sigmoid()
        return (gx * wgt).reshape(b, ch, h, w)


class MHA(nn.Module):
    """Plain multi-head self-attention over all positions of the plane (residual, pre-norm)."""

    def __init__(self, channels: int, heads: int = 4):
        super().__init__()
        self.norm = nn.GroupNorm(groups_for(channels), channels)
        self.attn = nn.MultiheadAttention(channels, heads, batch_first=True)

    def forward(self, x):
        b, c, h, w = x.shape
        t = self.norm(x).flatten(2).transpose(1, 2)
        y, _ = self.attn(t, t, t, need_weights=False)
        return x + y.transpose(1, 2).reshape(b, c, h, w)


def make_attention(kind: str, c: int, cfg: UNetConfig) -> nn.Module:
    if kind == "ema":
        return EMA(c, groups_for(c, cfg.ema_groups))
    if kind == "mha":
        return MHA(c, cfg.heads)
    return nn.Identity()


class Stage(nn.Module):
    """``n`` x (ResBlock + attention)."""

    def __init__(self, cin: int, cout: int, n: int, attn: str, cfg: UNetConfig):
        super().__init__()
        layers = []
        for i in range(n):
            layers += [ResBlock(cin if i == 0 else cout, cout), make_attention(attn, cout, cfg)]
        self.body = nn.Sequential(*layers)

    def forward(self, x):
        return self.body(x)


class Encoder(nn.Module):
    """U-Net encoder: one Stage per level, stride-2 cylinder conv between levels. Returns all levels."""

    def __init__(self, cin: int, cfg: UNetConfig):
        super().__init__()
        d = cfg.down_dims
        self.stem = CylConv(cin, d[0])
        # plain attention is quadratic in positions: only at the lowest resolution
        attn = [cfg.attention if (cfg.attention != "mha" or i == len(d) - 1) else "none" for i in range(len(d))]
        self.stages = nn.ModuleList(Stage(d[max(i - 1, 0)], d[i], cfg.blocks_per_res, attn[i], cfg)
                                    for i in range(len(d)))
        self.downs = nn.ModuleList(CylConv(d[i], d[i], 3, stride=2) for i in range(len(d) - 1))

    def forward(self, x):
        feats = []
        x = self.stem(x)
        for i, st in enumerate(self.stages):
            if i:
                x = self.downs[i - 1](x)
            x = st(x)
            feats.append(x)
        return feats


class Decoder(nn.Module):
    """U-Net decoder: from the lowest level up, nearest 2x upsampling, concat skip, Stage(blocks + 1)."""

    def __init__(self, cfg: UNetConfig, out_dim: int):
        super().__init__()
        d, u = cfg.down_dims, cfg.up_dims
        L = len(d)
        self.stages = nn.ModuleList()
        cin = d[-1]
        for i in range(L):
            skip = d[L - 1 - i]
            attn = cfg.attention if (cfg.attention != "mha" or i == 0) else "none"
            self.stages.append(Stage(cin + skip, u[i], cfg.blocks_per_res + 1, attn, cfg))
            cin = u[i]
        self.out = nn.Sequential(nn.GroupNorm(groups_for(u[-1]), u[-1]), nn.SiLU(), nn.Conv2d(u[-1], out_dim, 1))

    def forward(self, feats):
        x = feats[-1]
        L = len(feats)
        for i, st in enumerate(self.stages):
            skip = feats[L - 1 - i]
            if x.shape[-2:] != skip.shape[-2:]:
                x = F.interpolate(x, size=skip.shape[-2:], mode="nearest")
            x = st(torch.cat([x, skip], dim=1))
        return self.out(x)


class DualEncoder(nn.Module):
    """Weight-shared dual-branch encoder (paper Fig. YNet/XNet left half).

    F+ goes in as is; F- is flipped along W before the encoder and every encoder level is flipped back before
    the two branches are fused (concat + 1x1 conv per level). Ablations: ``flips=False`` feeds F- unflipped;
    ``dual=False`` encodes F+ only (single branch, no fusion).
    """

    def __init__(self, cin: int, cfg: UNetConfig, flips: bool = True, dual: bool = True):
        super().__init__()
        self.enc = Encoder(cin, cfg)
        self.flips, self.dual = flips, dual
        self.fuse = nn.ModuleList(nn.Conv2d(2 * c, c, 1) for c in cfg.down_dims) if dual else None

    def forward(self, f_plus: torch.Tensor, f_minus: torch.Tensor) -> list[torch.Tensor]:
        a = self.enc(f_plus)
        if not self.dual:
            return a
        if self.flips:
            b = [flip_w(t) for t in self.enc(flip_w(f_minus))]
        else:
            b = self.enc(f_minus)
        return [fz(torch.cat([x, y], dim=1)) for fz, x, y in zip(self.fuse, a, b)]


class YNet(nn.Module):
    """Y-shaped network: dual encoder + single decoder -> [B, out_dim, H, W]."""

    def __init__(self, cin: int, cfg: UNetConfig, out_dim: int, flips: bool = True, dual: bool = True):
        super().__init__()
        self.encoder = DualEncoder(cin, cfg, flips, dual)
        self.decoder = Decoder(cfg, out_dim)

    def forward(self, f_plus, f_minus):
        return self.decoder(self.encoder(f_plus, f_minus))


class XNet(nn.Module):
    """X-shaped network: dual encoder + dual decoder -> (geometry [B, geo_dim, H, W], appearance [B, app_dim, H, W])."""

    def __init__(self, cin: int, cfg: UNetConfig, geo_dim: int, app_dim: int, flips: bool = True,
                 dual: bool = True):
        super().__init__()
        self.encoder = DualEncoder(cin, cfg, flips, dual)
        self.geo = Decoder(cfg, geo_dim)
        self.app = Decoder(cfg, app_dim)

    def forward(self, f_plus, f_minus):
        feats = self.encoder(f_plus, f_minus)
        return self.geo(feats), self.app(feats)


def mlp(cin: int, width: int, cout: int, layers: int, act=nn.SiLU) -> nn.Sequential:
    """``layers`` linear layers (cin -> width ... -> cout) with activations between."""
    mods: list[nn.Module] = []
    c = cin
    for i in range(layers - 1):
        mods += [nn.Linear(c, width), act()]
        c = width
    mods.append(nn.Linear(c, cout))
    return nn.Sequential(*mods)


def init_last_linear(seq: nn.Sequential, bias: torch.Tensor | None = None, gain: float = 0.1) -> None:
    """Small last-layer weights so initial Gaussians sit at their anchors with the given bias."""
    last = [m for m in seq.modules() if isinstance(m, nn.Linear)][-1]
    nn.init.normal_(last.weight, std=gain / math.sqrt(last.in_features))
    if bias is not None:
        with torch.no_grad():
            last.bias.copy_(bias)
