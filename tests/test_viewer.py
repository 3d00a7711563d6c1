"""Tests of ``pocoloco view`` (pocoloco.viz.viewer): the self-contained WebGL viewer page.

The page is checked twice: in Python (data round trip, no network references) and, when a
Chromium is installed, rendered headless with SwiftShader (software WebGL): the screenshot
must not be blank and the page must report the number of points it drew.
"""

from __future__ import annotations

import base64
import json
import re
import shutil
import subprocess

import numpy as np
import pytest
from matplotlib.image import imread

from pocoloco.cli import main
from pocoloco.data.published import write_ply
from pocoloco.viz.viewer import (
    build_viewer_html,
    find_clouds,
    load_clouds,
    write_viewer,
)

BACKGROUND = np.array([0xF4, 0xF4, 0xF2]) / 255.0


def _ellipsoid(n: int, seed: int, shift: float = 0.0):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pts = d * [0.3, 0.2, 0.8] + [0.0, 0.0, 1.0 + shift]
    nrm = d / [0.3, 0.2, 0.8]
    return pts, nrm / np.linalg.norm(nrm, axis=1, keepdims=True)


@pytest.fixture()
def result_dir(tmp_path):
    """Two hypotheses with normals and labels: 3000 and 1500 points."""
    d = tmp_path / "samples"
    for k, n in enumerate((3000, 1500)):
        pts, nrm = _ellipsoid(n, seed=k, shift=0.1 * k)
        write_ply(d / f"sample_{k:03d}.ply", pts, normals=nrm, labels=(pts[:, 2] < 0.8).astype(np.uint8))
    (d / "hypotheses.png").write_bytes(b"not a cloud")  # other files are ignored
    return d


def _data(html: str) -> dict:
    m = re.search(r'<script type="application/json" id="pocoloco-data">(.*?)</script>', html, re.S)
    assert m, "data block missing"
    return json.loads(m.group(1))


def test_page_is_self_contained_and_round_trips_the_data(result_dir):
    files = find_clouds(result_dir)
    assert [f.name for f in files] == ["sample_000.ply", "sample_001.ply"]
    clouds = load_clouds(files, max_points=2000)
    assert [len(c.points) for c in clouds] == [2000, 1500] and [c.total for c in clouds] == [3000, 1500]
    html = build_viewer_html(clouds, title="t <x>")
    assert "http://" not in html and "https://" not in html and "<script src" not in html and "{{" not in html
    assert "<title>t &lt;x&gt;</title>" in html
    data = _data(html)
    assert len(data["clouds"]) == 2 and data["animation"] is False
    c0 = data["clouds"][0]
    pos = np.frombuffer(base64.b64decode(c0["pos"]), "<f4").reshape(-1, 3)
    np.testing.assert_array_equal(pos, clouds[0].points)
    nrm = np.frombuffer(base64.b64decode(c0["nrm"]), np.uint8).reshape(-1, 3) / 127.5 - 1
    np.testing.assert_allclose(nrm, clouds[0].normals, atol=1 / 127.5 + 1e-6)
    lab = np.frombuffer(base64.b64decode(c0["lab"]), np.uint8)
    np.testing.assert_array_equal(lab, clouds[0].labels)
    # subsampling is deterministic and keeps file order
    again = load_clouds(files, max_points=2000)
    np.testing.assert_array_equal(again[0].points, clouds[0].points)


def test_frames_are_an_animation_in_natural_order(tmp_path):
    for k in (10, 9, 0):
        write_ply(tmp_path / f"frame_{k}.ply", _ellipsoid(200, k)[0])
    path, clouds = write_viewer(tmp_path, max_points=100)
    assert [c.name for c in clouds] == ["frame_0.ply", "frame_9.ply", "frame_10.ply"]
    data = _data(path.read_text(encoding="utf-8"))
    assert data["animation"] is True and "nrm" not in data["clouds"][0] and data["clouds"][0]["n"] == 100


@pytest.mark.parametrize(
    "setup, args, message",
    [
        ("missing", [], "no such folder"),
        ("empty", [], "no .ply files"),
        ("file", [], "is not a folder"),
        ("bad", [], "not a PLY file"),
        ("ok", ["--max-points", "0"], "--max-points must be >= 1"),
    ],
)
def test_cli_errors_are_one_line_and_nothing_written(tmp_path, capsys, setup, args, message):
    target = tmp_path / "r"
    if setup == "empty":
        target.mkdir()
    elif setup == "file":
        target.write_text("x")
    elif setup in ("bad", "ok"):
        write_ply(target / "sample_000.ply", _ellipsoid(50, 0)[0])
        if setup == "bad":
            (target / "sample_001.ply").write_bytes(b"garbage")
    assert main(["view", str(target), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("pocoloco: error:") and message in err and "\n" not in err, err
    assert not (target / "viewer.html").exists()


# ------------------------------------------------------------------------------ headless browser
def _chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        if shutil.which(name):
            return shutil.which(name)
    return None


def _run_chromium(exe: str, url: str, *extra: str) -> subprocess.CompletedProcess:
    cmd = [exe, "--headless", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader",
           "--enable-unsafe-swiftshader", "--window-size=800,600", "--virtual-time-budget=5000",
           "--hide-scrollbars", *extra, url]  # fmt: skip
    return subprocess.run(cmd, capture_output=True, text=True, timeout=90)


def _status(exe: str, url: str, attempts: int = 3) -> dict:
    """The viewer's status attributes after chromium --dump-dom; a cold or loaded machine can
    dump the DOM before the page ran, so try a few times (the last answer counts)."""
    for _ in range(attempts):
        dom = _run_chromium(exe, url, "--dump-dom")
        m = re.search(r'<div id="status"([^>]*)>', dom.stdout)
        assert m, f"no status element in the DOM; chromium said: {dom.stderr[-2000:]}"
        attrs = dict(re.findall(r'data-([a-z-]+)="([^"]*)"', m.group(1)))
        if attrs.get("ready") == "1":
            break
    return {**attrs, "stderr": dom.stderr[-1500:]}


def test_viewer_draws_in_headless_chromium(result_dir, tmp_path, capsys):
    exe = _chromium()
    if exe is None:
        pytest.skip("chromium is not installed (apt-get install chromium) - browser rendering not tested")
    out = tmp_path / "viewer.html"
    assert main(["view", str(result_dir), "--out", str(out), "--max-points", "2000"]) == 0
    assert "2 clouds, 3500 points" in capsys.readouterr().out

    attrs = _status(exe, out.as_uri())
    assert attrs["ready"] == "1", attrs
    assert attrs["num-clouds"] == "2" and attrs["num-points-shown"] == "2000" and attrs["current"] == "0"
    assert attrs["color-mode"] == "normal"
    assert int(attrs["covered-pixels"]) > 5000, attrs  # counted with gl.readPixels after drawing

    # start-up options in the URL hash: the second hypothesis (1500 points), coloured by label
    attrs = _status(exe, out.as_uri() + "#cloud=1&color=label&az=30")
    shown = (attrs["ready"], attrs["current"], attrs["num-points-shown"], attrs["color-mode"])
    assert shown == ("1", "1", "1500", "label"), attrs

    shot = tmp_path / "shot.png"
    _run_chromium(exe, out.as_uri(), f"--screenshot={shot}")
    img = imread(shot)[..., :3]
    assert img.shape[:2] == (600, 800)
    body = img[60:560]  # below the toolbar, above the help line
    cloud = np.abs(body - BACKGROUND).sum(-1) > 0.1
    assert cloud.mean() > 0.03, cloud.mean()  # not blank
    ys, xs = np.nonzero(cloud)
    # the cloud is centred and taller than wide, as the ellipsoid seen from the front
    assert abs(xs.mean() - 400) < 40 and np.ptp(ys) > 2 * np.ptp(xs), (xs.mean(), np.ptp(xs), np.ptp(ys))
