"""Metrics against scikit-image / numpy references and hand-made grids."""

import math

import numpy as np
import pytest
from skimage.metrics import peak_signal_noise_ratio, structural_similarity
from xyzcyl.model_export import metrics as M


def _pair(rng, shape):
    a = rng.random(shape)
    b = np.clip(a + rng.normal(0, 0.1, shape), 0, 1)
    return a, b


def test_psnr_matches_skimage():
    rng = np.random.default_rng(0)
    a, b = _pair(rng, (32, 48, 3))
    # float64 both sides: only summation order differs
    assert M.psnr(b, a) == pytest.approx(peak_signal_noise_ratio(a, b, data_range=1.0), rel=1e-12)
    assert M.psnr(a, a) == math.inf


def test_psnr_hand_value():
    a = np.zeros((2, 2))
    b = np.array([[0.1, 0.0], [0.0, 0.0]])   # MSE = 0.01 / 4 = 0.0025 -> 10 log10(400) = 26.0206 dB
    assert M.psnr(b, a) == pytest.approx(10 * math.log10(400), abs=1e-12)


def test_psnr_masked_hand_value():
    target = np.zeros((2, 2, 3))
    pred = np.zeros((2, 2, 3))
    pred[0, 0] = [0.3, 0.0, 0.0]       # inside the mask: squared error 0.09 in one channel
    pred[1, 1] = [1.0, 1.0, 1.0]       # outside the mask: must not count
    mask = np.array([[True, True], [True, False]])
    # MSE over 3 pixels x 3 channels = 0.09 / 9 = 0.01 -> 10 log10(100) = 20 dB
    assert M.psnr_masked(pred, target, mask) == pytest.approx(20.0, abs=1e-12)
    assert M.psnr_masked(pred, target, np.ones((2, 2), bool)) == pytest.approx(M.psnr(pred, target), abs=1e-12)
    assert M.psnr_masked(pred, target, np.array([[False, True], [True, False]])) == math.inf   # identical there
    assert math.isnan(M.psnr_masked(pred, target, np.zeros((2, 2), bool)))
    with pytest.raises(ValueError, match="mask"):
        M.psnr_masked(pred, target, np.ones((2, 3), bool))


def test_mean_colour_error_hand_value():
    pred = np.array([[[0.2, 0.4, 0.6], [0.4, 0.4, 0.0]],
                     [[0.0, 0.8, 0.2], [0.2, 0.0, 0.4]]])           # mean colour (0.2, 0.4, 0.3)
    target = np.array([[[0.1, 0.1, 0.1], [0.3, 0.3, 0.3]],
                       [[0.5, 0.5, 0.5], [0.7, 0.7, 0.7]]])         # mean colour (0.4, 0.4, 0.4)
    # |0.2 - 0.4|, |0.4 - 0.4|, |0.3 - 0.4| -> (0.2 + 0 + 0.1) / 3 = 0.1
    assert M.mean_colour_error(pred, target) == pytest.approx(0.1, abs=1e-12)
    mask = np.array([[True, False], [False, True]])
    # masked means: pred (0.2, 0.2, 0.5), target (0.4, 0.4, 0.4) -> (0.2 + 0.2 + 0.1) / 3
    assert M.mean_colour_error(pred, target, mask) == pytest.approx(0.5 / 3, abs=1e-12)
    assert M.mean_colour_error(target, target) == 0.0
    assert math.isnan(M.mean_colour_error(pred, target, np.zeros((2, 2), bool)))
    with pytest.raises(ValueError, match="pred"):
        M.mean_colour_error(pred[..., 0], target[..., 0])


def test_mean_colour_error_catches_a_grey_blur():
    # a grey scene (checkerboard 0.2 / 0.8) and a flat grey of its global mean: same mean colour -> ~0
    # (blur is PSNR's and SSIM's job), although the PSNR is poor
    grey_target = np.repeat(np.where(np.indices((4, 4)).sum(0) % 2 == 0, 0.2, 0.8)[..., None], 3, axis=2)
    flat = np.full((4, 4, 3), 0.5)
    assert M.mean_colour_error(flat, grey_target) == pytest.approx(0.0, abs=1e-12)
    assert M.psnr(flat, grey_target) == pytest.approx(10 * math.log10(1 / 0.09))
    # a red / blue scene (mean colour (0.5, 0, 0.5)) against a constant grey of the same mean intensity 1/3:
    # |1/3 - 1/2| + |1/3 - 0| + |1/3 - 1/2| = 2/3 -> 2/9
    rb = np.zeros((4, 4, 3))
    rb[:, :2, 0] = 1.0
    rb[:, 2:, 2] = 1.0
    assert M.mean_colour_error(np.full((4, 4, 3), 1 / 3), rb) == pytest.approx(2 / 9, abs=1e-12)
    # while a flat image of the scene's own mean colour is a blur with the right colour
    assert M.mean_colour_error(np.broadcast_to(rb.mean(axis=(0, 1)), rb.shape), rb) == pytest.approx(0, abs=1e-12)


@pytest.mark.parametrize("shape", [(32, 48, 3), (20, 25, 1), (40, 17)])
def test_ssim_matches_skimage(shape):
    rng = np.random.default_rng(1)
    a, b = _pair(rng, shape)
    kw = {"gaussian_weights": True, "sigma": 1.5, "use_sample_covariance": False, "data_range": 1.0}
    if len(shape) == 3:
        ref = structural_similarity(a, b, channel_axis=2, **kw)
    else:
        ref = structural_similarity(a, b, **kw)
    # skimage filters the whole image (reflect padding) and crops 5 px; the interior windows are the same
    # numbers, so only floating-point summation order differs
    assert M.ssim(b, a) == pytest.approx(ref, abs=1e-10)
    assert M.ssim(a, a) == pytest.approx(1.0, abs=1e-12)


def test_ssim_rejects_small_and_nan():
    with pytest.raises(ValueError, match="pred"):
        M.ssim(np.zeros((8, 8)), np.zeros((8, 8)))
    x = np.zeros((12, 12))
    y = x.copy()
    y[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        M.ssim(y, x)


def test_depth_pcc_matches_corrcoef():
    rng = np.random.default_rng(2)
    gt = rng.uniform(1, 50, (24, 40))
    pred = 0.5 * gt + rng.normal(0, 5, gt.shape)
    valid = rng.random(gt.shape) > 0.3
    ref = np.corrcoef(pred[valid], gt[valid])[0, 1]
    assert M.depth_pcc(pred, gt, valid) == pytest.approx(ref, abs=1e-12)  # float64 rounding only
    # default mask: gt > 0 and finite
    gt2 = gt.copy()
    gt2[~valid] = 0.0
    assert M.depth_pcc(pred, gt2) == pytest.approx(ref, abs=1e-12)
    # scale/shift invariance
    assert M.depth_pcc(3 * gt + 2, gt) == pytest.approx(1.0, abs=1e-12)
    assert math.isnan(M.depth_pcc(np.ones((4, 4)), gt[:4, :4]))


def test_occupancy_iou_hand_grid():
    gt = np.zeros((2, 3, 3), bool)
    pred = np.zeros((2, 3, 3), bool)
    gt[0, :2, :2] = True          # 4 voxels
    pred[0, 1:, 1:] = True        # 4 voxels, overlap 1 (voxel [0,1,1]) -> IoU 1/7
    assert M.occupancy_iou(pred, gt) == pytest.approx(1 / 7)
    ignore = np.zeros_like(gt)
    ignore[0, 2, 2] = True        # drops one pred-only voxel -> 1/6
    assert M.occupancy_iou(pred, gt, ignore) == pytest.approx(1 / 6)
    assert math.isnan(M.occupancy_iou(np.zeros(3), np.zeros(3)))


def test_semantic_miou_hand_grid():
    gt = np.array([0, 1, 1, 2, 2, 255])
    pred = np.array([0, 1, 2, 2, 2, 1])
    # class 1: TP 1, FP 0 (the 255 voxel is ignored), FN 1 -> 1/2; class 2: TP 2, FP 1 -> 2/3
    miou, per = M.semantic_miou(pred, gt, num_classes=3)
    assert per[1] == pytest.approx(0.5) and per[2] == pytest.approx(2 / 3) and per[0] == pytest.approx(1.0)
    assert miou == pytest.approx((0.5 + 2 / 3) / 2)


def test_lpips_unavailable_without_weights(tmp_path):
    a = np.zeros((16, 16, 3))
    r = M.lpips(a, a)
    assert r.value is None and "unavailable" in r.reason
    r = M.lpips(a, a, backbone_path=str(tmp_path / "none.pth"), lin_path=str(tmp_path / "none2.pth"))
    assert r.value is None and "no such file" in r.reason


def _wall_camera(f=10.0, w=8, h=6, x=0.0):
    """A pinhole [K, cam_to_ego] at ego x = ``x`` looking down ego +z (camera = ego axes: the test needs no
    rig convention), centre at the middle pixel."""
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    T = np.eye(4)
    T[0, 3] = x
    return K, T


def _cam(K, T, w=8, h=6):
    """[one input Camera] with intrinsics K and pose T, w x h pixels."""
    from xyzcyl.runtime.rig import Camera

    return [Camera(name="in", width=w, height=h, K=K, cam_to_ego=T)]


def test_seen_by_inputs_hand_cases():
    w, h = 8, 6
    K, T = _wall_camera()
    wall = np.full((h, w), 10.0)                        # a fronto-parallel wall 10 m ahead
    # the target is the input camera: every pixel is seen
    assert M.seen_by_inputs(wall, K, T, wall[None], _cam(K, T)).all()
    # sky (0) and non-finite target depths are never seen
    sky = wall.copy()
    sky[0] = 0
    sky[1, 0] = np.nan
    got = M.seen_by_inputs(sky, K, T, wall[None], _cam(K, T))
    assert not got[0].any() and not got[1, 0] and got[2:].all() and got[1, 1:].all()
    # moved 2 m right: pixel u looks at the input's pixel u + f * 2 / 10 = u + 2; the last 2 columns fall outside
    K2, T2 = _wall_camera(x=2.0)
    got = M.seen_by_inputs(wall, K2, T2, wall[None], _cam(K, T))
    assert got[:, : w - 2].all() and not got[:, w - 2:].any()
    # occluded: the input saw a box at 5 m over its left half, so the wall behind it is not seen there
    box = wall.copy()
    box[:, : w // 2] = 5.0
    got = M.seen_by_inputs(wall, K, T, box[None], _cam(K, T))
    assert not got[:, : w // 2].any() and got[:, w // 2:].all()
    # a second input camera that sees the whole wall makes everything seen again; one looking away sees nothing
    assert M.seen_by_inputs(wall, K, T, np.stack([box, wall]), _cam(K, T) * 2).all()
    back = T.copy()
    back[:3, :3] = np.diag([-1.0, 1.0, -1.0])          # turned 180 degrees about y: the wall is behind it
    assert not M.seen_by_inputs(wall, K, T, wall[None], _cam(K, back)).any()
    # the tolerance: 5 % + 0.2 m of the depth (0.7 m at 10 m) -- 10.6 m counts as the same surface, 11 m not
    assert M.seen_by_inputs(wall, K, T, np.full((1, h, w), 10.6), _cam(K, T)).all()
    assert not M.seen_by_inputs(wall, K, T, np.full((1, h, w), 11.0), _cam(K, T)).any()
    with pytest.raises(ValueError, match="input_depth"):
        M.seen_by_inputs(wall, K, T, wall, _cam(K, T))
