import numpy as np
import pytest
import torch
from xyzcyl.model_export.render_fn import KEYS, render_views
from xyzcyl.runtime.camera import Camera


def _scene(dtype=torch.float64, n=6, seed=0):
    g = torch.Generator().manual_seed(seed)
    means = torch.stack([torch.rand(n, generator=g) * 2 - 1, torch.rand(n, generator=g) * 1.2 - 0.6,
                         4 + torch.rand(n, generator=g) * 2], 1)
    return {"means": means.to(dtype),
            "quats": (torch.tensor([1.0, 0, 0, 0]) + 0.3 * torch.randn(n, 4, generator=g)).to(dtype),
            "log_scales": (torch.log(torch.tensor([0.6, 0.12, 0.3])).expand(n, 3) + 0.2 * torch.randn(n, 3, generator=g)).to(dtype),
            "opacity_logits": (0.5 * torch.randn(n, generator=g)).to(dtype),
            "sh": (0.5 * torch.randn(n, 1, 3, generator=g)).to(dtype)}


def _cams():
    K = np.array([[40.0, 0, 23.5], [0, 40.0, 15.5], [0, 0, 1]])
    T2 = np.eye(4)
    c, s = np.cos(0.1), np.sin(0.1)
    T2[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    T2[:3, 3] = [0.2, -0.1, 0.0]
    return [Camera(K=K, cam_to_ego=np.eye(4), width=48, height=32), Camera(K=K, cam_to_ego=T2, width=48, height=32)]


def _loss(g, cams, w):
    rgb, alpha, depth = render_views(g, cams)
    return (rgb * w[0]).sum() + (alpha * w[1]).sum() + 0.05 * (depth * w[2]).sum()


def test_autograd_matches_finite_differences():
    """Directional derivatives of a weighted sum of rgb, alpha and depth over two views, for each parameter
    group, against central differences of the forward renderer (float64 Gaussians)."""
    g = _scene()
    cams = _cams()
    gen = torch.Generator().manual_seed(1)
    w = [torch.rand(2, 3, 32, 48, generator=gen, dtype=torch.float64),
         torch.rand(2, 1, 32, 48, generator=gen, dtype=torch.float64),
         torch.rand(2, 1, 32, 48, generator=gen, dtype=torch.float64)]
    leaves = {k: v.clone().requires_grad_(True) for k, v in g.items()}
    _loss(leaves, cams, w).backward()
    # eps 1e-5: small enough that no Gaussian crosses the renderer's cut-offs (alpha < 1/255 skip, 3-sigma
    # extent), which make larger steps jump; large enough for float32 rasterisation noise to stay ~0.1.
    eps = 1e-5
    for k in KEYS:
        v = torch.randn(g[k].shape, generator=gen, dtype=torch.float64)
        plus = dict(g, **{k: g[k] + eps * v})
        minus = dict(g, **{k: g[k] - eps * v})
        with torch.no_grad():
            fd = (_loss(plus, cams, w) - _loss(minus, cams, w)).item() / (2 * eps)
        an = (leaves[k].grad * v).sum().item()
        # the loss (~460) is accumulated from float32 renders: rounding ~1e-6 relative, /(2 eps) -> FD noise up to
        # ~0.2 absolute; directional derivatives here are O(50-300), so 2e-2 relative + 0.2 absolute.
        assert an == pytest.approx(fd, rel=2e-2, abs=0.2), k


def test_views_sum_and_shapes():
    g = {k: v.float().requires_grad_(True) for k, v in _scene(torch.float32).items()}
    cams = _cams()
    rgb, alpha, depth = render_views(g, cams)
    assert rgb.shape == (2, 3, 32, 48) and alpha.shape == (2, 1, 32, 48) and depth.shape == (2, 1, 32, 48)
    assert rgb.dtype == torch.float32
    (rgb.sum() + alpha.sum()).backward()
    both = {k: g[k].grad.clone() for k in KEYS}
    single = {k: torch.zeros_like(g[k]) for k in KEYS}
    for cam in cams:
        for k in KEYS:
            g[k].grad = None
        r, a, _ = render_views(g, [cam])
        (r.sum() + a.sum()).backward()
        for k in KEYS:
            single[k] += g[k].grad
    for k in KEYS:
        torch.testing.assert_close(both[k], single[k], rtol=1e-5, atol=1e-5)  # float32 summation order


def test_rejects_mixed_sizes():
    g = _scene(torch.float32)
    K = np.array([[40.0, 0, 23.5], [0, 40.0, 15.5], [0, 0, 1]])
    with pytest.raises(ValueError, match="cameras"):
        render_views(g, [Camera(K=K, cam_to_ego=np.eye(4), width=48, height=32), Camera(K=K, cam_to_ego=np.eye(4), width=40, height=32)])

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/model_export/conftest.py
