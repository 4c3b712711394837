"""Training losses of XYZCylinder (paper Sec. 3.4, appendix eq. "eq-loss" and "eq-loss2") and the optimiser.

Stage 1 (occupancy module):
    L_occ = w_sem * sem_scal + w_geo * geo_scal + w_ce * CE + w_bev * BEV          (0.02, 0.02, 0.1, 0.1)
Stage 2 (everything else, occupancy frozen):
    L = w_l1 * L1(I) + w_perc * perceptual(I) + w_sky * L1(A_fg, 1 - sky)
        + w_depth * L1(D_fg, D | valid, non-sky) + w_pear * (1 - PCC(D_fg, D | valid, non-sky))
                                                                        (1.0, 0.05, 0.5, 0.01, 0.01)
The perceptual term is LPIPS when local LPIPS weights are configured, else D-SSIM = (1 - SSIM) / 2.
Formulas, conventions and what is unavailable are documented in docs/training.md.

Tensor conventions (torch):
    class logits   [B, C, *S]  (C = 2 for occupancy: 0 empty, 1 occupied; S = (L_z, L_y, L_x) or (L_y, L_x))
    class targets  [B, *S]     int64, ``ignore_index`` (default 255) marks unknown voxels
    images         [B, 3, H, W] float in [0, 1]
    alpha, sky, depth, masks  [B, H, W]  (a singleton channel [B, 1, H, W] is accepted and squeezed)
    depth in metres along the optical axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import torch
import torch.nn.functional as F

from .config import ConfigError, _Frozen

IGNORE_INDEX = 255


# ----------------------------------------------------------------------------------------------- configs


def _nonneg(name: str, v) -> None:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not v >= 0 or not math.isfinite(v):
        raise ConfigError(f"{name}: must be a finite number >= 0, got {v!r}")


@dataclass(frozen=True)
class OccLossConfig(_Frozen):
    """Stage-1 weights (paper appendix table, 'Loss Weights') and label conventions."""

    sem: float = 0.02
    geo: float = 0.02
    ce: float = 0.1
    bev: float = 0.1
    ignore_index: int = IGNORE_INDEX
    empty_class: int = 0
    ce_class_weights: tuple[float, ...] | None = None   # per-class CE weights (None: uniform)

    def __post_init__(self):
        for n in ("sem", "geo", "ce", "bev"):
            _nonneg(n, getattr(self, n))
        if self.ce_class_weights is not None:
            object.__setattr__(self, "ce_class_weights", tuple(self.ce_class_weights))  # JSON lists
            for i, w in enumerate(self.ce_class_weights):
                _nonneg(f"ce_class_weights[{i}]", w)


@dataclass(frozen=True)
class RenderLossConfig(_Frozen):
    """Stage-2 weights (paper appendix table) and the optional local LPIPS weights."""

    l1: float = 1.0
    perceptual: float = 0.05
    sky: float = 0.5
    depth: float = 0.01
    pearson: float = 0.01
    lpips_net: str = "vgg"                 # "vgg" or "alex"
    lpips_backbone_path: str | None = None  # torchvision-layout state dict of VGG16 / AlexNet ``features``
    lpips_lin_path: str | None = None       # LPIPS v0.1 linear-layer state dict (lin0..lin4 / lin0..lin4)

    def __post_init__(self):
        for n in ("l1", "perceptual", "sky", "depth", "pearson"):
            _nonneg(n, getattr(self, n))
        if self.lpips_net not in ("vgg", "alex"):
            raise ConfigError(f"lpips_net: must be 'vgg' or 'alex', got {self.lpips_net!r}")
        if (self.lpips_backbone_path is None) != (self.lpips_lin_path is None):
            raise ConfigError("lpips_backbone_path: give both lpips_backbone_path and lpips_lin_path, or neither")


@dataclass(frozen=True)
class OptimConfig(_Frozen):
    """AdamW + linear warm-up + cosine decay + gradient clipping (paper appendix 'Training Details')."""

    lr: float = 1e-4
    weight_decay: float = 0.01
    betas: tuple[float, float] = (0.9, 0.999)
    eps: float = 1e-8
    warmup_steps: int = 1000
    total_steps: int = 100_000
    min_lr_ratio: float = 0.0   # cosine floor as a fraction of lr
    grad_clip: float = 1.0      # max global L2 norm; 0 disables

    def __post_init__(self):
        if not (isinstance(self.lr, (int, float)) and self.lr > 0):
            raise ConfigError(f"lr: must be > 0, got {self.lr!r}")
        _nonneg("weight_decay", self.weight_decay)
        if len(self.betas) != 2 or not all(0 <= b < 1 for b in self.betas):
            raise ConfigError(f"betas: must be two numbers in [0, 1), got {self.betas!r}")
        if isinstance(self.warmup_steps, bool) or not isinstance(self.warmup_steps, int) or self.warmup_steps < 0:
            raise ConfigError(f"warmup_steps: must be an integer >= 0, got {self.warmup_steps!r}")
        if isinstance(self.total_steps, bool) or not isinstance(self.total_steps, int) or self.total_steps < 1:
            raise ConfigError(f"total_steps: must be an integer >= 1, got {self.total_steps!r}")
        if not 0 <= self.min_lr_ratio <= 1:
            raise ConfigError(f"min_lr_ratio: must be in [0, 1], got {self.min_lr_ratio!r}")
        _nonneg("grad_clip", self.grad_clip)


@dataclass(frozen=True)
class TrainLossConfig(_Frozen):
    occ: OccLossConfig = field(default_factory=OccLossConfig)
    render: RenderLossConfig = field(default_factory=RenderLossConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)


# ------------------------------------------------------------------------------------- stage 1: occupancy


def _bce_to_one(x: torch.Tensor) -> torch.Tensor:
    """BCE(x, 1) = -log(x), with torch's BCE clamp of log at -100; x is clamped into [0, 1] first because
    ratios of sums can exceed 1 by rounding."""
    return F.binary_cross_entropy(x.clamp(0.0, 1.0), torch.ones_like(x))


def ce_loss(logits: torch.Tensor, target: torch.Tensor, ignore_index: int = IGNORE_INDEX,
            class_weights: torch.Tensor | None = None) -> torch.Tensor:
    """Cross-entropy averaged over the non-ignored elements (weighted mean when ``class_weights`` is given,
    as torch defines it). logits [B, C, *S], target [B, *S] int. Returns 0 when every element is ignored."""
    valid = target != ignore_index
    if not bool(valid.any()):
        return logits.sum() * 0.0
    return F.cross_entropy(logits, target.long(), weight=class_weights, ignore_index=ignore_index)


def sem_scal_loss(logits: torch.Tensor, target: torch.Tensor, ignore_index: int = IGNORE_INDEX) -> torch.Tensor:
    """MonoScene's semantic scene-class affinity loss.

    With p_i the softmax probability of class c at valid voxel i and y_i = [target_i == c], for every class c
    present in the (valid) target:
        P_c = sum p_i y_i / sum p_i,  R_c = sum p_i y_i / sum y_i,  S_c = sum (1 - p_i)(1 - y_i) / sum (1 - y_i)
        L_c = BCE(P_c, 1) + BCE(R_c, 1) + BCE(S_c, 1)   (a term is skipped where its denominator is 0)
    and the loss is the mean of L_c over the present classes (0 if none). Sums run over all valid voxels of
    the batch together.
    """
    probs = F.softmax(logits, dim=1)
    valid = target != ignore_index
    total = logits.sum() * 0.0
    count = 0
    for c in range(logits.shape[1]):
        p = probs[:, c][valid]
        y = (target[valid] == c).to(p.dtype)
        if not bool(y.sum() > 0):
            continue
        count += 1
        tp = (p * y).sum()
        if bool(p.sum() > 0):
            total = total + _bce_to_one(tp / p.sum())
        total = total + _bce_to_one(tp / y.sum())
        neg = (1 - y).sum()
        if bool(neg > 0):
            total = total + _bce_to_one(((1 - p) * (1 - y)).sum() / neg)
    return total / count if count else total


def geo_scal_loss(logits: torch.Tensor, target: torch.Tensor, ignore_index: int = IGNORE_INDEX,
                  empty_class: int = 0) -> torch.Tensor:
    """MonoScene's geometric scene-class affinity loss on occupied-vs-empty.

    q_i = 1 - softmax(logits)_empty (probability voxel i is occupied), y_i = [target_i != empty]:
        P = sum q y / sum q,  R = sum q y / sum y,  S = sum (1 - q)(1 - y) / sum (1 - y)
        L = BCE(P, 1) + BCE(R, 1) + BCE(S, 1)   over valid voxels (a term is skipped where its denominator is 0)
    """
    probs = F.softmax(logits, dim=1)
    valid = target != ignore_index
    empty = probs[:, empty_class][valid]
    q = 1 - empty
    y = (target[valid] != empty_class).to(q.dtype)
    total = logits.sum() * 0.0
    tp = (q * y).sum()
    if bool(q.sum() > 0):
        total = total + _bce_to_one(tp / q.sum())
    if bool(y.sum() > 0):
        total = total + _bce_to_one(tp / y.sum())
    if bool((1 - y).sum() > 0):
        total = total + _bce_to_one((empty * (1 - y)).sum() / (1 - y).sum())
    return total


def bev_target_from_occupancy(occ: torch.Tensor, ignore_index: int = IGNORE_INDEX,
                              empty_class: int = 0) -> torch.Tensor:
    """BEV occupancy labels from a voxel label grid: occ [..., L_z, L_y, L_x] int -> [..., L_y, L_x] int64.

    A column is 1 (occupied) if any of its voxels is non-empty and known, 0 if all its voxels are known
    empty, and ``ignore_index`` otherwise (only unknown / empty voxels, at least one unknown)."""
    known = occ != ignore_index
    occupied = (known & (occ != empty_class)).any(dim=-3)
    all_known = known.all(dim=-3)
    out = torch.full(occupied.shape, ignore_index, dtype=torch.long, device=occ.device)
    out[all_known] = 0
    out[occupied] = 1
    return out


def bev_loss(bev_logits: torch.Tensor, bev_target: torch.Tensor, ignore_index: int = IGNORE_INDEX,
             class_weights: torch.Tensor | None = None) -> torch.Tensor:
    """BEV loss: 2-class softmax cross-entropy on the BEV occupancy map (FastOcc supervises its BEV plane with
    a per-cell classification loss; we use plain CE on empty / occupied columns).
    bev_logits [B, 2, L_y, L_x], bev_target [B, L_y, L_x] int (see ``bev_target_from_occupancy``)."""
    return ce_loss(bev_logits, bev_target, ignore_index, class_weights)


def occupancy_loss(occ_logits: torch.Tensor, bev_logits: torch.Tensor, occ_target: torch.Tensor,
                   cfg: OccLossConfig = OccLossConfig(),
                   bev_target: torch.Tensor | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """Stage-1 total. occ_logits [B, C, L_z, L_y, L_x], bev_logits [B, 2, L_y, L_x], occ_target [B, L_z, L_y, L_x]
    (an unbatched [C, L_z, L_y, L_x] / [2, L_y, L_x] / [L_z, L_y, L_x] triple is accepted). ``bev_target``
    defaults to ``bev_target_from_occupancy(occ_target)``. Returns (loss, {term: value}) with unweighted terms."""
    if occ_logits.dim() == 4:
        occ_logits, bev_logits, occ_target = occ_logits[None], bev_logits[None], occ_target[None]
        if bev_target is not None and bev_target.dim() == 2:
            bev_target = bev_target[None]
    if bev_target is None:
        bev_target = bev_target_from_occupancy(occ_target, cfg.ignore_index, cfg.empty_class)
    w = None
    if cfg.ce_class_weights is not None:
        w = torch.tensor(cfg.ce_class_weights, dtype=occ_logits.dtype, device=occ_logits.device)
    parts = {
        "sem": sem_scal_loss(occ_logits, occ_target, cfg.ignore_index),
        "geo": geo_scal_loss(occ_logits, occ_target, cfg.ignore_index, cfg.empty_class),
        "ce": ce_loss(occ_logits, occ_target, cfg.ignore_index, w),
        "bev": bev_loss(bev_logits, bev_target, cfg.ignore_index),
    }
    total = cfg.sem * parts["sem"] + cfg.geo * parts["geo"] + cfg.ce * parts["ce"] + cfg.bev * parts["bev"]
    return total, {k: float(v.detach()) for k, v in parts.items()}


# ---------------------------------------------------------------------------------------- stage 2: render


def _hw(x: torch.Tensor) -> torch.Tensor:
    """[B, 1, H, W] -> [B, H, W]; [B, H, W] unchanged."""
    return x[:, 0] if x.dim() == 4 and x.shape[1] == 1 else x


def _masked_mean(x: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    if mask is None:
        return x.mean()
    m = mask.to(x.dtype)
    n = m.sum()
    return (x * m).sum() / n if bool(n > 0) else x.sum() * 0.0


def l1_image_loss(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """mean |pred - target| over pixels and channels; pred/target [B, 3, H, W], mask [B, H, W] (optional)."""
    err = (pred - target).abs().mean(dim=1)
    return _masked_mean(err, mask)


def gaussian_window(size: int = 11, sigma: float = 1.5, dtype=torch.float32) -> torch.Tensor:
    """Normalised 1-D Gaussian [size], centred (the SSIM window of Wang et al. is its outer product)."""
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-0.5 * (x / sigma) ** 2)
    return (g / g.sum()).to(dtype)


def ssim_map(pred: torch.Tensor, target: torch.Tensor, data_range: float = 1.0, size: int = 11,
             sigma: float = 1.5, k1: float = 0.01, k2: float = 0.03) -> torch.Tensor:
    """Per-window SSIM (Wang et al. 2004), Gaussian window, population (co)variances, 'valid' windows only.
    pred/target [B, C, H, W] with H, W >= size -> [B, C, H - size + 1, W - size + 1]."""
    if pred.shape[-1] < size or pred.shape[-2] < size:
        raise ValueError(f"image: SSIM needs at least {size}x{size} pixels, got {tuple(pred.shape[-2:])}")
    C = pred.shape[1]
    g = gaussian_window(size, sigma, pred.dtype).to(pred.device)
    gx = g.view(1, 1, 1, size).repeat(C, 1, 1, 1)
    gy = g.view(1, 1, size, 1).repeat(C, 1, 1, 1)

    def blur(x):
        return F.conv2d(F.conv2d(x, gx, groups=C), gy, groups=C)

    mu_x, mu_y = blur(pred), blur(target)
    sxx = blur(pred * pred) - mu_x * mu_x
    syy = blur(target * target) - mu_y * mu_y
    sxy = blur(pred * target) - mu_x * mu_y
    c1, c2 = (k1 * data_range) ** 2, (k2 * data_range) ** 2
    return ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x ** 2 + mu_y ** 2 + c1) * (sxx + syy + c2))


def dssim_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """D-SSIM = (1 - mean SSIM) / 2, in [0, 1]; pred/target [B, 3, H, W] in [0, 1]."""
    return (1 - ssim_map(pred, target).mean()) / 2


def sky_loss(alpha_fg: torch.Tensor, sky: torch.Tensor) -> torch.Tensor:
    """L1 between the foreground alpha and its target 1 - sky (sky = 1 on sky pixels). [B, H, W] each."""
    return (_hw(alpha_fg) - (1 - _hw(sky).to(alpha_fg.dtype))).abs().mean()


def depth_l1_loss(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """mean |D_pred - D| over mask (valid, non-sky pixels), metres. [B, H, W] each; 0 if the mask is empty."""
    return _masked_mean((_hw(pred) - _hw(target)).abs(), _hw(mask))


def pearson_depth_loss(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor,
                       eps: float = 1e-8) -> torch.Tensor:
    """SparseGS Pearson depth loss: mean over images of 1 - PCC(D_pred, D) over that image's masked pixels.
    Images with fewer than 2 masked pixels are skipped (0 if none is left). [B, H, W] each.
    ``eps`` keeps the denominator finite for a constant map (then PCC ~ 0 and the loss ~ 1)."""
    pred, target, mask = _hw(pred), _hw(target), _hw(mask).bool()
    losses = []
    for b in range(pred.shape[0]):
        m = mask[b]
        if int(m.sum()) < 2:
            continue
        x = pred[b][m]
        y = target[b][m].to(x.dtype)
        xc, yc = x - x.mean(), y - y.mean()
        pcc = (xc * yc).sum() / torch.sqrt((xc * xc).sum() * (yc * yc).sum() + eps)
        losses.append(1 - pcc)
    return torch.stack(losses).mean() if losses else pred.sum() * 0.0


# ---------------------------------------------------------------------------------------------- LPIPS

_LPIPS_SHIFT = (-0.030, -0.088, -0.188)   # LPIPS ScalingLayer constants (input in [-1, 1])
_LPIPS_SCALE = (0.458, 0.448, 0.450)
# torchvision ``features`` layouts: (kind, out_channels or None, kernel, stride, padding); 'M' = max pool.
_VGG16 = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512]
_VGG16_TAPS = (3, 8, 15, 22, 29)           # relu1_2, relu2_2, relu3_3, relu4_3, relu5_3 (features indices)
_ALEX = [(64, 11, 4, 2), "M", (192, 5, 1, 2), "M", (384, 3, 1, 1), (256, 3, 1, 1), (256, 3, 1, 1)]
_ALEX_TAPS = (1, 4, 7, 9, 11)              # relu1..relu5


class LPIPSUnavailable(RuntimeError):
    """No local LPIPS weights: the caller reports LPIPS as unavailable (never estimated)."""


class LPIPS(torch.nn.Module):
    """LPIPS v0.1 (Zhang et al. 2018) built from local files only.

    backbone_path: state dict of torchvision's ``vgg16().features`` / ``alexnet().features`` (keys ``N.weight``,
    ``N.bias``; a ``features.`` prefix is stripped). lin_path: the LPIPS linear layers (keys
    ``lin{k}.model.1.weight`` [1, C_k, 1, 1], as the ``lpips`` package ships them). Distance per image:
        sum_l mean_{h,w} || w_l * (f_l(x)/|f_l(x)| - f_l(y)/|f_l(y)|) ||^2,  inputs in [0, 1] mapped to [-1, 1].
    """

    def __init__(self, backbone_path: str | Path, lin_path: str | Path, net: str = "vgg"):
        super().__init__()
        for name, p in (("lpips_backbone_path", backbone_path), ("lpips_lin_path", lin_path)):
            if not Path(p).is_file():
                raise LPIPSUnavailable(f"{name}: no such file {str(p)!r}")
        layers: list[torch.nn.Module] = []
        chans: list[int] = []
        cin = 3
        if net == "vgg":
            for v in _VGG16:
                if v == "M":
                    layers.append(torch.nn.MaxPool2d(2, 2))
                else:
                    layers += [torch.nn.Conv2d(cin, v, 3, padding=1), torch.nn.ReLU()]
                    cin = v
            taps = _VGG16_TAPS
        elif net == "alex":
            for v in _ALEX:
                if v == "M":
                    layers.append(torch.nn.MaxPool2d(3, 2))
                else:
                    cout, k, s, p = v
                    layers += [torch.nn.Conv2d(cin, cout, k, s, p), torch.nn.ReLU()]
                    cin = cout
            taps = _ALEX_TAPS
        else:
            raise ConfigError(f"lpips_net: must be 'vgg' or 'alex', got {net!r}")
        self.features = torch.nn.Sequential(*layers)
        self.taps = taps
        for t in taps:
            chans.append(self.features[t - 1].out_channels)
        sd = torch.load(backbone_path, map_location="cpu", weights_only=True)
        sd = {k.removeprefix("features."): v for k, v in sd.items()}
        try:
            self.features.load_state_dict(sd)
        except RuntimeError as e:
            raise LPIPSUnavailable(f"lpips_backbone_path: not a {net} features state dict ({e})") from None
        lin = torch.load(lin_path, map_location="cpu", weights_only=True)
        self.lins = torch.nn.ParameterList()
        for k, c in enumerate(chans):
            key = f"lin{k}.model.1.weight"
            if key not in lin or tuple(lin[key].shape) != (1, c, 1, 1):
                raise LPIPSUnavailable(f"lpips_lin_path: missing or mis-shaped {key} (want [1, {c}, 1, 1])")
            self.lins.append(torch.nn.Parameter(lin[key].float(), requires_grad=False))
        self.register_buffer("shift", torch.tensor(_LPIPS_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_LPIPS_SCALE).view(1, 3, 1, 1))
        for p in self.parameters():
            p.requires_grad_(False)
        self.eval()

    def _feats(self, x: torch.Tensor) -> list[torch.Tensor]:
        x = ((2 * x - 1) - self.shift) / self.scale
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in self.taps:
                out.append(x)
            if i >= self.taps[-1]:
                break
        return out

    def forward(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """pred/target [B, 3, H, W] in [0, 1] -> [B] distances."""
        d = 0.0
        for fa, fb, w in zip(self._feats(pred), self._feats(target), self.lins):
            na = fa / (fa.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            nb = fb / (fb.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            d = d + ((na - nb) ** 2 * w).sum(1).mean(dim=(1, 2))
        return d  # type: ignore[return-value]


def load_lpips(cfg: RenderLossConfig) -> LPIPS | None:
    """The LPIPS network when both local paths are configured, else None (D-SSIM fallback)."""
    if cfg.lpips_backbone_path is None:
        return None
    return LPIPS(cfg.lpips_backbone_path, cfg.lpips_lin_path, cfg.lpips_net)  # type: ignore[arg-type]


# ------------------------------------------------------------------------------------------- stage-2 total


def render_loss(pred_rgb: torch.Tensor, target_rgb: torch.Tensor, alpha_fg: torch.Tensor, sky: torch.Tensor,
                pred_depth: torch.Tensor, target_depth: torch.Tensor, depth_valid: torch.Tensor | None = None,
                cfg: RenderLossConfig = RenderLossConfig(),
                lpips: LPIPS | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """Stage-2 total (eq-loss2). pred_rgb/target_rgb [B, 3, H, W] in [0, 1]; alpha_fg [B, H, W] (foreground
    alpha of the splats); sky [B, H, W] (1 = sky); pred_depth (foreground depth) / target_depth [B, H, W] metres;
    depth_valid [B, H, W] bool (default: target_depth finite and > 0). Depth terms use valid & ~sky pixels.
    The perceptual term is LPIPS when ``lpips`` is given, else D-SSIM. Returns (loss, unweighted terms)."""
    sky_b = _hw(sky) > 0.5
    tdepth = _hw(target_depth)
    if depth_valid is None:
        depth_valid = torch.isfinite(tdepth) & (tdepth > 0)
    dmask = _hw(depth_valid).bool() & ~sky_b
    tdepth = torch.where(dmask, tdepth, torch.zeros_like(tdepth))   # NaN/inf outside the mask never reach grads
    perc = lpips(pred_rgb, target_rgb).mean() if lpips is not None else dssim_loss(pred_rgb, target_rgb)
    parts = {
        "l1": l1_image_loss(pred_rgb, target_rgb),
        "perceptual": perc,
        "sky": sky_loss(alpha_fg, sky),
        "depth": depth_l1_loss(pred_depth, tdepth, dmask),
        "pearson": pearson_depth_loss(pred_depth, tdepth, dmask),
    }
    total = (cfg.l1 * parts["l1"] + cfg.perceptual * parts["perceptual"] + cfg.sky * parts["sky"]
             + cfg.depth * parts["depth"] + cfg.pearson * parts["pearson"])
    return total, {k: float(v.detach()) for k, v in parts.items()}


# -------------------------------------------------------------------------------------------- optimiser


def lr_factor(step: int, cfg: OptimConfig) -> float:
    """Multiplier of cfg.lr at optimiser step ``step`` (0-based): linear warm-up (step+1)/warmup_steps, then
    cosine from 1 to min_lr_ratio at total_steps (held there afterwards)."""
    if step < cfg.warmup_steps:
        return (step + 1) / cfg.warmup_steps
    span = max(1, cfg.total_steps - cfg.warmup_steps)
    t = min(1.0, (step - cfg.warmup_steps) / span)
    return cfg.min_lr_ratio + (1 - cfg.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * t))


def build_optimizer(params, cfg: OptimConfig = OptimConfig()
                    ) -> tuple[torch.optim.AdamW, torch.optim.lr_scheduler.LambdaLR]:
    """AdamW over the trainable ``params`` and its warm-up + cosine LambdaLR (call scheduler.step() after
    each optimiser.step())."""
    params = [p for p in params if p.requires_grad]
    if not params:
        raise ValueError("params: nothing to optimise (no parameter requires grad)")
    opt = torch.optim.AdamW(params, lr=cfg.lr, betas=tuple(cfg.betas), eps=cfg.eps,
                            weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: lr_factor(s, cfg))
    return opt, sched


def clip_gradients(params, cfg: OptimConfig) -> float:
    """Clip the global gradient L2 norm to cfg.grad_clip (no-op when 0); returns the norm before clipping."""
    params = [p for p in params if p.grad is not None]
    if not params:
        return 0.0
    if cfg.grad_clip <= 0:
        return float(torch.norm(torch.stack([p.grad.detach().norm() for p in params])))
    return float(torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip))
