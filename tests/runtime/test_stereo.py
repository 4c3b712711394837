"""Depth from the motion between a drive's frames (runtime.stereo): the midpoint triangulation against its least
squares reference, the partner frames, and a textured wall seen from two places found at its depth."""

from __future__ import annotations

import numpy as np
from xyzcyl.runtime import stereo as S
from xyzcyl.runtime.camera import Camera, pinhole_K
from xyzcyl.testing.drives import pose

FRONT = np.array([[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 1.5], [0, 0, 0, 1]], float)   # camera -> ego: ahead


def test_triangulate_matches_its_reference():
    rng = np.random.default_rng(0)
    o_a, o_b = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    d_a, d_b = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    d_a /= np.linalg.norm(d_a, axis=1, keepdims=True)
    d_b /= np.linalg.norm(d_b, axis=1, keepdims=True)
    pts, gap, st, ang = S.triangulate(o_a, d_a, o_b, d_b)
    np.testing.assert_allclose(pts, S.triangulate_reference(o_a, d_a, o_b, d_b), atol=1e-9)    # float64 algebra
    pa, pb = o_a + st[:, :1] * d_a, o_b + st[:, 1:] * d_b
    np.testing.assert_allclose(gap, np.linalg.norm(pa - pb, axis=1), atol=1e-9)
    np.testing.assert_allclose(ang, np.degrees(np.arccos(np.einsum("ij,ij->i", d_a, d_b))), atol=1e-6)
    # two rays that meet: their point, no gap
    p, g, _, _ = S.triangulate(np.zeros((1, 3)), np.array([[1.0, 0, 0]]), np.array([[5.0, -5, 0]]),
                               np.array([[0, 1.0, 0]]))
    np.testing.assert_allclose(p, [[5.0, 0, 0]], atol=1e-12)
    assert g[0] < 1e-12


def test_match_finds_what_opencvs_brute_force_matcher_finds():
    """stereo.match (one matrix product, a parallel pass for each row's nearest two and each column's nearest)
    against match_reference (OpenCV's BFMatcher, knnMatch both ways): the same pairs. SIFT-like descriptors (0..255,
    128-D); b holds a's first 300 with a little noise (each should match), shuffled among others; the ratio test
    also turns down a's 20 that have two near twins in b."""
    rng = np.random.default_rng(5)
    a = rng.uniform(0, 255, (600, 128)).astype(np.float32)
    twins = np.repeat(a[300:320], 2, axis=0) + rng.normal(0, 2.0, (40, 128)).astype(np.float32)
    b = np.concatenate([a[:300] + rng.normal(0, 3.0, (300, 128)).astype(np.float32), twins,
                        rng.uniform(0, 255, (400, 128)).astype(np.float32)])
    perm = rng.permutation(len(b))
    fa, fb = (np.zeros((len(a), 2)), a), (np.zeros((len(b), 2)), b[perm])
    i, j = S.match(fa, fb)
    ri, rj = S.match_reference(fa, fb)
    assert sorted(zip(i.tolist(), j.tolist())) == sorted(zip(ri.tolist(), rj.tolist()))
    assert set(i.tolist()) == set(range(300))                        # each of a's first 300 found, none of the twins
    np.testing.assert_array_equal(perm[j[np.argsort(i)]], np.arange(300))   # ... at its copy in b
    assert len(S.match((np.zeros((1, 2)), a[:1]), fb)[0]) == 0             # fewer than two features: no matches


def test_partner_frames_about_a_baseline_away_on_each_side():
    xs = np.array([0.0, 0.4, 0.8, 1.2, 1.6, 2.0, 2.4])
    P = np.stack([xs, 0 * xs, 0 * xs], axis=1)
    assert S.partner_frames(P, 3, 1.0) == [0, 6]         # 1.2 m back, 1.2 m ahead
    assert S.partner_frames(P, 0, 1.0) == [3]
    assert S.partner_frames(np.zeros((5, 3)), 2, 1.0) == []          # a still ego: no stereo


def test_a_textured_wall_seen_from_two_places_is_found_at_its_depth(monkeypatch):
    """A wall facing the camera at ``depth_m``; the ego steps 1 m to the right and 1 m to the left of the keyframe,
    so those images are the keyframe's shifted by -+ f B / D pixels. Every kept point lies on the wall, in the
    keyframe's ego frame."""
    import cv2

    monkeypatch.setattr(S, "MAX_FEATURES", 2000)         # enough for the test, and quick to match
    depth_m = 8.0
    w, h, f = 480, 360, 300.0
    cam = Camera(K=pinhole_K(f, f, (w - 1) / 2, (h - 1) / 2), cam_to_ego=FRONT, width=w, height=h)
    rng = np.random.default_rng(1)
    tex = cv2.GaussianBlur(rng.uniform(0, 1, (h, w + 200)).astype(np.float32), (0, 0), 2.0)
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    shift = f * 1.0 / depth_m                                   # pixels
    a = tex[:, :w]
    M = np.float32([[1, 0, shift], [0, 1, 0]])                  # b(u) = a(u + shift)
    b = cv2.warpAffine(tex, M, (w + 200, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                       borderMode=cv2.BORDER_REFLECT)[:, :w]
    rgb = lambda x: np.repeat(x[..., None], 3, axis=2)
    T_b = np.array(pose(0.0, -1.0))                             # the ego 1 m to its right (ego y is left)
    M2 = np.float32([[1, 0, -shift], [0, 1, 0]])                # and 1 m to its left: c(u) = a(u - shift)
    c = cv2.warpAffine(np.pad(tex, ((0, 0), (200, 0)), mode="reflect"), M2, (w + 400, h),
                       flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REFLECT)[:, 200:200 + w]
    T_c = np.array(pose(0.0, 1.0))
    # one partner: nothing tells a still wall from a moving one, no points
    assert len(S.stereo_points([cam], [rgb(a)], np.eye(4), [([cam], [rgb(b)], T_b)])) == 0
    pts = S.stereo_points([cam], [rgb(a)], np.eye(4), [([cam], [rgb(b)], T_b), ([cam], [rgb(c)], T_c)])
    assert len(pts) > 200, len(pts)
    # the wall is at ego x = depth (the camera looks along ego x); tolerance: a tenth of a pixel of matching error
    # is D / (f B) * 0.1 = 0.27 % of the depth at 8 m, so 3 % for the median and 10 % for 95 % are loose bounds that
    # a wrong sign, scale or frame (tens of percent, or points behind) still fails
    err = np.abs(pts[:, 0] - depth_m) / depth_m
    assert np.median(err) < 0.03 and np.percentile(err, 95) < 0.10, (np.median(err), np.percentile(err, 95))
    # a still ego (the same image from the same place) gives nothing: no parallax
    still = ([cam], [rgb(a)], np.eye(4))
    assert len(S.stereo_points([cam], [rgb(a)], np.eye(4), [still, still])) == 0
    # a wall that moved with the ego to the right (the partner on the left sees it where it was): the two points
    # part, and none is kept
    moved = ([cam], [rgb(b)], T_c)
    assert len(S.stereo_points([cam], [rgb(a)], np.eye(4), [([cam], [rgb(b)], T_b), moved])) < 0.05 * len(pts)
    # a drive whose tracks name what moves: one partner is enough, and the points are as good
    one = S.stereo_points([cam], [rgb(a)], np.eye(4), [([cam], [rgb(b)], T_b)], tracked=True)
    assert len(one) > 200, len(one)
    err = np.abs(one[:, 0] - depth_m) / depth_m
    assert np.median(err) < 0.03 and np.percentile(err, 95) < 0.10, (np.median(err), np.percentile(err, 95))
    # a moving object's box over the wall's left half (ego y > 0: the image's u < 240) and beyond its top and
    # bottom: its outline in the image, no feature inside it and no point in it
    half_y = 0.8 * depth_m / 2                    # the image spans y in +-0.8 depth (tan = 240 / 300)
    box = (np.linalg.inv(np.array(pose(depth_m, half_y))), np.array([0.5, half_y, 8.0]))
    m = S.box_mask(cam, np.eye(4), [box], (w, h))
    assert m[:, :230].mean() > 0.99 and m[:, 250:].mean() < 0.01, (m[:, :230].mean(), m[:, 250:].mean())
    kept = S.stereo_points([cam], [rgb(a)], np.eye(4), [([cam], [rgb(b)], T_b)], boxes=[box], tracked=True)
    assert len(kept) > 100 and (kept[:, 1] < 0.0).all(), (len(kept), kept[:, 1].max())


def test_stereo_goes_with_a_drive_file(tmp_path, capsys):
    from xyzcyl.cli import main
    from xyzcyl.testing import EXAMPLE_RIG

    for flag in ("--stereo", "--no-stereo"):
        assert main(["reconstruct", str(EXAMPLE_RIG), "--out", str(tmp_path / "s"), flag]) == 2
        assert f"{flag}: goes with a drive file" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()
