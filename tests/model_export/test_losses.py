"""Each loss against an independent numpy computation on tiny arrays."""

import math

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity
from xyzcyl.model_export import losses as L
from xyzcyl.model_export.config import ConfigError

# float64 tensors everywhere: the numpy references agree to rounding (tolerance 1e-10 unless said otherwise)
TOL = 1e-10


def _softmax(x, axis):
    e = np.exp(x - x.max(axis=axis, keepdims=True))
    return e / e.sum(axis=axis, keepdims=True)


def _tiny_occ(seed=0, classes=2, shape=(1, 2, 3, 4)):
    rng = np.random.default_rng(seed)
    B = shape[0]
    logits = rng.normal(0, 1.5, (B, classes) + shape[1:])
    target = rng.integers(0, classes, shape)
    target[..., 0, 0] = 255  # some unknown voxels
    return logits, target


def test_ce_matches_numpy_with_ignore_and_weights():
    logits, target = _tiny_occ()
    p = _softmax(logits, 1)
    valid = target != 255
    t = np.where(valid, target, 0)
    nll = -np.log(np.take_along_axis(p, t[:, None], 1)[:, 0])
    ref = nll[valid].mean()
    got = L.ce_loss(torch.tensor(logits), torch.tensor(target))
    assert float(got) == pytest.approx(ref, abs=TOL)
    w = np.array([0.3, 2.0])
    ref_w = (w[t] * nll)[valid].sum() / w[t][valid].sum()
    got_w = L.ce_loss(torch.tensor(logits), torch.tensor(target), class_weights=torch.tensor(w))
    assert float(got_w) == pytest.approx(ref_w, abs=TOL)
    assert float(L.ce_loss(torch.tensor(logits), torch.full(target.shape, 255))) == 0.0


def test_ce_two_voxels_by_hand():
    # logits (0, ln 3): p(occupied) = 3/4; targets occupied and empty -> (-ln 3/4 - ln 1/4) / 2
    logits = torch.tensor([[[0.0, 0.0], [math.log(3), math.log(3)]]], dtype=torch.float64)  # [1, 2, 2]
    target = torch.tensor([[1, 0]])
    assert float(L.ce_loss(logits, target)) == pytest.approx((-math.log(0.75) - math.log(0.25)) / 2, abs=TOL)


def _np_sem_scal(logits, target):
    p = _softmax(logits, 1)
    valid = target != 255
    tot, n = 0.0, 0
    for c in range(logits.shape[1]):
        pc = p[:, c][valid]
        y = (target[valid] == c).astype(float)
        if y.sum() == 0:
            continue
        n += 1
        tp = (pc * y).sum()
        tot += -np.log(tp / pc.sum()) - np.log(tp / y.sum()) - np.log(((1 - pc) * (1 - y)).sum() / (1 - y).sum())
    return tot / n


def _np_geo_scal(logits, target):
    p = _softmax(logits, 1)
    valid = target != 255
    q = 1 - p[:, 0][valid]
    y = (target[valid] != 0).astype(float)
    tp = (q * y).sum()
    return -np.log(tp / q.sum()) - np.log(tp / y.sum()) - np.log(((1 - q) * (1 - y)).sum() / (1 - y).sum())


@pytest.mark.parametrize("classes", [2, 3])
def test_sem_and_geo_scal_match_numpy(classes):
    logits, target = _tiny_occ(seed=classes, classes=classes)
    lt, tt = torch.tensor(logits), torch.tensor(target)
    assert float(L.sem_scal_loss(lt, tt)) == pytest.approx(_np_sem_scal(logits, target), abs=TOL)
    assert float(L.geo_scal_loss(lt, tt)) == pytest.approx(_np_geo_scal(logits, target), abs=TOL)


def test_geo_scal_by_hand():
    # two voxels, q = (3/4, 1/4), targets (occupied, empty):
    # P = 0.75 / 1 ; R = 0.75 / 1 ; S = 0.75 / 1  -> 3 * -ln 0.75
    logits = torch.tensor([[[0.0, math.log(3)], [math.log(3), 0.0]]], dtype=torch.float64)
    target = torch.tensor([[1, 0]])
    assert float(L.geo_scal_loss(logits, target)) == pytest.approx(-3 * math.log(0.75), abs=TOL)
    # with 2 classes sem_scal averages the same three terms over both classes, each equal -> same value
    assert float(L.sem_scal_loss(logits, target)) == pytest.approx(-3 * math.log(0.75), abs=TOL)


def test_scal_losses_skip_undefined_terms():
    # all voxels empty: geo recall undefined (no occupied target) -> only precision and specificity
    logits = torch.tensor([[[0.0, 0.0], [math.log(3), 0.0]]], dtype=torch.float64)  # q = (3/4, 1/2)
    target = torch.tensor([[0, 0]])
    # P = 0 / 1.25 -> BCE clamps log at -100; S = (1/4 + 1/2) / 2
    ref = 100.0 - math.log(0.375)
    assert float(L.geo_scal_loss(logits, target)) == pytest.approx(ref, abs=1e-6)  # clamp is in float math
    assert math.isfinite(float(L.sem_scal_loss(logits, target)))


def test_bev_target_and_loss():
    occ = torch.tensor([[[0, 1], [0, 255]],      # z = 0
                        [[0, 0], [255, 255]]])   # z = 1     -> [L_z=2, L_y=2, L_x=2]
    bev = L.bev_target_from_occupancy(occ)
    assert bev.tolist() == [[0, 1], [255, 255]]
    occ2 = occ.clone()
    occ2[0, 1, 1] = 1
    assert L.bev_target_from_occupancy(occ2).tolist() == [[0, 1], [255, 1]]
    logits = torch.tensor([[[[0.0, 0.0], [0.0, 0.0]], [[math.log(3), math.log(3)], [0.0, 0.0]]]],
                          dtype=torch.float64)
    # valid cells: (0,0) empty with p_empty 1/4, (0,1) occupied with p_occ 3/4
    assert float(L.bev_loss(logits, bev[None])) == pytest.approx((-math.log(0.25) - math.log(0.75)) / 2, abs=TOL)


def test_occupancy_loss_weights_and_unbatched():
    logits, target = _tiny_occ(seed=5)
    bev_logits = torch.tensor(np.random.default_rng(5).normal(size=(1, 2, 3, 4)))
    cfg = L.OccLossConfig()
    total, parts = L.occupancy_loss(torch.tensor(logits), bev_logits, torch.tensor(target), cfg)
    ref = 0.02 * parts["sem"] + 0.02 * parts["geo"] + 0.1 * parts["ce"] + 0.1 * parts["bev"]
    assert float(total) == pytest.approx(ref, abs=TOL)
    assert parts["sem"] == pytest.approx(_np_sem_scal(logits, target), abs=TOL)
    total_u, _ = L.occupancy_loss(torch.tensor(logits[0]), bev_logits[0], torch.tensor(target[0]), cfg)
    assert float(total_u) == pytest.approx(float(total), abs=TOL)


def _img(rng, B=1, H=16, W=20):
    a = rng.random((B, 3, H, W))
    b = np.clip(a + rng.normal(0, 0.15, a.shape), 0, 1)
    return a, b


def test_l1_and_dssim():
    rng = np.random.default_rng(7)
    a, b = _img(rng)
    assert float(L.l1_image_loss(torch.tensor(a), torch.tensor(b))) == pytest.approx(np.abs(a - b).mean(), abs=TOL)
    ref = structural_similarity(a[0].transpose(1, 2, 0), b[0].transpose(1, 2, 0), channel_axis=2, data_range=1.0,
                                gaussian_weights=True, sigma=1.5, use_sample_covariance=False)
    # same definition (valid windows = skimage's cropped interior); float64 summation order only
    assert float(L.dssim_loss(torch.tensor(a), torch.tensor(b))) == pytest.approx((1 - ref) / 2, abs=1e-9)


def test_sky_depth_pearson():
    alpha = torch.tensor([[[1.0, 0.2], [0.5, 0.0]]], dtype=torch.float64)
    sky = torch.tensor([[[0.0, 1.0], [0.0, 1.0]]], dtype=torch.float64)
    # targets 1 - sky = (1, 0, 1, 0): |0| + |0.2| + |0.5| + |0| = 0.7 / 4
    assert float(L.sky_loss(alpha, sky)) == pytest.approx(0.175, abs=TOL)
    assert float(L.sky_loss(alpha[:, None], sky[:, None])) == pytest.approx(0.175, abs=TOL)

    pred = torch.tensor([[[2.0, 5.0], [4.0, 9.0]]], dtype=torch.float64)
    gt = torch.tensor([[[3.0, 1.0], [4.5, 0.0]]], dtype=torch.float64)
    mask = torch.tensor([[[True, False], [True, False]]])
    assert float(L.depth_l1_loss(pred, gt, mask)) == pytest.approx(0.75, abs=TOL)   # (1 + 0.5) / 2

    rng = np.random.default_rng(8)
    p = rng.uniform(1, 30, (2, 6, 7))
    g = p * 0.7 + rng.normal(0, 3, p.shape)
    m = rng.random(p.shape) > 0.25
    ref = np.mean([1 - np.corrcoef(p[i][m[i]], g[i][m[i]])[0, 1] for i in range(2)])
    # eps 1e-8 in the denominator shifts the value by ~1e-8 / (n var^2), far below 1e-9 here
    got = float(L.pearson_depth_loss(torch.tensor(p), torch.tensor(g), torch.tensor(m)))
    assert got == pytest.approx(ref, abs=1e-9)


def test_render_loss_total_and_nan_safety():
    rng = np.random.default_rng(9)
    a, b = _img(rng, B=2)
    pa = torch.tensor(a, requires_grad=True)
    alpha = torch.tensor(rng.random((2, 16, 20)))
    sky = torch.tensor((rng.random((2, 16, 20)) > 0.7).astype(float))
    pdepth = torch.tensor(rng.uniform(1, 20, (2, 16, 20)), requires_grad=True)
    tdepth = rng.uniform(1, 20, (2, 16, 20))
    tdepth[0, 0, :5] = np.nan       # invalid ground truth must not poison the loss
    tdepth[1, 3, :] = 0.0
    total, parts = L.render_loss(pa, torch.tensor(b), alpha, sky, pdepth, torch.tensor(tdepth))
    ref = (1.0 * parts["l1"] + 0.05 * parts["perceptual"] + 0.5 * parts["sky"] + 0.01 * parts["depth"]
           + 0.01 * parts["pearson"])
    assert float(total.detach()) == pytest.approx(ref, abs=TOL)
    m = np.isfinite(tdepth) & (tdepth > 0) & (sky.numpy() < 0.5)
    assert parts["depth"] == pytest.approx(np.abs(pdepth.detach().numpy() - np.nan_to_num(tdepth))[m].mean(), abs=TOL)
    total.backward()
    assert torch.isfinite(pa.grad).all() and torch.isfinite(pdepth.grad).all()


def test_lr_schedule_and_optimizer():
    cfg = L.OptimConfig(warmup_steps=4, total_steps=14)
    assert [L.lr_factor(s, cfg) for s in range(4)] == pytest.approx([0.25, 0.5, 0.75, 1.0])
    assert L.lr_factor(4, cfg) == pytest.approx(1.0)
    assert L.lr_factor(9, cfg) == pytest.approx(0.5)          # half-way through the cosine
    assert L.lr_factor(14, cfg) == pytest.approx(0.0, abs=1e-12)
    assert L.lr_factor(100, cfg) == pytest.approx(0.0, abs=1e-12)
    w = torch.nn.Parameter(torch.ones(3))
    frozen = torch.nn.Parameter(torch.ones(2), requires_grad=False)
    opt, sched = L.build_optimizer([w, frozen], cfg)
    g = opt.param_groups[0]
    assert g["betas"] == (0.9, 0.999) and g["weight_decay"] == 0.01 and len(g["params"]) == 1
    assert g["lr"] == pytest.approx(1e-4 * 0.25)
    (w * torch.tensor([30.0, 40.0, 0.0])).sum().backward()     # grad norm 50
    assert L.clip_gradients([w], cfg) == pytest.approx(50.0)
    assert float(w.grad.norm()) == pytest.approx(1.0, rel=1e-5)
    opt.step()
    sched.step()
    assert opt.param_groups[0]["lr"] == pytest.approx(1e-4 * 0.5)


def test_configs_validate_and_round_trip():
    with pytest.raises(ConfigError, match="sem"):
        L.OccLossConfig(sem=-1)
    with pytest.raises(ConfigError, match="lpips_backbone_path"):
        L.RenderLossConfig(lpips_lin_path="x")
    with pytest.raises(ConfigError, match="warmup_steps"):
        L.OptimConfig(warmup_steps=-1)
    cfg = L.TrainLossConfig(occ=L.OccLossConfig(ce_class_weights=(1.0, 2.0)))
    assert L.TrainLossConfig.from_dict(cfg.to_dict()) == cfg


def _np_conv(x, w, b, stride, pad):
    """Direct numpy 2-D convolution (cross-correlation) [C, H, W] -> [O, H', W']."""
    x = np.pad(x, ((0, 0), (pad, pad), (pad, pad)))
    O, _C, k, _ = w.shape
    Ho = (x.shape[1] - k) // stride + 1
    Wo = (x.shape[2] - k) // stride + 1
    out = np.zeros((O, Ho, Wo))
    for i in range(k):
        for j in range(k):
            patch = x[:, i:i + stride * Ho:stride, j:j + stride * Wo:stride]
            out += np.einsum("oc,chw->ohw", w[:, :, i, j], patch)
    return out + b[:, None, None]


def _np_maxpool(x, k, s):
    Ho, Wo = (x.shape[1] - k) // s + 1, (x.shape[2] - k) // s + 1
    out = np.full((x.shape[0], Ho, Wo), -np.inf)
    for i in range(k):
        for j in range(k):
            out = np.maximum(out, x[:, i:i + s * Ho:s, j:j + s * Wo:s])
    return out


def test_lpips_alexnet_from_local_files_matches_numpy(tmp_path):
    torch.manual_seed(0)
    rng = np.random.default_rng(10)
    spec = [(0, 3, 64, 11, 4, 2), (3, 64, 192, 5, 1, 2), (6, 192, 384, 3, 1, 1), (8, 384, 256, 3, 1, 1),
            (10, 256, 256, 3, 1, 1)]
    sd = {}
    for idx, cin, cout, k, s, p in spec:
        sd[f"features.{idx}.weight"] = torch.tensor(rng.normal(0, (2 / (cin * k * k)) ** 0.5, (cout, cin, k, k)),
                                                    dtype=torch.float32)
        sd[f"features.{idx}.bias"] = torch.tensor(rng.normal(0, 0.01, cout), dtype=torch.float32)
    lin = {f"lin{i}.model.1.weight": torch.tensor(rng.random((1, c, 1, 1)), dtype=torch.float32)
           for i, c in enumerate([64, 192, 384, 256, 256])}
    torch.save(sd, tmp_path / "alex.pth")
    torch.save(lin, tmp_path / "lin.pth")
    net = L.LPIPS(tmp_path / "alex.pth", tmp_path / "lin.pth", net="alex")
    a = rng.random((64, 64, 3))
    b = np.clip(a + rng.normal(0, 0.2, a.shape), 0, 1)
    got = float(net(torch.tensor(a.transpose(2, 0, 1)[None], dtype=torch.float32),
                    torch.tensor(b.transpose(2, 0, 1)[None], dtype=torch.float32))[0])

    def feats(img):
        shift = np.array([-0.030, -0.088, -0.188])[:, None, None]
        scale = np.array([0.458, 0.448, 0.450])[:, None, None]
        x = ((2 * img.transpose(2, 0, 1) - 1) - shift) / scale
        out = []
        for n, (idx, cin, cout, k, s, p) in enumerate(spec):
            if n in (1, 2):
                x = _np_maxpool(x, 3, 2)
            x = np.maximum(_np_conv(x, sd[f"features.{idx}.weight"].double().numpy(),
                                    sd[f"features.{idx}.bias"].double().numpy(), s, p), 0)
            out.append(x)
        return out

    ref = 0.0
    for i, (fa, fb) in enumerate(zip(feats(a), feats(b))):
        na = fa / (np.sqrt((fa ** 2).sum(0, keepdims=True)) + 1e-10)
        nb = fb / (np.sqrt((fb ** 2).sum(0, keepdims=True)) + 1e-10)
        w = lin[f"lin{i}.model.1.weight"].double().numpy()[0]
        ref += ((na - nb) ** 2 * w).sum(0).mean()
    assert got == pytest.approx(ref, rel=1e-4)   # torch float32 convs vs float64 numpy
    from xyzcyl.model_export import metrics as M
    r = M.lpips(a, b, str(tmp_path / "alex.pth"), str(tmp_path / "lin.pth"), net="alex")
    assert r.reason is None and r.value == pytest.approx(ref, rel=1e-4)
    with pytest.raises(L.LPIPSUnavailable, match="lpips_lin_path"):
        torch.save({"lin0.model.1.weight": torch.zeros(1, 3, 1, 1)}, tmp_path / "bad.pth")
        L.LPIPS(tmp_path / "alex.pth", tmp_path / "bad.pth", net="alex")
