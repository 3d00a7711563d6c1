"""Shading of clouds without normals and the garment tint of unlabeled clouds (pocoloco.viz.render):
estimated normals against analytic ones, the tint against a known body, the rendered picture."""

from __future__ import annotations

import time

import numpy as np
import pytest
from matplotlib.image import imread

from pocoloco.data.poses import DEMO_POSES_DIR
from pocoloco.viz.render import (
    BONE_RADII_M,
    BONE_RADII_SCALE_M,
    LABEL_COLORS,
    estimate_normals,
    garment_weights,
    render_grid,
)

JOINTS = np.load(DEMO_POSES_DIR / "skirt_a.npz")["joints"].astype(np.float64)  # (24, 3) a standing pose


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _sphere(n: int, r: float = 0.3, seed: int = 0):
    d = _unit(np.random.default_rng(seed).normal(size=(n, 3)))
    return r * d + [0.0, 0.0, 1.0], d


def _tube(a, b, r: float, n: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """n points on the side of a cylinder of radius r around segment a-b, and its outward normals."""
    axis = _unit(b - a)
    e1 = _unit(np.cross(axis, [0.0, 0.0, 1.0] if abs(axis[2]) < 0.9 else [1.0, 0.0, 0.0]))
    e2 = np.cross(axis, e1)
    t, phi = rng.uniform(0, 1, n), rng.uniform(0, 2 * np.pi, n)
    radial = np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2
    return a + t[:, None] * (b - a) + r * radial, radial


def _scale() -> float:
    j = JOINTS
    return (np.linalg.norm(j[15] - j[0]) + np.linalg.norm(j[4] - j[1]) + np.linalg.norm(j[7] - j[4])) / BONE_RADII_SCALE_M


def _dressed(seed: int = 0):
    """Skin on tubes inside the skeleton's body envelope (shins, torso, arms; no thighs: a skirt
    hides them) and a flared skirt from the hips to the knees. Returns points, is_skirt, part."""
    rng = np.random.default_rng(seed)
    pts, skirt, part = [], [], []
    for child, name in ((7, "shin"), (8, "shin"), (6, "torso"), (9, "torso"), (18, "arm"), (19, "arm"),
                        (20, "arm"), (21, "arm")):  # fmt: skip
        parent = {7: 4, 8: 5, 6: 3, 9: 6, 18: 16, 19: 17, 20: 18, 21: 19}[child]
        r = 0.7 * BONE_RADII_M[child - 1].min() * _scale()
        p, _ = _tube(JOINTS[parent], JOINTS[child], r, 150, rng)
        pts.append(p)
        skirt.append(np.zeros(len(p), bool))
        part += [name] * len(p)
    hips, knees = JOINTS[[1, 2]].mean(0), JOINTS[[4, 5]].mean(0)
    n = 900
    t, phi = rng.uniform(0, 1, n), rng.uniform(0, 2 * np.pi, n)
    radius = 0.15 + 0.13 * t  # clings at the hips, flares to the hem
    centre = hips + t[:, None] * (knees - hips)
    pts.append(centre + radius[:, None] * np.stack([np.cos(phi), np.sin(phi), np.zeros(n)], 1))
    skirt.append(np.ones(n, bool))
    part += ["skirt"] * n
    return np.concatenate(pts), np.concatenate(skirt), np.array(part)


# ------------------------------------------------------------------------------------ normals
def test_normals_of_a_sphere_match_the_analytic_ones_and_face_outward():
    pts, true = _sphere(2000)
    est = estimate_normals(pts)  # no joints: the local-centroid / vertical-axis orientation
    cos = np.einsum("ni,ni->n", est, true)
    angle = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    assert np.allclose(np.linalg.norm(est, axis=1), 1.0)
    assert (cos > 0).all()  # every one outward
    assert np.median(angle) < 2.0 and np.percentile(angle, 99) < 6.0


def test_normals_of_a_limb_face_away_from_its_bone():
    rng = np.random.default_rng(1)
    pts, true = _tube(JOINTS[4], JOINTS[7], 0.05, 1500, rng)  # a shin 10 cm thick, ~1 cm between points
    est = estimate_normals(pts, JOINTS)
    cos = np.einsum("ni,ni->n", est, true)
    assert (cos > 0).all()
    t = (pts - JOINTS[4]) @ _unit(JOINTS[7] - JOINTS[4]) / np.linalg.norm(JOINTS[7] - JOINTS[4])
    inner = (t > 0.1) & (t < 0.9)  # the open ends see neighbours on one side only
    angle = np.degrees(np.arccos(np.clip(cos[inner], -1, 1)))
    assert np.median(angle) < 3.0 and np.percentile(angle, 95) < 8.0


def _slow_normals(pts: np.ndarray, k: int) -> np.ndarray:
    """Obviously correct PCA normals, one point at a time (unoriented)."""
    out = np.zeros_like(pts)
    for i, p in enumerate(pts):
        near = pts[np.argsort(np.linalg.norm(pts - p, axis=1), kind="stable")[:k]]
        out[i] = np.linalg.svd(near - near.mean(0))[2][-1]
    return out


def test_normals_agree_with_a_slow_reference_up_to_the_neighbour_averaging():
    pts, _ = _sphere(400, seed=3)
    pts = pts + np.random.default_rng(3).normal(scale=0.004, size=pts.shape)  # a noisy sphere
    slow = _slow_normals(pts, 12)
    est = estimate_normals(pts, k=12)
    angle = np.degrees(np.arccos(np.clip(np.abs(np.einsum("ni,ni->n", est, slow)), 0, 1)))
    assert np.median(angle) < 5.0  # the averaging over agreeing neighbours moves them a little


# ---------------------------------------------------------------------------------- the tint
def test_garment_weights_from_a_known_body_surface():
    body, _ = _sphere(4000, r=0.3, seed=4)  # vertices ~1 cm apart
    pts, d = _sphere(2000, r=0.3, seed=5)
    pts = pts + np.random.default_rng(7).normal(scale=0.002, size=pts.shape)
    lower = d[:, 2] < 0
    pts[lower] += 0.05 * d[lower]  # the lower half: cloth 5 cm off the body
    w = garment_weights(pts, body=body)
    assert w.shape == (2000,) and w.min() >= 0 and w.max() <= 1
    clear = np.abs(d[:, 2]) > 0.2  # away from the border, where the 12 neighbours mix both
    assert (w[clear & ~lower] == 0).all() and (w[clear & lower] == 1).all()
    assert ((w >= 0.5) == lower).mean() > 0.97
    assert garment_weights(pts) is None  # nothing known: no tint
    assert garment_weights(pts, joints=JOINTS[:10]) is None  # another skeleton: no tint


def test_garment_weights_from_joints_tint_the_skirt_up_to_the_waist_and_nothing_else():
    pts, skirt, part = _dressed()
    w = garment_weights(pts, joints=JOINTS)
    assert (w[skirt] >= 0.5).mean() > 0.97  # the hem hangs free, the rest is reached from it
    top = skirt & (pts[:, 2] > np.quantile(pts[skirt, 2], 0.8))  # the fifth that clings to the hips
    assert (w[top] >= 0.5).mean() > 0.9
    for name in ("shin", "torso", "arm"):
        assert (w[part == name] < 0.5).mean() > 0.97, name  # bare legs below the hem stay skin


# ----------------------------------------------------------------------------- the picture
def test_an_unlabeled_cloud_renders_shaded_and_tinted(tmp_path):
    pts, skirt, _ = _dressed()
    render_grid([(pts, None, None, "dressed")], tmp_path / "a.png", views=("front",), panel_size=3.0, dpi=80,
                joints=JOINTS)  # fmt: skip
    img = imread(tmp_path / "a.png")[..., :3]
    drawn = img.min(-1) < 0.95
    blue = drawn & (img[..., 2] > img[..., 0] + 0.15)
    warm = drawn & (img[..., 0] > img[..., 2] + 0.1)
    assert blue.sum() > 300 and warm.sum() > 300  # skin and garment, two hues
    lum = img[drawn].mean(-1)
    assert np.percentile(lum, 90) - np.percentile(lum, 10) > 0.15  # shaded, not one flat colour
    # without joints: no tint, still shaded (two-sided, by estimated normals)
    render_grid([(pts, None, None, "")], tmp_path / "b.png", views=("side",), panel_size=3.0, dpi=80)
    img = imread(tmp_path / "b.png")[..., :3]
    drawn = img.min(-1) < 0.95
    lum = img[drawn].mean(-1)
    assert np.percentile(lum, 90) - np.percentile(lum, 10) > 0.15
    assert not (drawn & (img[..., 2] > img[..., 0] + 0.15)).any()  # skin only
    # the label colours stay what they were
    assert np.allclose(LABEL_COLORS[:2], [[0.87, 0.72, 0.62], [0.25, 0.47, 0.82]])


def test_three_clouds_of_2048_points_render_fast(tmp_path):
    rng = np.random.default_rng(0)
    pts, _, _ = _dressed()
    clouds = [(pts[rng.choice(len(pts), 2048)] + rng.normal(scale=0.003, size=(2048, 3)), None, None, f"{k}")
              for k in range(3)]  # fmt: skip
    render_grid(clouds[:1], tmp_path / "w.png", views=("front",), joints=JOINTS)  # warm-up
    t0 = time.perf_counter()
    render_grid(clouds, tmp_path / "a.png", views=("front", "side"), joints=JOINTS, fit=True)
    assert time.perf_counter() - t0 < 6.0  # ~1.3 s on a busy 2-core CPU, ~0.15 s of it the shading
    t0 = time.perf_counter()
    big = np.concatenate([c[0] for c in clouds] + [clouds[0][0] + 0.002])[:8192]
    estimate_normals(big, JOINTS)
    garment_weights(big, JOINTS)
    assert time.perf_counter() - t0 < 1.5  # ~0.3 s for 8K points


# ---------------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("call, message", [
    (lambda: estimate_normals(np.zeros((10, 2))), "points must have shape"),
    (lambda: estimate_normals(np.full((10, 3), np.nan)), "NaN"),
    (lambda: estimate_normals(np.zeros((2, 3))), "at least 3"),
    (lambda: estimate_normals(np.random.rand(20, 3), k=1), "k must be"),
    (lambda: estimate_normals(np.random.rand(20, 3), JOINTS[:, :2]), "joints must have shape"),
    (lambda: garment_weights(np.random.rand(20, 3), joints=np.full((24, 3), np.inf)), "joints contain NaN"),
    (lambda: garment_weights(np.random.rand(20, 3), body=np.zeros((5, 4))), "body must have shape"),
    (lambda: garment_weights(np.array([["a", "b", "c"]])), "numeric"),
    (lambda: render_grid([(np.random.rand(20, 3), None, None, "a")], "/nonexistent/x.png", joints=[JOINTS] * 2),
     "one entry per cloud"),
])  # fmt: skip
def test_bad_input_is_a_one_line_value_error(call, message):
    with pytest.raises(ValueError, match=message) as err:
        call()
    assert "\n" not in str(err.value)


def test_write_samples_tints_hypotheses_with_the_pose(tmp_path):
    from pocoloco.data.poses import Pose
    from pocoloco.methods import SampledClouds
    from pocoloco.methods.outputs import write_samples

    pts, _, _ = _dressed()
    clouds = SampledClouds(np.stack([pts, pts + [0.0, 0.0, 0.01]]).astype(np.float32), None)
    for pose, tinted in ((Pose(JOINTS.astype(np.float32)), True), (None, False)):
        out = write_samples(tmp_path / f"s{tinted}", clouds, {"num": 2}, pose=pose)
        img = imread(out / "hypotheses.png")[..., :3]
        drawn = img.min(-1) < 0.95
        assert ((drawn & (img[..., 2] > img[..., 0] + 0.15)).sum() > 300) == tinted
        lum = img[drawn].mean(-1)
        assert np.percentile(lum, 90) - np.percentile(lum, 10) > 0.15  # shaded either way
