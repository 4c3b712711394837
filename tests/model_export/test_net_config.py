import pytest
from xyzcyl.model_export.config import NUSCENES_FRONT_FOCAL, ConfigError, ModelConfig, parse_focal_ref, preset


@pytest.mark.parametrize("name", ["cpu", "paper"])
def test_json_round_trip(name, tmp_path):
    cfg = preset(name)
    path = tmp_path / "cfg.json"
    cfg.to_json(path)
    assert ModelConfig.from_json(path) == cfg
    assert ModelConfig.from_json(cfg.to_json()) == cfg


def test_paper_preset_sizes():
    c = preset("paper")
    assert (c.backbone.feature_dim, c.backbone.feature_stride) == (768, 16)
    assert (c.cylinder.height, c.cylinder.width) == (56, 512)
    assert c.grid.shape == (40, 200, 200) and c.grid.voxel_size == 0.4
    assert c.grid.pc_range == (-40.0, -40.0, -3.0, 40.0, 40.0, 13.0)
    assert (c.occupancy.k, c.occupancy.d_occ, c.occupancy.out_dim) == (48, 8, 384)
    assert c.occupancy.unet.down_dims == (384, 576, 576) and c.occupancy.unet.up_dims == (576, 576, 384)
    assert (c.volume.k, c.volume.d_geo, c.volume.d_app, c.volume.g_v) == (48, 12, 36, 3)
    assert (c.volume.app_out_dim, c.volume.geo_out_dim, c.volume.mlp_width) == (432, 144, 96)
    assert (c.pixel.k_in * c.pixel.k_out, c.pixel.d_pix, c.pixel.g_p) == (4, 128, 1)
    assert c.background.synth_dims == (24, 12, 6, 3) and c.background.k == 4
    assert (c.cylinder.rho_occ, c.cylinder.rho_vol, c.cylinder.dh_vol) == (0.9, 0.98, 0.4)


def test_cpu_preset_sizes():
    c = preset("cpu")
    assert (c.backbone.input_height, c.backbone.input_width, c.backbone.feature_stride) == (224, 400, 8)
    assert c.grid.shape == (20, 100, 100) and c.volume.g_v == 2
    assert c.pixel.k_in * c.pixel.k_out == 4


def test_errors_name_the_field():
    with pytest.raises(ConfigError, match=r"occupancy\.k"):
        ModelConfig.from_dict({"occupancy": {"k": 0}})
    with pytest.raises(ConfigError, match=r"volume\.bogus"):
        ModelConfig.from_dict({"volume": {"bogus": 1}})
    with pytest.raises(ConfigError, match="volume_branch"):
        ModelConfig.from_dict({"ablation": {"volume_branch": False, "pixel_branch": False}})
    with pytest.raises(ConfigError, match="preset"):
        preset("huge")


def test_depth_focal_ref_field_and_parser():
    # the cpu preset is focal-aware (the shipped 1.2.0 setting); the dataclass default stays focal-blind
    assert preset("cpu").backbone.depth_focal_ref == NUSCENES_FRONT_FOCAL
    assert ModelConfig().backbone.depth_focal_ref is None
    # configs written before the field existed load focal-blind (the v1.x checkpoints)
    d = preset("cpu").to_dict()
    del d["backbone"]["depth_focal_ref"]
    assert ModelConfig.from_dict(d).backbone.depth_focal_ref is None
    d["backbone"]["depth_focal_ref"] = 1.0553
    assert ModelConfig.from_dict(d).backbone.depth_focal_ref == 1.0553
    for bad in (0, -1.0, "x"):
        with pytest.raises(ConfigError, match=r"backbone\.depth_focal_ref|depth_focal_ref"):
            ModelConfig.from_dict(dict(d, backbone=dict(d["backbone"], depth_focal_ref=bad)))
    assert parse_focal_ref("off") is None and parse_focal_ref("nuscenes") == NUSCENES_FRONT_FOCAL
    assert parse_focal_ref(" 1.5 ") == 1.5
    for bad in ("0", "-2", "inf", "nan", "wide"):
        with pytest.raises(ConfigError, match="depth_focal_ref"):
            parse_focal_ref(bad)
