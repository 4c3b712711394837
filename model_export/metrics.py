"""Evaluation metrics (paper appendix "Overview of Evaluation Metrics"), numpy only.

    psnr(pred, target)            dB, data range 1 (images float in [0, 1])
    psnr_masked(pred, target, m)  the same over the pixels where m is True (eval: non-sky pixels)
    mean_colour_error(pred, t)    mean over channels of |mean colour of pred - mean colour of target|
    ssim(pred, target)            Wang et al. 2004: 11x11 Gaussian window (sigma 1.5), K1 0.01, K2 0.03,
                                  population (co)variances, mean over valid windows, then over channels
    depth_pcc(pred, gt, valid)    Pearson correlation over valid pixels
    occupancy_iou / semantic_miou voxel IoU of the occupied class / mean IoU over classes
    lpips(pred, target, ...)      only with local weights; otherwise (None, reason) — never estimated

torch is imported only by ``lpips`` when weights are given. Definitions are in docs/training.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _check_pair(pred: np.ndarray, target: np.ndarray, name: str = "pred") -> tuple[np.ndarray, np.ndarray]:
    pred = np.asarray(pred, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    if pred.shape != target.shape:
        raise ValueError(f"{name}: shape {pred.shape} differs from target {target.shape}")
    if not (np.isfinite(pred).all() and np.isfinite(target).all()):
        raise ValueError(f"{name}: images contain NaN or inf")
    return pred, target


def psnr(pred: np.ndarray, target: np.ndarray, data_range: float = 1.0) -> float:
    """PSNR = 10 log10(L^2 / MSE) in dB over all pixels and channels. pred/target [H, W, C] or [H, W] in
    [0, data_range]. Identical images give inf."""
    pred, target = _check_pair(pred, target)
    mse = float(np.mean((pred - target) ** 2))
    return float("inf") if mse == 0 else float(10 * np.log10(data_range ** 2 / mse))


def _pixel_mask(mask: np.ndarray | None, pred: np.ndarray) -> np.ndarray:
    """The [H, W] bool pixel mask for channels-last ``pred`` [H, W, C] (None: every pixel)."""
    if pred.ndim != 3:
        raise ValueError(f"pred: need [H, W, C] (channels last), got shape {pred.shape}")
    if mask is None:
        return np.ones(pred.shape[:2], dtype=bool)
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != pred.shape[:2]:
        raise ValueError(f"mask: shape {mask.shape} differs from the image's {pred.shape[:2]}")
    return mask


def psnr_masked(pred: np.ndarray, target: np.ndarray, mask: np.ndarray, data_range: float = 1.0) -> float:
    """PSNR = 10 log10(L^2 / MSE) in dB with the MSE over the pixels where ``mask`` is True, all channels.
    pred/target [H, W, C] (channels last, in [0, data_range]); mask [H, W] bool. Identical masked pixels give
    inf; an empty mask gives NaN. Evaluation uses it over the target's non-sky pixels (sky < 0.5)."""
    pred, target = _check_pair(pred, target)
    mask = _pixel_mask(mask, pred)
    if not mask.any():
        return float("nan")
    return psnr(pred[mask], target[mask], data_range)


# seen_by_inputs: a target point counts as seen where an input camera's depth at the point's pixel agrees with
# the point's own depth to SEEN_REL_TOL * depth + SEEN_ABS_TOL. Why these: the lookup is at whole pixels (the 4
# around the projection), so on a slanted surface the looked-up depth differs from the point's by up to one
# pixel's depth step, which on the ground seen at grazing angles is a few per cent of the depth (d^2 / (h f):
# 1.6 % at 30 m for a 1.5 m high camera with f = 1266 px); 5 % covers it at half the input resolution too. The
# 0.2 m term covers near surfaces, where the step is small in metres but the depth maps' own rounding is not.
SEEN_REL_TOL = 0.05
SEEN_ABS_TOL = 0.2   # metres


def seen_by_inputs(depth: np.ndarray, K: np.ndarray, cam_to_ego: np.ndarray, input_depth: np.ndarray,
                   input_cameras, rel_tol: float = SEEN_REL_TOL, abs_tol: float = SEEN_ABS_TOL) -> np.ndarray:
    """[H, W] bool: the target pixels whose surface some input camera sees.

    depth [H, W] metres along the target's optical axis (0 / non-finite: no surface, e.g. sky: never seen);
    K [3, 3] pixels; cam_to_ego [4, 4] OpenCV camera -> ego, metres. input_depth [N, h, w] metres as each input
    camera measures it (``Camera.project``'s z: optical axis, or distance for equirectangular; 0 / non-finite:
    unknown); input_cameras: the N ``runtime.rig.Camera`` of the rig (their own projection, distortion included).
    Pixel (u, v) (integer pixel centres) with depth z is the ego point cam_to_ego @ [z inv(K) [u, v, 1], 1]. It
    is seen when, for some input camera, it lies in front of that camera, projects inside its image, and one of
    the 4 input pixels around the projection holds a depth within ``rel_tol * z_in + abs_tol`` of the point's
    depth z_in in that camera (not occluded, not beyond what that camera saw). Evaluation uses it to split a
    target's error into what the rig saw and what no camera of it saw (a rig's blind sector, the ego car)."""
    depth = np.asarray(depth, np.float64)
    input_depth = np.asarray(input_depth, np.float64)
    if depth.ndim != 2:
        raise ValueError(f"depth: need [H, W], got shape {depth.shape}")
    if input_depth.ndim != 3 or len(input_cameras) != len(input_depth):
        raise ValueError(f"input_depth: need [N, h, w] for N input_cameras, got shape {input_depth.shape} for "
                         f"{len(input_cameras)} cameras")
    has = np.isfinite(depth) & (depth > 0)
    v, u = np.nonzero(has)
    z = depth[has]
    rays = np.stack([u, v, np.ones_like(u)], -1).astype(np.float64) @ np.linalg.inv(K).T
    cam_to_ego = np.asarray(cam_to_ego, np.float64)
    pts = (rays * z[:, None]) @ cam_to_ego[:3, :3].T + cam_to_ego[:3, 3]            # [P, 3] ego
    seen = np.zeros(len(z), bool)
    for d_in, cam in zip(input_depth, input_cameras):
        rest = np.nonzero(~seen)[0]
        uv, zc, front = cam.project(pts[rest])
        ih, iw = d_in.shape
        tol = rel_tol * zc + abs_tol
        hit = np.zeros(len(rest), bool)
        for cu in (np.floor(uv[:, 0]), np.ceil(uv[:, 0])):
            for cv in (np.floor(uv[:, 1]), np.ceil(uv[:, 1])):
                inside = front & (cu >= 0) & (cu <= iw - 1) & (cv >= 0) & (cv <= ih - 1)
                dz = np.zeros(len(rest))
                dz[inside] = d_in[cv[inside].astype(int), cu[inside].astype(int)]
                hit |= inside & np.isfinite(dz) & (dz > 0) & (np.abs(dz - zc) <= tol)
        seen[rest[hit]] = True
    out = np.zeros(depth.shape, bool)
    out[v, u] = seen
    return out


def mean_colour_error(pred: np.ndarray, target: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean colour error: mean over the C channels of |mean_pred - mean_target|, where mean_x is the image's
    mean colour (a C-vector, the mean over the pixels where ``mask`` is True; all pixels without a mask).
    pred/target [H, W, 3] float in [0, 1] (channels last); mask [H, W] bool or None. Units: [0, 1] intensity
    (0 = same mean colour). NaN for an empty mask. Blind to blur and structure (a flat image of the target's
    mean colour scores 0); it catches a colour cast, e.g. a grey image standing in for a coloured scene."""
    pred, target = _check_pair(pred, target)
    mask = _pixel_mask(mask, pred)
    if not mask.any():
        return float("nan")
    return float(np.mean(np.abs(pred[mask].mean(axis=0) - target[mask].mean(axis=0))))


def _gauss1d(size: int, sigma: float) -> np.ndarray:
    x = np.arange(size, dtype=np.float64) - (size - 1) / 2
    g = np.exp(-0.5 * (x / sigma) ** 2)
    return g / g.sum()


def _filter_valid(img: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Separable 'valid' correlation of [H, W] with the window g ⊗ g -> [H - n + 1, W - n + 1]."""
    n = g.size
    rows = np.lib.stride_tricks.sliding_window_view(img, n, axis=1) @ g          # [H, W - n + 1]
    return np.lib.stride_tricks.sliding_window_view(rows, n, axis=0) @ g         # [H - n + 1, W - n + 1]


def ssim(pred: np.ndarray, target: np.ndarray, data_range: float = 1.0, win_size: int = 11,
         sigma: float = 1.5, k1: float = 0.01, k2: float = 0.03) -> float:
    """Mean SSIM. pred/target [H, W, C] (channels last) or [H, W], H, W >= win_size.

    Local statistics use a normalised Gaussian window (win_size x win_size, sigma) over the windows that lie
    entirely inside the image; sigma_x^2 = E[x^2] - mu_x^2 (population), c1 = (k1 L)^2, c2 = (k2 L)^2;
    SSIM = mean over windows, then over channels."""
    pred, target = _check_pair(pred, target)
    if pred.ndim == 2:
        pred, target = pred[..., None], target[..., None]
    if pred.ndim != 3 or min(pred.shape[:2]) < win_size:
        raise ValueError(f"pred: need [H, W(, C)] with H, W >= {win_size}, got shape {pred.shape}")
    g = _gauss1d(win_size, sigma)
    c1, c2 = (k1 * data_range) ** 2, (k2 * data_range) ** 2
    vals = []
    for c in range(pred.shape[2]):
        x, y = pred[..., c], target[..., c]
        mx, my = _filter_valid(x, g), _filter_valid(y, g)
        sxx = _filter_valid(x * x, g) - mx * mx
        syy = _filter_valid(y * y, g) - my * my
        sxy = _filter_valid(x * y, g) - mx * my
        s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
        vals.append(s.mean())
    return float(np.mean(vals))


def depth_pcc(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray | None = None) -> float:
    """Pearson correlation of predicted and ground-truth depth over the valid pixels (paper appendix):
    sum (D - mu_D)(D^ - mu_D^) / sqrt(sum (D - mu_D)^2 * sum (D^ - mu_D^)^2). [H, W] each; valid [H, W] bool
    (default: gt finite and > 0, pred finite). NaN when fewer than 2 valid pixels or a constant map."""
    pred = np.asarray(pred, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    if pred.shape != gt.shape:
        raise ValueError(f"pred: shape {pred.shape} differs from gt {gt.shape}")
    if valid is None:
        valid = np.isfinite(gt) & (gt > 0) & np.isfinite(pred)
    valid = np.asarray(valid, dtype=bool)
    if valid.shape != gt.shape:
        raise ValueError(f"valid: shape {valid.shape} differs from gt {gt.shape}")
    x, y = pred[valid], gt[valid]
    if not np.isfinite(x).all():
        raise ValueError("pred: NaN or inf at valid pixels")
    if x.size < 2:
        return float("nan")
    xc, yc = x - x.mean(), y - y.mean()
    den = np.sqrt((xc * xc).sum() * (yc * yc).sum())
    return float((xc * yc).sum() / den) if den > 0 else float("nan")


def occupancy_iou(pred: np.ndarray, gt: np.ndarray, ignore: np.ndarray | None = None) -> float:
    """Binary occupancy IoU = |pred ∩ gt| / |pred ∪ gt| over known voxels. pred/gt [...] bool (or ints,
    nonzero = occupied); ignore [...] bool marks unknown voxels. NaN when both are empty."""
    pred = np.asarray(pred) != 0
    gt = np.asarray(gt) != 0
    if pred.shape != gt.shape:
        raise ValueError(f"pred: shape {pred.shape} differs from gt {gt.shape}")
    keep = np.ones_like(gt) if ignore is None else ~np.asarray(ignore, dtype=bool)
    inter = int((pred & gt & keep).sum())
    union = int(((pred | gt) & keep).sum())
    return float("nan") if union == 0 else inter / union


def semantic_miou(pred: np.ndarray, gt: np.ndarray, num_classes: int, ignore_index: int = 255,
                  skip_classes: tuple[int, ...] = (0,)) -> tuple[float, list[float]]:
    """Mean IoU over classes (per-class IoU = TP / (TP + FP + FN) over voxels with gt != ignore_index).
    Classes in ``skip_classes`` (default: 0 = empty, as SSC benchmarks do) and classes absent from both pred
    and gt (NaN) are left out of the mean. Returns (mIoU, per-class IoU list)."""
    pred = np.asarray(pred)
    gt = np.asarray(gt)
    if pred.shape != gt.shape:
        raise ValueError(f"pred: shape {pred.shape} differs from gt {gt.shape}")
    keep = gt != ignore_index
    p, g = pred[keep], gt[keep]
    ious = []
    for c in range(num_classes):
        inter = int(((p == c) & (g == c)).sum())
        union = int(((p == c) | (g == c)).sum())
        ious.append(float("nan") if union == 0 else inter / union)
    use = [v for c, v in enumerate(ious) if c not in skip_classes and not np.isnan(v)]
    return (float(np.mean(use)) if use else float("nan")), ious


@dataclass(frozen=True)
class LpipsResult:
    value: float | None      # None when unavailable
    reason: str | None       # why it is unavailable (None when computed)


_LPIPS_CACHE: dict = {}


def lpips(pred: np.ndarray, target: np.ndarray, backbone_path: str | None = None, lin_path: str | None = None,
          net: str = "vgg") -> LpipsResult:
    """LPIPS v0.1 from local weights (see xyzcyl.model_export.losses.LPIPS), pred/target [H, W, 3] in [0, 1].
    Without both paths, or when the files cannot be loaded, returns LpipsResult(None, reason)."""
    if backbone_path is None or lin_path is None:
        return LpipsResult(None, "LPIPS unavailable: no local VGG/AlexNet + LPIPS linear weights were given "
                                 "(no package ships them and model hubs are unreachable)")
    pred, target = _check_pair(pred, target)
    import torch

    from .losses import LPIPS, LPIPSUnavailable

    key = (str(backbone_path), str(lin_path), net)
    try:
        if key not in _LPIPS_CACHE:
            _LPIPS_CACHE[key] = LPIPS(backbone_path, lin_path, net)
    except LPIPSUnavailable as e:
        return LpipsResult(None, f"LPIPS unavailable: {e}")
    model = _LPIPS_CACHE[key]
    with torch.no_grad():
        a = torch.from_numpy(pred).float().permute(2, 0, 1)[None]
        b = torch.from_numpy(target).float().permute(2, 0, 1)[None]
        return LpipsResult(float(model(a, b)[0]), None)
