"""The XYZCylinder network (paper Sec. 3, appendix architecture tables), one scene per call.

    model = XYZCylinder(preset("cpu"))
    inp = rig_inputs(rig, model.cfg)                    # numpy geometry from xyzcyl.runtime.lifting, as tensors
    out = model(images, inp)                            # images [N, 3, H, W] float RGB 0..1
    out["gaussians"]                                    # dict of tensors (means, quats, log_scales, opacity_logits, sh)
    bg = model.background(out["app_plane"], bg_grids)   # [T, 3, H_t, W_t] sky images for T target views

See docs/architecture.md for the paper-to-code map.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from .backbone import DepthHead, build_backbone
from .blocks import CylConv, ResBlock, XNet, YNet, flip_w, groups_for, init_last_linear, mlp
from .config import INPUT_REF_MEAN, INPUT_REF_STD, ModelConfig
from .lifting import (
    cpfg,
    frustum_coords_torch,
    lift,
    overlay_sum,
    sample_cameras,
    sample_cpfg,
    sample_plane_wrapped,
)

SH_C0 = 0.28209479177387814
GAUSSIAN_KEYS = ("means", "quats", "log_scales", "opacity_logits", "sh")
RGB_MEAN, RGB_STD = 0.45, 0.25   # standardisation of the lifted input RGB (about the data's mean / spread)
COLOUR_CLAMP = 0.02              # input colours clamped to [c, 1 - c] before the logit (finite residual base)
MASKED_LOGIT = -30.0  # opacity logit of pixel Gaussians no camera sees (sigmoid ~ 1e-13: invisible)


def n_sh(deg: int) -> int:
    return (deg + 1) ** 2


class GaussianDecoder(nn.Module):
    """Per-anchor MLP outputs -> Gaussian parameters (everything but the mean's anchor).

    Appearance layout per Gaussian: [dc rgb (3), scale (3), rotation (4), opacity (1), higher SH (3*(S-1))].
    colour = sigmoid(raw) (sh DC = (colour - 0.5)/SH_C0, so the renderer's SH_C0*dc + 0.5 gives it back);
    scale = max_scale * sigmoid(raw) (bounded above); quats raw + (1, 0, 0, 0); opacity logit raw.
    """

    def __init__(self, sh_degree: int):
        super().__init__()
        self.S = n_sh(sh_degree)
        self.dim = 11 + 3 * (self.S - 1)

    def bias(self, g: int, opacity_logit: float = -1.0, scale_logit: float = -0.5) -> torch.Tensor:
        b = torch.zeros(g, self.dim)
        b[:, 3:6] = scale_logit
        b[:, 6] = 1.0
        b[:, 10] = opacity_logit
        return b.flatten()

    def forward(self, raw: torch.Tensor, max_scale: torch.Tensor) -> dict[str, torch.Tensor]:
        """raw [M, G, dim]; max_scale [M, 1] metres -> dict of [M*G, ...] tensors (means missing)."""
        M, G, _ = raw.shape
        rgb = torch.sigmoid(raw[..., 0:3])
        dc = ((rgb - 0.5) / SH_C0).unsqueeze(-2)
        if self.S > 1:   # degree 0: no empty reshape (it breaks ONNX shape inference)
            sh = torch.cat([dc, raw[..., 11:].reshape(M, G, self.S - 1, 3) * 0.1], dim=-2)
        else:
            sh = dc
        log_scales = torch.log(max_scale).unsqueeze(1) + F.logsigmoid(raw[..., 3:6])
        return {"quats": raw[..., 6:10].reshape(M * G, 4), "log_scales": log_scales.reshape(M * G, 3),
                "opacity_logits": raw[..., 10].reshape(M * G), "sh": sh.reshape(M * G, self.S, 3)}


class ModConv(nn.Module):
    """StyleGAN2 modulated 3x3 conv (weight demodulation); style shared by all target views of a scene."""

    def __init__(self, cin: int, cout: int, style_dim: int, demod: bool = True):
        super().__init__()
        self.weight = nn.Parameter(torch.randn(cout, cin, 3, 3) / math.sqrt(cin * 9))
        self.bias = nn.Parameter(torch.zeros(cout))
        self.affine = nn.Linear(style_dim, cin)
        nn.init.normal_(self.affine.weight, std=0.1 / math.sqrt(style_dim))  # styles start near 1
        nn.init.zeros_(self.affine.bias)
        self.demod = demod

    def forward(self, x, w):
        s = self.affine(w).view(-1) + 1.0                                       # [cin]
        y = F.conv2d(x * s.view(1, -1, 1, 1), self.weight, padding=1)
        if self.demod:
            d = torch.rsqrt(((self.weight * s.view(1, -1, 1, 1)) ** 2).sum(dim=(1, 2, 3)) + 1e-8)
            y = y * d.view(1, -1, 1, 1)
        return y + self.bias.view(1, -1, 1, 1)


class ZNet(nn.Module):
    """ZNet_bg: ResNet blocks with a 2x upsample on the appearance plane, ray-cylinder sampling per target view,
    StyleGAN-like modulated synthesis at k x the target resolution, average-pool back to the target size."""

    def __init__(self, cin: int, cfg):
        super().__init__()
        b = cfg.block_dims
        self.k = cfg.k
        self.stem = nn.Conv2d(cin, b[0], 1)
        self.pre = ResBlock(b[0], b[0])
        self.post = nn.Sequential(*[ResBlock(b[max(i - 1, 0)], b[i]) for i in range(1, len(b))])
        self.mapping = mlp(cin, cfg.style_dim, cfg.style_dim, 2, act=lambda: nn.LeakyReLU(0.2))
        s = cfg.synth_dims
        self.inp = nn.Conv2d(b[-1], s[0], 1) if b[-1] != s[0] else nn.Identity()
        self.synth = nn.ModuleList(ModConv(s[i], s[i + 1], cfg.style_dim, demod=i < len(s) - 2)
                                   for i in range(len(s) - 1))

    def forward(self, app_plane: torch.Tensor, grids: torch.Tensor) -> torch.Tensor:
        """app_plane [1, C, H_u, W_u]; grids [T, H_t, W_t, 2] (runtime.lifting.background_grid) -> [T, 3, H_t, W_t]."""
        x = self.pre(self.stem(app_plane))
        x = F.interpolate(x, scale_factor=2, mode="nearest")
        x = self.post(x)
        w = self.mapping(app_plane.mean(dim=(2, 3)))
        T = grids.shape[0]
        # border padding along p: rays above the cylinder's top see its top row (sky), below its bottom row
        y = sample_plane_wrapped(x.expand(T, -1, -1, -1), grids, padding_mode="border")
        if self.k > 1:
            y = F.interpolate(y, scale_factor=self.k, mode="bilinear", align_corners=False)
        y = self.inp(y)
        for i, layer in enumerate(self.synth):
            y = layer(y, w)
            if i < len(self.synth) - 1:
                y = F.leaky_relu(y, 0.2)
        y = torch.sigmoid(y)
        return F.avg_pool2d(y, self.k) if self.k > 1 else y


class XYZCylinder(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        ab = cfg.ablation
        D = cfg.backbone.feature_dim
        self.backbone = build_backbone(cfg.backbone)
        self.depth_head = DepthHead(D, cfg.backbone.depth_hidden, cfg.backbone.max_depth,
                                    cfg.backbone.depth_focal_ref)
        self.use_rgb = ab.rgb_path
        self.rgb_occ = ab.rgb_occupancy
        self.d_feat = D                    # backbone channels; the lifted features append 3 RGB channels
        D_occ = D + 3 if self.rgb_occ else D
        D = D + 3 if self.use_rgb else D   # lifted features of the volume and pixel modules
        self.grid_shape = cfg.grid.shape  # (L_z, L_y, L_x)
        Lz = self.grid_shape[0]

        o = cfg.occupancy
        self.occ_net = YNet(D_occ, o.unet, o.out_dim, ab.flips, ab.dual_encoder)
        self.occ_proj = nn.Conv2d(o.out_dim, o.k * o.d_occ, 1) if o.out_dim != o.k * o.d_occ else nn.Identity()
        self.occ_head = mlp(o.d_occ, o.mlp_width, o.num_classes, o.mlp_layers)
        self.bev_proj = nn.Linear(o.d_occ * Lz, o.bev_in_dim)
        self.bev_head = mlp(o.bev_in_dim, o.bev_width, o.bev_out, o.bev_layers)

        self.dec = GaussianDecoder(cfg.sh_degree)
        v = cfg.volume
        self.use_volume = ab.volume_branch
        self.use_background = ab.separate_background
        if self.use_volume or self.use_background:  # XNet_vol also feeds the background's appearance plane
            self.vol_net = XNet(D, v.unet, v.geo_out_dim, v.app_out_dim, ab.flips, ab.dual_encoder)
            self.geo_proj = nn.Conv2d(v.geo_out_dim, v.k * v.d_geo, 1)
            self.app_proj = nn.Conv2d(v.app_out_dim, v.k * v.d_app, 1)
        if self.use_volume:
            self.geo_mlp = mlp(v.d_geo, v.mlp_width, 3 * v.g_v, v.mlp_layers)
            self.app_mlp = mlp(v.d_geo + v.d_app, v.mlp_width, self.dec.dim * v.g_v, v.mlp_layers)
            init_last_linear(self.geo_mlp, torch.zeros(3 * v.g_v))
            init_last_linear(self.app_mlp, self.dec.bias(v.g_v))

        p = cfg.pixel
        self.use_pixel = ab.pixel_branch
        if self.use_pixel:
            self.pix_net = YNet(D + 2, p.unet, p.out_dim, ab.flips, ab.dual_encoder)
            self.pix_out = nn.Conv2d(p.out_dim, p.d_pix, 1)
            self.pix_norm = nn.GroupNorm(p.gn_groups, p.d_pix)
            self.pix_mlp = mlp(p.d_pix, p.mlp_width, (3 + self.dec.dim) * p.g_p, p.mlp_layers)
            b = torch.cat([torch.zeros(p.g_p, 3), self.dec.bias(p.g_p, opacity_logit=0.0).view(p.g_p, -1)], 1)
            init_last_linear(self.pix_mlp, b.flatten())
            self.use_projection = ab.pixel_projection and self.use_volume
            if self.use_projection:
                self.proj_conv = nn.Sequential(nn.Conv2d(p.d_pix * v.k, D, 1), nn.SiLU(), CylConv(D, D))
                # small last layer: the projection starts as a gentle perturbation of the lifted features
                nn.init.normal_(self.proj_conv[-1].conv.weight, std=1e-3)
                nn.init.zeros_(self.proj_conv[-1].conv.bias)
        else:
            self.use_projection = False
        if self.use_background:
            self.bg_net = ZNet(v.app_out_dim, cfg.background)

    # -- stages -------------------------------------------------------------------------------------------------
    def encode_images(self, images, depth=None, depth_mask=None, focal=None):
        """-> (lifted features [N, D_feat (+3), h, w], depth [N, 1, h, w] metres, confidence [N, 1, h, w]).
        ``focal`` [N]: the lifting input ``focal_n`` (needed by a focal-aware depth head, ignored otherwise).
        With ``ablation.rgb_path`` the input RGB, area-pooled to the feature map's size and standardised, is
        concatenated to the backbone features (with ``rgb_occupancy`` alone, only the occupancy module reads them:
        ``module_features``)."""
        feats = self.backbone(standardize_images(images) if self.cfg.backbone.input_norm == "standardize"
                              else images)
        d, c = self.depth_head(feats, depth, depth_mask, focal)
        if self.use_rgb or self.rgb_occ:
            rgb = F.adaptive_avg_pool2d(images, feats.shape[-2:])
            feats = torch.cat([feats, (rgb - RGB_MEAN) / RGB_STD], dim=1)
        return feats, d, c

    def module_features(self, feats, module: str):
        """The lifted features a module reads: all channels, or the backbone's alone where its RGB is off."""
        rgb = self.rgb_occ if module == "occupancy" else self.use_rgb
        return feats if rgb or feats.shape[1] == self.d_feat else feats[:, :self.d_feat]

    def input_colour(self, images, inp):
        """Colour path: the input colour along each pixel Gaussian's ray, [1, 3, kH_u, kW_u] in 0..1 (0 where no
        camera sees it): the images area-pooled by ``pixel.colour_pool``, sampled at the fine lattice
        (``grid_pixc``) and overlaid with the cw selection, the camera the anchors come from."""
        q = self.cfg.pixel.colour_pool
        img = F.avg_pool2d(images, q) if q > 1 else images
        return overlay_sum(sample_cameras(img, inp["grid_pixc"]), inp["sel_pixc"])

    def occupancy(self, feats, inp):
        """-> (occ_logits [C, L_z, L_y, L_x], bev_logits [bev_out, L_y, L_x])."""
        o = self.cfg.occupancy
        feats = self.module_features(feats, "occupancy")
        fp, fm = lift(feats, inp["grid_occ"], inp["sel_cw_occ"], inp["sel_ccw_occ"])
        group = cpfg(self.occ_proj(self.occ_net(fp, fm)), o.k)
        vf = sample_cpfg(group, inp["occ_coords"].reshape(-1, 3))              # [V, d_occ]
        Lz, Ly, Lx = self.grid_shape
        occ = self.occ_head(vf).t().reshape(-1, Lz, Ly, Lx)
        col = vf.reshape(Lz, Ly, Lx, o.d_occ).permute(1, 2, 0, 3).reshape(Ly, Lx, Lz * o.d_occ)
        bev = self.bev_head(self.bev_proj(col)).permute(2, 0, 1)
        return occ, bev

    def select_voxels(self, occ_logits, occ_gt=None, source: str | None = None) -> torch.Tensor:
        """Flat indices [M] of occupied voxels: argmax of the occupancy head (paper), or the ground-truth mask
        occ_gt [L_z, L_y, L_x]; at most ``volume.max_voxels`` (highest margin). ``source`` None follows
        ``cfg.volume_selection`` (ground truth only when occ_gt is given, as in training); "ground_truth" forces
        the mask (evaluation's oracle; occ_gt required), "predicted" the head."""
        if source is None:
            source = "ground_truth" if self.cfg.volume_selection == "ground_truth" and occ_gt is not None \
                else "predicted"
        if source == "ground_truth":
            if occ_gt is None:
                raise ValueError("occ_gt: required for ground-truth voxel selection")
            margin = occ_gt.reshape(-1).float() - 0.5
        else:
            margin = (occ_logits[1] - occ_logits[0]).reshape(-1).detach()
        idx = torch.nonzero(margin > 0).view(-1)
        if idx.numel() > self.cfg.volume.max_voxels:
            idx = idx[torch.topk(margin[idx], self.cfg.volume.max_voxels).indices]
        return idx

    def pixel_branch(self, feats, depth, conf, inp, images=None):
        """Pixel Gaussians; ``images`` [N, 3, H, W] (the network's input) feed the colour path (rgb_path)."""
        p = self.cfg.pixel
        feats = self.module_features(feats, "pixel")
        grid = inp["grid_pix"]
        s = sample_cameras(feats, grid)
        dn = F.grid_sample(depth, grid, mode="bilinear", padding_mode="border", align_corners=False)  # [N,1,H,W]
        cn = F.grid_sample(conf, grid, mode="bilinear", padding_mode="border", align_corners=False)
        rays = inp["pix_rays"].permute(0, 3, 1, 2)                           # [N, 3, H, W]
        xrel = inp["pix_offsets"].view(-1, 3, 1, 1) + dn * rays             # X - centre, per camera
        r_max = self.cfg.grid.r_max
        planes, geo = [], []
        for key in ("sel_cw_pix", "sel_ccw_pix"):
            sel = inp[key]
            x = overlay_sum(xrel, sel)                                      # [1, 3, H, W]
            r = torch.sqrt(x[:, 0:1] ** 2 + x[:, 1:2] ** 2 + 1e-12)
            planes.append(torch.cat([overlay_sum(s, sel), r / r_max, overlay_sum(cn, sel)], dim=1))
            geo.append((x, r))
        fp, fm = planes
        if p.k_in > 1:
            fp = F.interpolate(fp, scale_factor=p.k_in, mode="bilinear", align_corners=False)
            fm = F.interpolate(fm, scale_factor=p.k_in, mode="bilinear", align_corners=False)
        y = self.pix_net(fp, fm)
        if p.k_out > 1:
            y = F.interpolate(y, scale_factor=p.k_out, mode="bilinear", align_corners=False)
        fpix = self.pix_norm(self.pix_out(y))                               # [1, d_pix, kH, kW]
        k = p.k_in * p.k_out
        x, r = geo[0]                                                       # anchors from F+ (cw overlay)
        valid = inp["sel_cw_pix"].sum(0, keepdim=True).unsqueeze(0)         # [1, 1, H, W]
        if k > 1:
            # normalised interpolation: pixels no camera sees (x = r = 0) must not pull their neighbours inwards
            up = lambda t: F.interpolate(t, scale_factor=k, mode="bilinear", align_corners=False)
            wsum = up(valid).clamp_min(1e-6)
            x, r = up(x * valid) / wsum, up(r * valid) / wsum
            valid = F.interpolate(valid, scale_factor=k, mode="nearest")
        centre = inp["spec_pix"][:3]
        if p.placement == "cylinder_ray":
            anchor = centre + r[0].permute(1, 2, 0) * inp["pix_dirs"]      # [kH, kW, 3]
        else:
            anchor = centre + x[0].permute(1, 2, 0)
        anchor = anchor.reshape(-1, 1, 3)
        feat = fpix[0].permute(1, 2, 0).reshape(-1, p.d_pix)                # [P, d_pix]
        raw = self.pix_mlp(feat).view(feat.shape[0], p.g_p, -1)
        # pixel footprint: horizontal radius x angular pixel size, floor 1 cm
        fp_size = (r[0].reshape(-1, 1) * (2 * math.pi / (self.cfg.cylinder.width * k))).clamp_min(0.01)
        if self.use_rgb:
            if images is None:
                raise ValueError("images: the colour path (ablation.rgb_path) needs the input images")
            # colour = sigmoid(logit(c_in) + residual): the MLP's colour output starts at 0, so an untrained
            # branch already shows the input colours at full resolution
            cin = self.input_colour(images, inp)[0].permute(1, 2, 0).reshape(-1, 1, 3)
            base = torch.logit(cin.clamp(COLOUR_CLAMP, 1 - COLOUR_CLAMP))
            raw = torch.cat([raw[..., :3], raw[..., 3:6] + base, raw[..., 6:]], dim=-1)
            valid = valid * (inp["sel_pixc"].sum(0) > 0.5).to(valid.dtype)[None, None]
        g = self.dec(raw[..., 3:], 4.0 * fp_size)
        g["means"] = (anchor + p.offset_scale * torch.tanh(raw[..., :3])).reshape(-1, 3)
        vmask = valid.reshape(-1, 1).expand(-1, p.g_p).reshape(-1) > 0.5
        g["opacity_logits"] = torch.where(vmask, g["opacity_logits"], torch.full_like(g["opacity_logits"],
                                                                                       MASKED_LOGIT))
        return g, feat, vmask, anchor.reshape(-1, 3)

    def pixel_projection(self, means, feat, vmask, spec_vol):
        """Appendix eq. 41-42: CV_proj(F_proj) [1, D_feat, H_u, W_u] from the pixel features (see
        ``scatter_pixel_features``). The G_p Gaussians of a pixel share its feature; the first one's centre
        places it."""
        g_p = self.cfg.pixel.g_p
        return self.proj_conv(self.scatter_pixel_features(means.view(-1, g_p, 3)[:, 0], feat,
                                                          vmask.view(-1, g_p)[:, 0], spec_vol))

    def scatter_pixel_features(self, points, feat, valid, spec_vol):
        """Eq. 41: scatter features [P, d] at ego points [P, 3] into the volume CPFG grid, returned as a plane
        [1, d*K, H_u, W_u] (channel = d*K + k). Plane index floor(t K) gets (1 - q), the next plane q, with
        q = t K - floor(t K); column floor(s W_u), row floor(p H_u); out-of-range planes/rows and invalid
        pixels contribute nothing. ``scatter_add`` (ONNX ScatterElements with add, deterministic in onnxruntime;
        ``index_add`` exports to ScatterND with add, which loses updates with several onnxruntime threads)."""
        v, cyl = self.cfg.volume, self.cfg.cylinder
        K, H, W = v.k, cyl.height, cyl.width
        c = frustum_coords_torch(points, spec_vol, self.cfg.grid.r_min, self.cfg.grid.r_max)
        t, s, pp = (c[:, 0] + 1) / 2, (c[:, 1] + 1) / 2, (c[:, 2] + 1) / 2
        tk = t * K
        k0f = torch.floor(tk).detach()
        q = tk - k0f
        k0 = k0f.long()
        col = torch.remainder(torch.floor(s * W).long(), W)
        row = torch.floor(pp * H).long()
        ok_row = (row >= 0) & (row < H) & valid
        out = feat.new_zeros(K * H * W, feat.shape[1])
        for kk, w in ((k0, 1 - q), (k0 + 1, q)):
            ok = ok_row & (kk >= 0) & (kk < K)
            flat = (kk.clamp(0, K - 1) * H + row.clamp(0, H - 1)) * W + col
            src = feat * (w * ok.to(feat.dtype)).unsqueeze(1)
            out = out.scatter_add(0, flat.unsqueeze(1).expand(-1, src.shape[1]), src)
        return out.view(K, H, W, -1).permute(3, 0, 1, 2).reshape(1, -1, H, W)

    def volume_gaussians(self, geo_g, app_g, idx, inp):
        v = self.cfg.volume
        coords = inp["vol_coords"].reshape(-1, 3)[idx]
        centres = inp["voxel_centres"].reshape(-1, 3)[idx]
        fg = sample_cpfg(geo_g, coords)
        fa = sample_cpfg(app_g, coords)
        vs = self.cfg.grid.voxel_size
        off = torch.tanh(self.geo_mlp(fg)).view(-1, v.g_v, 3) * (v.offset_scale * vs)
        raw = self.app_mlp(torch.cat([fg, fa], dim=1)).view(-1, v.g_v, self.dec.dim)
        g = self.dec(raw, torch.full((raw.shape[0], 1), vs, dtype=raw.dtype, device=raw.device))
        g["means"] = (centres.unsqueeze(1) + off).reshape(-1, 3)
        return g

    # -- full forward -------------------------------------------------------------------------------------------
    def planes(self, images, inp, depth=None, depth_mask=None):
        """Everything before the data-dependent voxel selection (also the export's ``encode`` graph).

        Returns dict: depth, conf [N, 1, h, w]; occ_logits [2, L_z, L_y, L_x]; bev_logits [2, L_y, L_x];
        pixel (Gaussians dict of the pixel branch, or None); geo_cpfg, app_cpfg [1, D, K, H_u, W_u] (volume
        branch, or None); app_plane [1, C_app, H_u, W_u] (background input, or None)."""
        feats, d, c = self.encode_images(images, depth, depth_mask, inp.get("focal_n"))
        occ, bev = self.occupancy(feats, inp)
        out = {"depth": d, "conf": c, "occ_logits": occ, "bev_logits": bev, "pixel": None, "geo_cpfg": None,
               "app_cpfg": None, "app_plane": None}
        if self.use_pixel:
            out["pixel"], pfeat, vmask, _ = self.pixel_branch(feats, d, c, inp, images)
        if self.use_volume or self.use_background:
            v = self.cfg.volume
            fp, fm = lift(self.module_features(feats, "volume"), inp["grid_vol"], inp["sel_cw_vol"],
                          inp["sel_ccw_vol"])
            if self.use_projection:
                pr = self.pixel_projection(out["pixel"]["means"], pfeat, vmask, inp["spec_vol"])
                fp, fm = fp + pr, fm + pr
            geo, app = self.vol_net(fp, fm)
            out["app_plane"] = app
            if self.use_volume:
                out["geo_cpfg"], out["app_cpfg"] = cpfg(self.geo_proj(geo), v.k), cpfg(self.app_proj(app), v.k)
        return out

    def forward(self, images, inp, depth=None, depth_mask=None, occ_gt=None, voxel_idx=None):
        """images [N, 3, H, W] RGB 0..1; inp: lifting inputs (tensors); depth [N, 1, h, w] metres + depth_mask [N]
        (1 = use the given depth, confidence 1); occ_gt [L_z, L_y, L_x] bool (training selection);
        voxel_idx: precomputed occupied-voxel flat indices (skips the selection).

        Returns dict: depth, conf [N, 1, h, w]; occ_logits [2, L_z, L_y, L_x]; bev_logits [2, L_y, L_x];
        voxel_idx [M]; app_plane [1, C_app, H_u, W_u] (background input, or None); gaussians (dict of
        [G, ...] tensors: means, quats, log_scales, opacity_logits, sh); n_volume, n_pixel counts."""
        p = self.planes(images, inp, depth, depth_mask)
        out = {k: p[k] for k in ("depth", "conf", "occ_logits", "bev_logits", "app_plane")}
        parts = []
        if self.use_volume:
            idx = voxel_idx if voxel_idx is not None else self.select_voxels(p["occ_logits"], occ_gt)
            out["voxel_idx"] = idx
            parts.append(self.volume_gaussians(p["geo_cpfg"], p["app_cpfg"], idx, inp))
        out["n_volume"] = parts[0]["means"].shape[0] if parts else 0
        pix = p["pixel"]
        if pix is not None:
            parts.append(pix)
        out["n_pixel"] = pix["means"].shape[0] if pix is not None else 0
        out["gaussians"] = {k: torch.cat([q[k] for q in parts], dim=0) for k in GAUSSIAN_KEYS}
        return out

    def background(self, app_plane, grids):
        """[T, 3, H_t, W_t] background images for T target views (grids from runtime.lifting.background_grid);
        None when the separate background is ablated (the blend then uses black)."""
        if not self.use_background:
            return None
        return self.bg_net(app_plane, grids)


def standardize_images(images: torch.Tensor) -> torch.Tensor:
    """images [N, 3, H, W] RGB 0..1 -> same, each image's per-channel mean and standard deviation moved to
    INPUT_REF_MEAN / INPUT_REF_STD (config.py), clipped to 0..1 (BackboneConfig.input_norm = "standardize").
    Invariant to a per-channel gain and offset of an image (exposure, white balance) where nothing clips."""
    mu = images.mean(dim=(2, 3), keepdim=True)
    sd = images.std(dim=(2, 3), keepdim=True, unbiased=False)
    ref_mu = images.new_tensor(INPUT_REF_MEAN).view(1, 3, 1, 1)
    ref_sd = images.new_tensor(INPUT_REF_STD).view(1, 3, 1, 1)
    # 1e-3: a flat image (sd 0, e.g. a black frame) stays flat at the reference mean instead of dividing by 0
    return ((images - mu) / (sd + 1e-3) * ref_sd + ref_mu).clamp(0.0, 1.0)


def blend(fg_rgb, fg_alpha, bg_rgb):
    """I = I_fg + (1 - A_fg) * I_bg; fg_rgb [T, 3, H, W] rendered over black, fg_alpha [T, 1, H, W]."""
    if bg_rgb is None:
        return fg_rgb
    return fg_rgb + (1 - fg_alpha) * bg_rgb


__all__ = ["GaussianDecoder", "ModConv", "XYZCylinder", "ZNet", "blend", "flip_w", "groups_for"]
