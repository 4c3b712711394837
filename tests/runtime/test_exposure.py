"""Exposure and white balance harmonised across a drive's cameras and keyframes (runtime.exposure): the gains are
solved from what two views both saw, divided out of each camera's cells, and given back to a view at that camera."""

import json
from pathlib import Path

import numpy as np
import pytest
from xyzcyl.runtime import exposure as X
from xyzcyl.runtime.render import Gaussians


def test_solve_log_gains_recovers_known_gains_up_to_the_gauge():
    rng = np.random.default_rng(1)
    truth = rng.uniform(-0.3, 0.3, size=(4, 3))
    truth -= truth.mean(axis=0)                            # the gauge: the linked views' mean log gain is 0
    pairs = [(a, b, truth[a] - truth[b], 500) for a, b in ((0, 1), (1, 2), (2, 3), (3, 0))]
    x = X.solve_log_gains(5, pairs)                        # view 4 is in no pair: it stays at 0
    # the ridge (0.05 against weights ~22) pulls each x towards 0 by well under 1 %
    np.testing.assert_allclose(x[:4], truth, atol=0.01)
    np.testing.assert_allclose(x[4], 0.0, atol=1e-9)
    # against harmonised views (b None: x_b = 0), no gauge: the offsets are the gains
    y = X.solve_log_gains(2, [(0, None, truth[0], 500), (1, 0, truth[1] - truth[0], 500)])
    np.testing.assert_allclose(y, truth[:2], atol=0.01)


def test_pair_offset_needs_enough_agreeing_cells():
    rng = np.random.default_rng(2)
    cb = rng.uniform(0.1, 0.8, size=(1000, 3))
    off, n = X.pair_offset(cb * 1.2, cb)
    np.testing.assert_allclose(off, np.log(1.2), atol=1e-9)
    assert n == 1000
    assert X.pair_offset(cb[:100] * 1.2, cb[:100]) is None                 # under MIN_PAIRS
    assert X.pair_offset(rng.uniform(0.1, 0.8, size=(1000, 3)), cb) is None  # unrelated colours: no agreement


def test_a_noisy_pair_counts_when_it_agrees_well_beyond_chance():
    """Two cameras' cells of one surface spread (another angle, resolution, an image edge): fewer than half agree
    within AGREE_LOG, but far more than chance does (cells paired at random): kept, at the right ratio. Colours that
    agree about as often paired at random as matched are refused; one colour (the sky) matched counts by its share."""
    rng = np.random.default_rng(4)
    cb = rng.uniform(0.1, 0.8, size=(4000, 3))
    noisy = cb * 1.2 * np.exp(rng.normal(0.0, 0.09, size=cb.shape))        # ~39 % within 10 % in all channels
    r = np.log(noisy) - np.log(cb)
    assert X.AGREE_MIN < np.mean(np.all(np.abs(r - np.median(r, 0)) <= X.AGREE_LOG, axis=1)) < X.AGREE_SHARE
    off, n = X.pair_offset(noisy, cb)
    np.testing.assert_allclose(off, np.log(1.2), atol=0.01)     # the median of ~3600 cells: within 1 %
    lo, hi = X.COLOUR_RANGE
    assert n == np.all((noisy > lo) & (noisy < hi) & (cb > lo) & (cb < hi), axis=1).sum() > 3000
    # narrow colours, unrelated: a third agree with the median, and as many would at random
    a, b = rng.uniform(0.45, 0.55, size=(4000, 3)), rng.uniform(0.45, 0.55, size=(4000, 3))
    assert X.pair_offset(a, b) is None
    # as well agreeing, but 2x apart: more than two cameras of one rig are (AGREE_MIN_RATIO), refused
    assert X.pair_offset(noisy / 1.2 * 2.0, cb) is None
    # the sky: one colour in both, 1.3x brighter in a; chance agrees as much, the share alone counts
    sky = np.full((4000, 3), 0.5) * np.exp(rng.normal(0.0, 0.03, size=(4000, 3)))
    off, _ = X.pair_offset(sky * 1.3, sky)
    np.testing.assert_allclose(off, np.log(1.3), atol=1e-9)


def test_apply_gain_divides_the_colour_of_every_band():

    rng = np.random.default_rng(3)
    n = 50
    g = Gaussians(means=rng.normal(size=(n, 3)), quats=np.tile([1.0, 0, 0, 0], (n, 1)),
                  log_scales=np.full((n, 3), -3.0), opacity_logits=np.zeros(n),
                  sh=rng.normal(scale=0.3, size=(n, 4, 3)).astype(np.float32))
    gain = np.array([1.3, 1.0, 0.8])
    h = X.apply_gain(g, gain)
    np.testing.assert_allclose(X.base_colours(h) * gain, X.base_colours(g), rtol=1e-5)   # float32 storage
    np.testing.assert_allclose(h.sh[:, 1:] * gain, g.sh[:, 1:], rtol=1e-5)
    assert h.sh.dtype == g.sh.dtype and np.shares_memory(h.means, g.means) and not np.shares_memory(h.sh, g.sh)
    per = rng.uniform(0.6, 1.6, size=(n, 3))                   # one gain per Gaussian (Harmoniser.coarse)
    np.testing.assert_allclose(X.base_colours(X.apply_gain(g, per)) * per, X.base_colours(g), rtol=1e-5)
    for bad in ([1.0, 0.0, 1.0], [1.0, np.nan, 1.0], [-1.0, 1.0, 1.0]):
        with pytest.raises(ValueError, match="gain"):        # it would make colours that are not finite
            X.apply_gain(g, np.array(bad))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_apply_gain_gives_its_references_bits(dtype):
    """apply_gain (one numba pass over the DC terms) against its numpy definition, bit for bit: a gain per channel
    and one per Gaussian, SH degree 0 and 1, float32 and float64 colours (the kernel stores in the SH's dtype)."""
    rng = np.random.default_rng(4)
    n = 5000
    for bands in (1, 4):
        g = Gaussians.joined(means=rng.normal(size=(n, 3)), quats=np.tile([1.0, 0, 0, 0], (n, 1)),
                             log_scales=np.full((n, 3), -3.0), opacity_logits=np.zeros(n),
                             sh=rng.normal(scale=0.5, size=(n, bands, 3)).astype(dtype))
        for gain in (np.array([1.37, 0.91, 0.63]), rng.uniform(0.5, 1.8, size=(n, 3))):
            got, want = X.apply_gain(g, gain), X.apply_gain_reference(g, gain)
            assert got.sh.dtype == want.sh.dtype == dtype
            np.testing.assert_array_equal(got.sh, want.sh)


@pytest.fixture(scope="module")
def shipped():
    from xyzcyl.runtime.inference import Reconstructor
    from xyzcyl.testing import SHIPPED_MODEL

    return Reconstructor.load(SHIPPED_MODEL, threads=2)


def test_a_brighter_camera_is_harmonised_and_its_view_gets_its_gain_back(tmp_path, shipped):
    """The example rig's second camera posted 1.3x brighter in every frame of a still ego's drive (three
    keyframes): its gain comes out ~1.3x the others' in each keyframe, its cells are divided by it, and a view at that
    camera is drawn with the gain back (nearer its image than without), a novel view looking up is not."""
    import cv2
    from xyzcyl.runtime.detail import DetailOptions
    from xyzcyl.runtime.drive import load_drive, reconstruct_drive
    from xyzcyl.runtime.scene import Scene, rig_camera
    from xyzcyl.testing import EXAMPLE_RIG
    from xyzcyl.testing.drives import pose, write_drive

    base = json.loads(Path(EXAMPLE_RIG).read_text())
    img = cv2.imread(str(Path(EXAMPLE_RIG).parent / base["cameras"][1]["image"]))
    cv2.imwrite(str(tmp_path / "bright.png"), np.clip(img.astype(np.float32) * 1.3, 0, 255).astype(np.uint8))

    def edit(i, rig):
        rig["cameras"][1]["image"] = str(tmp_path / "bright.png")

    E = pose(7, 3, 20)
    drive = load_drive(write_drive(tmp_path, [E] * 3, [0.0, 2.5, 5.0], edit=edit))
    opts = DetailOptions(stride=8)
    scene = reconstruct_drive(shipped, drive, detail=opts, ego_body=False)
    plain = reconstruct_drive(shipped, drive, detail=opts, ego_body=False, exposure=False)
    assert "exposure" not in plain.drive
    gains = np.array(scene.drive["exposure"]["gains"])             # [K, C, 3]
    assert gains.shape == (3, 6, 3)
    others = [c for c in range(6) if c != 1 and not np.allclose(gains[0, c], 1.0)]    # the ones it overlaps
    assert len(others) >= 2
    for k in range(3):
        ratio = gains[k, 1] / np.median(gains[k, others], axis=0)
        # the clipped highlights of the brightened image (>= 255/1.3) and JPEG-free PNG rounding: within 6 %
        np.testing.assert_allclose(ratio, 1.3, rtol=0.06)
    # a view at the bright camera gets its gain back, and is nearer its (bright) image than without harmonising:
    # drawn from the fused cells alone (no camera layer), the other cameras' cells and the model's Gaussians in view
    # keep the others' exposure (measured when written: 23.97 against 23.01 dB); with the camera's own layer drawn
    # first (runtime.cameralayers) both are its own cells, the harmonised ones with the gain back: no worse (25.53
    # against 25.44 dB when measured)
    cam = rig_camera(drive.frames[0].rig.cameras[1])
    k = scene.primary_keyframe(cam)
    np.testing.assert_allclose(scene.exposure_gain(cam, k), gains[k, 1])
    gt = cv2.resize(cv2.imread(str(tmp_path / "bright.png"))[..., ::-1].astype(np.float32) / 255,
                    (cam.width, cam.height), interpolation=cv2.INTER_AREA)

    def psnr(r):
        return -10 * np.log10(np.mean((np.clip(r, 0, 1) - gt) ** 2))

    layered = psnr(scene.render(cam)[0]), psnr(plain.render(cam)[0])
    assert scene.camera_layer(cam, k) is not None and layered[0] >= layered[1], layered
    layers = scene.camera_layers, plain.camera_layers
    scene.camera_layers = plain.camera_layers = None
    assert psnr(scene.render(cam)[0]) > psnr(plain.render(cam)[0]) + 0.5
    scene.camera_layers, plain.camera_layers = layers
    up = cam.replace(cam_to_ego=cam.cam_to_ego @ np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]]))
    assert scene.exposure_gain(up, 0) is None                       # 90 degrees off every camera's axis
    scene.save(tmp_path / "scene")
    assert Scene.load(tmp_path / "scene").drive["exposure"]["gains"] == scene.drive["exposure"]["gains"]
    # a scene folder whose gains are not [keyframe][camera][3] positive numbers is refused naming the field
    from xyzcyl.runtime.scene import SceneError

    doc = json.loads((tmp_path / "scene" / "scene.json").read_text())
    doc["drive"]["exposure"]["gains"][1][2] = [1.0, -1.0, 1.0]
    (tmp_path / "scene" / "scene.json").write_text(json.dumps(doc))
    with pytest.raises(SceneError, match="gains"):
        Scene.load(tmp_path / "scene")


def test_a_rigs_cameras_are_harmonised_too(tmp_path, shipped):
    """One timestamp (Reconstructor.reconstruct): the example rig's second camera posted 1.3x brighter gets a gain
    ~1.3x the others', a view at it is drawn with its gain back (at its own pose: its own cells, the others' at its
    edges in its exposure), nearer its image than without harmonising; the gains go through the scene folder, and
    a folder whose exposure block is malformed is refused naming the field."""
    import cv2
    from xyzcyl.runtime.detail import DetailOptions
    from xyzcyl.runtime.rig import Rig
    from xyzcyl.runtime.scene import Scene, SceneError, rig_camera
    from xyzcyl.testing import EXAMPLE_RIG

    doc = json.loads(Path(EXAMPLE_RIG).read_text())
    img = cv2.imread(str(Path(EXAMPLE_RIG).parent / doc["cameras"][1]["image"]))
    cv2.imwrite(str(tmp_path / "bright.png"), np.clip(img.astype(np.float32) * 1.3, 0, 255).astype(np.uint8))
    for c in doc["cameras"]:
        c["image"] = str(Path(EXAMPLE_RIG).parent / c["image"])
    doc["cameras"][1]["image"] = str(tmp_path / "bright.png")
    rig = Rig.from_dict(doc, root=tmp_path)
    opts = DetailOptions(stride=8)
    scene = shipped.reconstruct(rig, detail=opts)
    plain = shipped.reconstruct(rig, detail=opts, exposure=False)
    assert plain.exposure is None and "exposure" in scene.timings
    gains = np.array(scene.exposure["gains"])                    # [1, C, 3]
    assert gains.shape == (1, 6, 3)
    others = [c for c in range(6) if c != 1 and not np.allclose(gains[0, c], 1.0)]
    assert len(others) >= 2
    # the clipped highlights of the brightened image and PNG rounding: within 6 % (as a drive's test)
    np.testing.assert_allclose(gains[0, 1] / np.median(gains[0, others], axis=0), 1.3, rtol=0.06)
    cam = rig_camera(rig.cameras[1])
    np.testing.assert_allclose(scene.exposure_gain(cam, None), gains[0, 1])
    gt = cv2.resize(cv2.imread(str(tmp_path / "bright.png"))[..., ::-1].astype(np.float32) / 255,
                    (cam.width, cam.height), interpolation=cv2.INTER_AREA)

    def psnr(r):
        return -10 * np.log10(np.mean((np.clip(r, 0, 1) - gt) ** 2))

    assert psnr(scene.render(cam)[0]) > psnr(plain.render(cam)[0])
    scene.save(tmp_path / "scene")
    assert Scene.load(tmp_path / "scene").exposure["gains"] == scene.exposure["gains"]
    meta = json.loads((tmp_path / "scene" / "scene.json").read_text())
    meta["exposure"]["gains"][0][2] = [1.0, 0.0, 1.0]
    (tmp_path / "scene" / "scene.json").write_text(json.dumps(meta))
    with pytest.raises(SceneError, match="positive") as e:
        Scene.load(tmp_path / "scene")
    assert e.value.field == "exposure.gains"


def test_a_view_gets_the_gain_of_its_input_camera_in_a_rig_and_in_a_drive_of_one_keyframe():
    """Scene.exposure_gain without a primary keyframe: a one-rig scene's exposure block, else a drive fused from one
    keyframe (its drive.exposure); a view looking 90 degrees off every camera gets none."""
    from xyzcyl.runtime.rig import load_rig
    from xyzcyl.runtime.scene import Scene, rig_camera
    from xyzcyl.testing import EXAMPLE_RIG

    rig = load_rig(EXAMPLE_RIG)
    gains = [[[1.0 + 0.1 * c, 1.0, 1.0 - 0.05 * c] for c in range(len(rig.cameras))]]
    block = {"cameras": rig.names, "gains": gains}
    g = Gaussians.empty()
    one_rig = Scene(gaussians=g, background=None, rig=rig, exposure=block)
    drive = Scene(gaussians=g, background=None, rig=rig,
                  drive={"keyframes": [0], "trajectory": [np.eye(4).tolist()], "exposure": block})
    for scene in (one_rig, drive):
        assert scene.primary_keyframe(rig_camera(rig.cameras[2])) is None
        np.testing.assert_allclose(scene.exposure_gain(rig_camera(rig.cameras[2]), None), gains[0][2])
    cam = rig_camera(rig.cameras[0])
    up = cam.replace(cam_to_ego=cam.cam_to_ego @ np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]]))
    assert one_rig.exposure_gain(up, None) is None
    assert Scene(gaussians=g, background=None, rig=rig).exposure_gain(cam, None) is None
