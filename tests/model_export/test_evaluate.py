"""xyzcyl eval: the pixel-unprojection baseline's geometry, the oracle reproducing an input view, the model
path, report counts and well-formedness, and CLI errors (exit 2 naming the field)."""

import json
import math

import cv2
import numpy as np
import pytest
import torch
from xyzcyl.cli import main
from xyzcyl.model_export import metrics as M
from xyzcyl.model_export.dataset import DatasetConfig, SceneDataset
from xyzcyl.model_export.evaluate import (
    SH_C0,
    EvalConfig,
    EvalError,
    evaluate,
    summary_markdown,
    unproject_gaussians,
    write_reports,
)
from xyzcyl.model_export.train import build_model
from xyzcyl.runtime.camera import Camera
from xyzcyl.runtime.render import render
from xyzcyl.testing.model import synth_test_config


def _checkpoint(path, stage="render"):
    torch.manual_seed(0)
    cfg = synth_test_config()
    torch.save({"model": build_model(cfg).state_dict(), "model_cfg": cfg.to_dict(), "train_cfg": {"stage": stage},
                "step": 0}, path)
    return path


def _strict_json(path):
    def bad(c):
        raise ValueError(f"non-standard JSON constant {c}")

    return json.loads(path.read_text(), parse_constant=bad)


def _targets(root, setting):
    """{scene: number of usable (non-occluded) target views of ``setting``}."""
    out = {}
    for scene in sorted(root.glob("scene_*")):
        cams = json.loads((scene / "targets.json").read_text())["settings"][setting]["cameras"]
        out[scene.name] = sum(not c.get("occluded", False) for c in cams)
    return out


def test_unproject_by_hand():
    K = np.array([[[20.0, 0, 3.0], [0, 25.0, 1.5], [0, 0, 1]]])
    a = math.radians(30)                                    # camera yawed and shifted
    T = np.eye(4)[None].copy()
    T[0, :3, :3] = [[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]]
    T[0, :3, 3] = [1.0, -2.0, 0.5]
    img = np.random.default_rng(0).uniform(size=(1, 3, 4, 3))
    depth = np.zeros((1, 3, 4))
    depth[0, 0, 1] = 5.0
    depth[0, 2, 3] = 12.0
    depth[0, 1, 2] = np.inf                                 # non-finite: no Gaussian (like depth <= 0 = sky)
    g = unproject_gaussians(img, depth, K, T, scale=0.5, opacity=0.9)
    assert len(g) == 2
    for n, (v, u) in enumerate([(0, 1), (2, 3)]):
        z = depth[0, v, u]
        p_cam = np.array([(u - 3.0) / 20.0 * z, (v - 1.5) / 25.0 * z, z])     # x = (u - cx) z / fx, ...
        assert np.allclose(g.means[n], T[0, :3, :3] @ p_cam + T[0, :3, 3], atol=1e-5)   # float32 storage
        assert np.allclose(g.scales[n], 0.5 * z / math.sqrt(20.0 * 25.0), rtol=1e-5)
        assert np.allclose(SH_C0 * g.sh[n, 0] + 0.5, img[0, v, u], atol=1e-6)  # the renderer's DC colour
    assert np.allclose(g.opacities, 0.9, atol=1e-6)


def test_oracle_reproduces_an_input_view(tiny_synth_data):
    """The ground-truth-depth baseline rendered at an input camera's own pose gives that image back, up to the
    blur of its Gaussians. Threshold 22 dB over the sky-free interior (sky has no Gaussian; its border pixels
    blend with black): a Gaussian of sigma footprint/sqrt(12) plus the renderer's 0.3 px^2 low-pass acts like a
    ~0.8 px blur, and blurring these 32x56 images with sigma 0.8 px scores 23-26 dB (measured 24-25.5 dB for
    the render), while the same images shifted by 2 px score 15-19 dB: 22 dB separates correct geometry from a
    1-2 px registration error."""
    ds = SceneDataset(tiny_synth_data, DatasetConfig(setting="ego-inward", voxel_size=1.6, max_depth=1e12))
    item = ds.item(0, 0)
    rig = item["rig"]
    img = item["images"].permute(0, 2, 3, 1).numpy()
    depth = item["depth"][:, 0].numpy()
    g = unproject_gaussians(img, depth, np.stack([c.K for c in rig.cameras]),
                            np.stack([c.cam_to_ego for c in rig.cameras]))
    assert len(g) == int((depth > 0).sum())
    for k, c in enumerate(rig.cameras):
        r = render(g, Camera(K=c.K, cam_to_ego=c.cam_to_ego, width=c.width, height=c.height))
        inner = cv2.erode((depth[k] > 0).astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        assert inner.sum() > 100
        assert M.psnr(r.rgb[inner], img[k][inner]) > 22.0, c.name
        assert r.alpha[inner].min() > 0.98                  # opacity 0.99: every interior pixel is covered
        # rendered depth follows the true depth (the blend of neighbouring splats keeps PCC just below 1;
        # measured 0.985-0.992)
        assert M.depth_pcc(r.depth, depth[k], inner & (depth[k] < 80)) > 0.97, c.name


def test_eval_baseline_reports(tiny_synth_data, tmp_path, capsys):
    out = tmp_path / "ev"
    rc = main(["eval", "--baseline", "unproject-gt-depth", "--data", str(tiny_synth_data),
               "--setting", "ego-inward,ego-forward", "--out", str(out), "--quiet"])
    assert rc == 0
    res = _strict_json(out / "unproject-gt-depth_ego-inward+ego-forward.json")
    md = (out / "unproject-gt-depth_ego-inward+ego-forward.md").read_text()
    assert res["lpips_unavailable"] and "LPIPS: n/a" in md
    assert "black" in res["background"]
    for setting in ("ego-inward", "ego-forward"):
        want = _targets(tiny_synth_data, setting)
        rows = [r for r in res["views"] if r["setting"] == setting]
        assert {s: sum(r["scene"] == s for r in rows) for s in want} == want
        agg = [a for a in res["aggregate"] if a["setting"] == setting]
        assert len(agg) == 1 and agg[0]["rig"] == "nuscenes"
        assert agg[0]["scenes"] == 2 and agg[0]["views"] == sum(want.values())
        assert agg[0]["psnr"] == pytest.approx(np.mean([r["psnr"] for r in rows]))
        for key in ("psnr_fg", "psnr_seen", "seen_frac", "colour_err"):   # the later columns, aggregated like PSNR
            assert agg[0][key] == pytest.approx(np.mean([r[key] for r in rows])) and agg[0][f"{key}_undefined"] == 0
        assert agg[0]["lpips"] is None
        assert f"| unproject (GT depth, oracle) | {setting} | nuscenes | 2 | {agg[0]['views']} |" in md
        assert (f"| {agg[0]['psnr']:.2f} | {agg[0]['psnr_fg']:.2f} | {agg[0]['psnr_seen']:.2f} | "
                f"{100 * agg[0]['seen_frac']:.0f} % | {agg[0]['ssim']:.3f} | n/a | "
                f"{agg[0]['pcc']:.3f} | {agg[0]['colour_err']:.4f} |") in md
        for r in rows:
            assert 0 < r["psnr"] < 60 and -1 <= r["ssim"] <= 1
            assert r["pcc"] is None or -1 <= r["pcc"] <= 1
            assert 0 < r["psnr_fg"] < 60 and r["psnr_fg_inf"] is False and 0 <= r["colour_err"] <= 1
            assert 0 < r["seen_frac"] <= 1 and 0 < r["psnr_seen"] < 60
        if setting == "ego-forward":
            # the oracle unprojects exactly what the inputs saw: what they saw renders better than the rest
            assert np.mean([r["psnr_seen"] for r in rows]) > np.mean([r["psnr_fg"] for r in rows])
    assert "| PSNR ↑ | PSNR fg ↑ | PSNR seen ↑ | seen | SSIM ↑ | LPIPS ↓ | PCC ↑ | colour err ↓ |" in md
    assert "wrote" in capsys.readouterr().out
    # the sheet (default 4 scenes; the fixture has 2): first view of each scene and setting, 4 rows
    import cv2

    sheet = cv2.imread(str(out / "unproject-gt-depth_ego-inward+ego-forward_sheet.png"))
    assert sheet.shape == (4 * 32, 4 * 56, 3)
    first = SceneDataset(tiny_synth_data, DatasetConfig(setting="ego-inward", num_targets=1 << 30, voxel_size=1.6)
                         ).item(0, 0)["targets"]["images"][0].permute(1, 2, 0).numpy()
    # below the title text, the first column's top tile is that scene's first ego-inward target (8-bit rounding)
    np.testing.assert_allclose(sheet[16:32, :56, ::-1] / 255.0, first[16:32], atol=0.5 / 255 + 1e-6)
    # the combined table: one row per report and setting, grouped by setting, in the reports' order
    other = dict(res, label="other", aggregate=[dict(a, psnr=None) for a in res["aggregate"]])
    table = summary_markdown([res, other]).splitlines()
    assert len(table) == 2 + 4
    assert [line.split(" | ")[:2] for line in table[2:]] == [
        ["| unproject (GT depth, oracle)", "ego-inward"], ["| other", "ego-inward"],
        ["| unproject (GT depth, oracle)", "ego-forward"], ["| other", "ego-forward"]]
    assert " n/a " in table[3] and table[2] in md


def test_eval_view_colour_error_and_non_sky_psnr(tiny_synth_data):
    """A view's colour_err and psnr_fg are the metrics of its render (the sheet tile) against its target over
    all pixels / the target's non-sky pixels; the GT-depth baseline leaves the sky black, so the non-sky PSNR is
    the higher one."""
    tiles: list = []
    res = evaluate([tiny_synth_data], EvalConfig(settings=("ego-inward",), method="unproject-gt-depth",
                                                 max_scenes=1, sheet_scenes=1), progress=False, sheet=tiles)
    row, tile = res["views"][0], tiles[0]
    t = SceneDataset(tiny_synth_data, DatasetConfig(setting="ego-inward", num_targets=1 << 30, voxel_size=1.6)
                     ).item(0, 0)["targets"]
    gt = t["images"][0].permute(1, 2, 0).numpy()
    np.testing.assert_array_equal(tile["gt"], gt)
    pred, gt = tile["pred"].astype(np.float64), gt.astype(np.float64)      # float32 images; metrics use float64
    fg = t["sky"][0].numpy() < 0.5
    assert 0 < fg.sum() < fg.size                      # the view has sky and non-sky pixels
    # by hand: mean colour per channel, then the mean of the absolute differences
    by_hand = np.abs(pred.reshape(-1, 3).mean(0) - gt.reshape(-1, 3).mean(0)).mean()
    assert row["colour_err"] == pytest.approx(by_hand, abs=1e-12)
    assert row["colour_err"] == M.mean_colour_error(pred, gt)
    mse_fg = np.mean((pred[fg] - gt[fg]) ** 2)
    assert row["psnr_fg"] == pytest.approx(10 * math.log10(1 / mse_fg), abs=1e-9)
    assert row["psnr_fg"] == M.psnr_masked(pred, gt, fg)
    assert row["psnr_fg"] > row["psnr"] and row["psnr_fg_inf"] is False
    # psnr_seen: over the non-sky pixels the input cameras see, by the ground-truth depths (eval reads them
    # without a depth cap)
    item = SceneDataset(tiny_synth_data, DatasetConfig(setting="ego-inward", num_targets=1 << 30, voxel_size=1.6,
                                                       max_depth=1e12)).item(0, 0)
    cams, t = item["rig"].cameras, item["targets"]
    seen = fg & M.seen_by_inputs(t["depth"][0].numpy(), t["K"][0], t["cam_to_ego"][0],
                                 item["depth"][:, 0].numpy(), cams)
    assert 0 < seen.sum() < fg.sum()                   # an inward view sees the ego car and hidden sides too
    assert row["psnr_seen"] == pytest.approx(10 * math.log10(1 / np.mean((pred[seen] - gt[seen]) ** 2)), abs=1e-9)
    assert row["seen_frac"] == pytest.approx(seen.sum() / fg.sum())
    assert res["aggregate"][0]["colour_err"] == pytest.approx(np.mean([r["colour_err"] for r in res["views"]]))


def test_eval_model_and_depth_head_baseline(tiny_synth_data, tmp_path):
    ck = _checkpoint(tmp_path / "render.pt")
    cfg = EvalConfig(settings=("ego-inward",), max_scenes=1)
    res = evaluate([tiny_synth_data], cfg, ck, progress=False)
    want = _targets(tiny_synth_data, "ego-inward")["scene_000000"]
    assert len(res["views"]) == want and res["aggregate"][0]["scenes"] == 1
    assert res["label"].startswith("XYZCylinder (cpu") and "background network" in res["background"]
    assert all(r["n_gaussians"] > 0 and r["psnr"] is not None for r in res["views"])
    jp, _ = write_reports(res, tmp_path / "ev")
    assert jp.name == "model_ego-inward.json" and _strict_json(jp)["aggregate"][0]["views"] == want
    # ablation switches show in the label and the report name
    ab = synth_test_config()
    ab = ab.replace(ablation=ab.ablation.replace(separate_background=False))
    torch.save({"model": build_model(ab).state_dict(), "model_cfg": ab.to_dict(), "train_cfg": {"stage": "render"}},
               tmp_path / "ab.pt")
    res_ab = evaluate([tiny_synth_data], cfg, tmp_path / "ab.pt", progress=False)
    assert "no separate_background" in res_ab["label"] and "black" in res_ab["background"]
    assert write_reports(res_ab, tmp_path / "ev")[0].name == "model-no-separate-background_ego-inward.json"
    # the oracle takes the voxels from the ground truth even for a model trained on its predicted occupancy
    pred = synth_test_config().replace(volume_selection="predicted")
    pred = pred.replace(volume=pred.volume.replace(max_voxels=50 * 50 * 10))   # no cap on the 1.6 m grid
    torch.save({"model": build_model(pred).state_dict(), "model_cfg": pred.to_dict(),
                "train_cfg": {"stage": "render"}}, tmp_path / "pred.pt")
    one = cfg.replace(max_scenes=1)
    r_pred = evaluate([tiny_synth_data], one, tmp_path / "pred.pt", progress=False)["views"][0]["n_gaussians"]
    r_gt = evaluate([tiny_synth_data], one.replace(occupancy="ground-truth"), tmp_path / "pred.pt",
                    progress=False)["views"][0]["n_gaussians"]
    model = build_model(pred)
    n_pix = model(torch.zeros(6, 3, 32, 56), {k: v for k, v in SceneDataset(
        tiny_synth_data, DatasetConfig(setting="ego-inward", voxel_size=1.6), model_cfg=pred)[0]["lifting"].items()}
    )["n_pixel"]
    occupied = int(SceneDataset(tiny_synth_data, DatasetConfig(setting="ego-inward", voxel_size=1.6))[0]
                   ["occupancy"].sum())
    assert r_gt == min(occupied, pred.volume.max_voxels) * pred.volume.g_v + n_pix
    assert r_gt != r_pred
    # the depth-head baseline: one Gaussian per input pixel (the head predicts every pixel, sky included)
    res_u = evaluate([tiny_synth_data], cfg.replace(method="unproject"), ck, progress=False)
    assert res_u["label"] == "unproject (depth head)"
    assert res_u["views"][0]["n_gaussians"] == 6 * 32 * 56
    # a stage-1 checkpoint has untrained render modules: refused for the model, fine for the depth head
    occ = _checkpoint(tmp_path / "occ.pt", stage="occ")
    with pytest.raises(EvalError, match="checkpoint"):
        evaluate([tiny_synth_data], cfg, occ, progress=False)
    evaluate([tiny_synth_data], cfg.replace(method="unproject"), occ, progress=False)


@pytest.mark.parametrize("extra, field", [
    (["--setting", "ego-forward"], "checkpoint"),                                    # model without checkpoint
    (["--setting", "sideways", "--baseline", "unproject-gt-depth"], "setting"),
    (["--setting", "ego-forward", "--baseline", "unproject"], "checkpoint"),
    (["--setting", "ego-forward", "--baseline", "unproject-gt-depth", "--max-scenes", "0"], "max_scenes"),
    (["--setting", "ego-forward", "--baseline", "unproject-gt-depth", "--sheet", "-1"], "sheet"),
    (["--setting", "ego-forward", "--baseline", "unproject-gt-depth", "--rig", "waymo"], "rig"),
    (["--setting", "ego-forward", "--checkpoint", "nope.pt"], "checkpoint"),
    (["--setting", "ego-forward", "--baseline", "unproject-gt-depth", "--checkpoint", "x.pt"], "checkpoint"),
])
def test_cli_errors_exit_2(tiny_synth_data, tmp_path, capsys, extra, field):
    rc = main(["eval", "--data", str(tiny_synth_data), "--out", str(tmp_path), "--quiet", *extra])
    err = capsys.readouterr().err
    assert rc == 2 and field in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_cli_missing_data_exit_2(tmp_path, capsys):
    rc = main(["eval", "--data", str(tmp_path / "none"), "--setting", "ego-forward", "--baseline",
               "unproject-gt-depth", "--quiet"])
    assert rc == 2 and "data" in capsys.readouterr().err


@pytest.mark.parametrize("rig, label", [("waymo", "waymo"), ("docs/runs/x/ring8.json", "ring8"),
                                        ("../shared/data/real/pandaset_002_00/rig.json", "pandaset_002_00")])
def test_data_rig_labels(tmp_path, rig, label):
    from xyzcyl.model_export.evaluate import data_rig

    (tmp_path / "index.json").write_text(json.dumps({"config": {"rig": rig}}))
    assert data_rig(tmp_path) == label
    assert data_rig(tmp_path / "missing") is None
