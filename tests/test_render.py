"""Tests of the matplotlib point-cloud renderer (pocoloco.viz.render)."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest
from matplotlib.image import imread

from pocoloco.viz.render import (
    LABEL_COLORS,
    VIEWS,
    colors_for,
    new_figure,
    plot_curves,
    render_grid,
    render_points,
    render_turntable_frames,
)


def _cloud(n: int = 4000, seed: int = 0):
    """A unit-ish 'body' sphere (label 0) above a 'skirt' cylinder (label 1), with outward normals."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n // 2, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    sphere = 0.3 * d + [0, 0, 0.5]
    a = rng.uniform(0, 2 * np.pi, n - n // 2)
    cyl = np.stack([0.4 * np.cos(a), 0.4 * np.sin(a), rng.uniform(-0.5, 0.1, len(a))], 1)
    cyl_n = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], 1)
    pts = np.concatenate([sphere, cyl])
    nrm = np.concatenate([d, cyl_n])
    lab = np.concatenate([np.zeros(n // 2, int), np.ones(n - n // 2, int)])
    return pts, lab, nrm


def _has_color(img: np.ndarray, rgb, tol: float = 0.12) -> int:
    return int((np.abs(img[..., :3] - np.asarray(rgb)).max(-1) < tol).sum())


def test_colors_for_modes():
    pts, lab, nrm = _cloud(100)
    c = colors_for(pts, labels=lab)
    assert c.shape == (100, 3)
    np.testing.assert_allclose(c[lab == 0], np.broadcast_to(LABEL_COLORS[0], ((lab == 0).sum(), 3)))
    np.testing.assert_allclose(c[lab == 1], np.broadcast_to(LABEL_COLORS[1], ((lab == 1).sum(), 3)))
    cn = colors_for(pts, normals=nrm, mode="normal")
    np.testing.assert_allclose(cn, (nrm + 1) / 2, atol=1e-6)
    ch = colors_for(pts, mode="height")
    assert ch.shape == (100, 3) and ch.min() >= 0 and ch.max() <= 1
    top, bottom = np.argmax(pts[:, 2]), np.argmin(pts[:, 2])
    assert not np.allclose(ch[top], ch[bottom])
    assert colors_for(pts).shape == (100, 3)  # no labels: one colour


def test_colors_for_rejects_bad_input():
    pts, lab, _ = _cloud(10)
    with pytest.raises(ValueError, match="mode"):
        colors_for(pts, mode="rainbow")
    with pytest.raises(ValueError, match="needs normals"):
        colors_for(pts, mode="normal")
    with pytest.raises(ValueError, match="labels"):
        colors_for(pts, labels=lab[:3])
    with pytest.raises(ValueError, match="points"):
        colors_for(pts[:, :2])


def test_render_grid_writes_a_png_with_both_label_colours(tmp_path):
    pts, lab, nrm = _cloud()
    path = tmp_path / "sub" / "grid.png"
    out = render_grid([(pts, lab, nrm, "a"), (pts + 1.0, lab, None, "b")], path, views=("front", "side"),
                      ncols=2, panel_size=2.0, dpi=80)
    assert out == str(path) and path.exists()
    assert os.listdir(path.parent) == ["grid.png"]  # no temporary file left behind
    img = imread(path)
    assert img.shape[:2] == (round(80 * (2.0 + 0.35)), 80 * 2.0 * 4)
    assert _has_color(img, LABEL_COLORS[1], 0.1) > 200  # lit garment
    assert (img[..., :3].min(-1) < 0.95).mean() > 0.03  # something was drawn


def test_painters_order_nearest_point_wins():
    # two points on the same line of sight: the one nearer the viewer must be on top
    pts = np.array([[0.0, 0.5, 0.0], [0.0, -0.5, 0.0]])  # second is nearer for the front view (-Y)
    colors = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    for view, winner in (("front", 1), ("back", 0)):
        for order in ([0, 1], [1, 0]):
            fig = new_figure(1.0, 1.0, 50)
            ax = fig.add_axes((0, 0, 1, 1))
            render_points(ax, pts[order], colors=colors[order], view=view, point_size=400,
                          extent=(-1, 1, -1, 1), shade=False)
            fig.canvas.draw()
            img = np.asarray(fig.canvas.buffer_rgba())[..., :3] / 255.0
            np.testing.assert_allclose(img[25, 25], colors[winner], atol=0.05)


def test_views_cull_and_shade():
    pts, lab, nrm = _cloud()
    imgs = {}
    for view in VIEWS:
        fig = new_figure(2.0, 2.0, 60)
        ax = fig.add_axes((0, 0, 1, 1))
        render_points(ax, pts, labels=lab, normals=nrm, view=view)
        fig.canvas.draw()
        imgs[view] = np.asarray(fig.canvas.buffer_rgba())[..., :3].astype(float)
    assert np.abs(imgs["front"] - imgs["top"]).mean() > 5  # top view shows a disc, not a silhouette
    with pytest.raises(ValueError, match="view"):
        render_points(new_figure(1, 1, 10).add_subplot(), pts, view="diagonal")


def test_render_grid_rejects_bad_input(tmp_path):
    pts, lab, nrm = _cloud(50)
    with pytest.raises(ValueError, match="empty"):
        render_grid([], tmp_path / "x.png")
    with pytest.raises(ValueError, match="view"):
        render_grid([(pts, lab, nrm, "a")], tmp_path / "x.png", views=("up",))
    with pytest.raises(ValueError, match="points"):
        render_grid([(pts[:, :2], lab, nrm, "a")], tmp_path / "x.png")
    with pytest.raises(ValueError, match=r"clouds\[0\]"):
        render_grid([(pts, lab)], tmp_path / "x.png")
    assert not (tmp_path / "x.png").exists()


def test_render_10k_points_is_fast(tmp_path):
    pts, lab, nrm = _cloud(10000)
    render_grid([(pts, lab, nrm, "warm-up")], tmp_path / "w.png", views=("front",))
    t0 = time.perf_counter()
    render_grid([(pts, lab, nrm, "10K")], tmp_path / "a.png", views=("front",))
    assert time.perf_counter() - t0 < 1.5  # ~0.12 s measured on an idle 2-core CPU


def test_turntable_frames(tmp_path):
    pts, lab, nrm = _cloud(500)
    paths = render_turntable_frames(pts, lab, nrm, tmp_path / "tt", num_frames=3, size=1.0, dpi=40)
    assert [os.path.basename(p) for p in paths] == ["frame_0000.png", "frame_0001.png", "frame_0002.png"]
    assert all(imread(p).shape[:2] == (40, 40) for p in paths)


def test_plot_curves(tmp_path):
    x = np.arange(50)
    path = plot_curves({"train": (x, np.exp(-x / 10)), "val": (x, np.exp(-x / 12) + 0.01)}, tmp_path / "c.png",
                       xlabel="step", ylabel="loss", logy=True)
    assert imread(path).shape[:2] == (400, 600)
    with pytest.raises(ValueError, match="equal length"):
        plot_curves({"bad": (x, x[:-1])}, tmp_path / "d.png")
    with pytest.raises(ValueError, match="empty"):
        plot_curves({}, tmp_path / "e.png")


# ------------------------------------------------------------------------------ pocoloco render
def _write_cloud(path, n=600, seed=0, normals=True, labels=True):
    from pocoloco.data.published import write_ply

    pts, lab, nrm = _cloud(n, seed)
    write_ply(path, pts, normals=nrm if normals else None, labels=lab if labels else None)
    return pts, lab, nrm


def _gif_frames(path):
    from PIL import Image

    with Image.open(path) as im:
        return im.n_frames, im.size


def test_cli_render_cloud_views_and_turntable(tmp_path, capsys):
    from pocoloco.cli import main

    _write_cloud(tmp_path / "c.ply")
    png, gif = tmp_path / "c.png", tmp_path / "c.gif"
    argv = ["render", str(tmp_path / "c.ply"), "--out", str(png), "--views", "front", "side", "back",
            "--turntable", str(gif), "--frames", "4"]  # fmt: skip
    assert main(argv) == 0, capsys.readouterr().err
    assert "wrote" in capsys.readouterr().out
    img = imread(png)
    assert img.shape[1] > 2.5 * img.shape[0]  # three views side by side
    assert _has_color(img, LABEL_COLORS[1], 0.1) > 200 and _has_color(img, LABEL_COLORS[0], 0.1) > 200
    frames, size = _gif_frames(gif)
    assert frames == 4 and size[0] > 50
    # normal colouring of a cloud without normals: estimated, differs from the label colouring
    _write_cloud(tmp_path / "n.ply", normals=False, labels=False)
    one = ["--views", "front"]
    assert main(["render", str(tmp_path / "n.ply"), "--out", str(tmp_path / "n.png"), "--color", "normal", *one]) == 0
    assert main(["render", str(tmp_path / "n.ply"), "--out", str(tmp_path / "l.png"), *one]) == 0
    a, b = imread(tmp_path / "n.png")[..., :3], imread(tmp_path / "l.png")[..., :3]
    assert a.shape == b.shape and np.abs(a - b).mean() > 0.02


def test_cli_render_folder_as_meshes_and_animation(tmp_path, capsys):
    from pocoloco.cli import main
    from pocoloco.data.published import write_ply

    folder = tmp_path / "anim"
    folder.mkdir()
    for k in range(2):
        _write_cloud(folder / f"frame_{k:04d}.ply", n=800 + 10 * k, seed=k)
    # a PLY with faces is drawn with its own faces: a tetrahedron
    write_ply(folder / "zz_tet.ply", np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32),
              faces=np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]))  # fmt: skip
    png, gif = tmp_path / "m.png", tmp_path / "a.gif"
    argv = ["render", str(folder), "--out", str(png), "--mesh", "--depth", "5", "--views", "front", "side",
            "--animate", str(gif), "--fps", "5"]  # fmt: skip
    assert main(argv) == 0, capsys.readouterr().err
    assert "rendered 3 meshes" in capsys.readouterr().out
    img = imread(png)
    assert img.shape[0] > 2.5 * img.shape[1] / 2  # three rows of two views
    assert (img[..., :3].min(-1) < 0.9).mean() > 0.05  # surfaces drawn
    assert _gif_frames(gif)[0] == 3  # every file is a frame (subsampled to the smallest: 4 points)


@pytest.mark.parametrize(
    "setup, extra, message",
    [
        ("missing", [], "no such file or folder"),
        ("empty", [], "has no points"),
        ("garbage", [], "not a PLY file"),
        ("ok", ["--views", "diagonal"], "unknown view(s) diagonal"),
        ("ok", ["--turntable", "t.mp4"], "must end with .gif"),
        ("ok", ["--animate", "a.gif"], "--animate needs a folder"),
        ("sparse", ["--mesh"], "too sparse to mesh"),
        ("emptydir", [], "no .ply files"),
    ],
)
def test_cli_render_bad_input_one_line_nothing_written(tmp_path, capsys, setup, extra, message):
    from pocoloco.cli import main
    from pocoloco.data.published import write_ply

    src = tmp_path / "in.ply"
    if setup == "empty":
        write_ply(src, np.zeros((0, 3), np.float32))
    elif setup == "garbage":
        src.write_bytes(b"hello")
    elif setup == "ok":
        _write_cloud(src, n=200)
    elif setup == "sparse":
        _write_cloud(src, n=40)
    elif setup == "emptydir":
        src = tmp_path / "dir"
        src.mkdir()
    before = sorted(os.listdir(tmp_path))
    out = tmp_path / "out.png"
    assert main(["render", str(src), "--out", str(out), *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("pocoloco: error:") and message in err and "\n" not in err, err
    assert sorted(os.listdir(tmp_path)) == before
