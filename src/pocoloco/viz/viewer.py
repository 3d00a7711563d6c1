"""``pocoloco view``: a self-contained HTML viewer for a folder of PLY point clouds.

The page needs no network at view time: the WebGL1 renderer (plain JavaScript,
written for pocoloco, in ``assets/viewer/viewer.js``) and every cloud are inlined;
clouds are base64 float32 positions with optional uint8-quantised normals and
uint8 labels. It shows one cloud at a time: hypotheses (``sample_000.ply`` ... from
``pocoloco sample``) are switched with buttons or the arrow keys, animations
(``frame_0000.ply`` ...) are scrubbed with a slider or played. Orbit with the
mouse (drag), zoom with the wheel, colour by normal, height or label.

After the first frame is drawn the page sets ``window.pocolocoViewer =
{ready, numClouds, numPointsShown, current, coveredPixels, colorMode}`` and mirrors it
on ``<div id="status" data-...>`` (for tests: ``chromium --dump-dom``).
"""

from __future__ import annotations

import base64
import json
import os
import re
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from pocoloco.data.published import check_cloud, read_ply
from pocoloco.utils.atomic import write_text_atomic

__all__ = ["ViewerCloud", "find_clouds", "load_clouds", "build_viewer_html", "write_viewer", "serve_file"]

_NUMBER = re.compile(r"(\d+)")
_FRAME = re.compile(r"^frame_\d+\.ply$", re.IGNORECASE)


@dataclass
class ViewerCloud:
    """One cloud as shown: name, points (n, 3) float32, normals (n, 3) float32 | None,
    labels (n,) int | None, and total = the number of points in the file (n <= total)."""

    name: str
    points: np.ndarray
    normals: np.ndarray | None
    labels: np.ndarray | None
    total: int


def _natural_key(name: str) -> list:
    """'sample_10.ply' after 'sample_9.ply'."""
    return [int(t) if t.isdigit() else t.lower() for t in _NUMBER.split(name)]


def find_clouds(result_dir: str | os.PathLike) -> list[Path]:
    """The ``*.ply`` files directly in ``result_dir``, in natural order. One-line ValueError if none."""
    root = Path(result_dir)
    if not root.exists():
        raise ValueError(f"{root}: no such folder")
    if not root.is_dir():
        raise ValueError(f"{root}: is not a folder (expected a folder of .ply files)")
    files = sorted((p for p in root.iterdir() if p.suffix.lower() == ".ply" and p.is_file()),
                   key=lambda p: _natural_key(p.name))  # fmt: skip
    if not files:
        raise ValueError(f"{root}: no .ply files")
    return files


def load_clouds(files: list[Path], max_points: int = 20000, seed: int = 0) -> list[ViewerCloud]:
    """Read PLY files; clouds with more than ``max_points`` points are subsampled uniformly at
    random (fixed ``seed``, file order kept) so the page stays small and fast."""
    if max_points < 1:
        raise ValueError(f"--max-points must be >= 1, got {max_points}")
    clouds = []
    for path in files:
        ply = read_ply(path)
        n = len(ply.points)
        if n == 0:
            raise ValueError(f"{path}: has no points")
        if ply.faces is None or len(ply.faces) == 0:  # a mesh's vertices may be few
            check_cloud(os.fspath(path), ply.points)
        keep = slice(None)
        if n > max_points:
            keep = np.sort(np.random.default_rng(seed).choice(n, max_points, replace=False))
        normals = None if ply.normals is None else ply.normals[keep]
        labels = None if ply.labels is None else ply.labels[keep]
        clouds.append(ViewerCloud(path.name, ply.points[keep], normals, labels, n))
    return clouds


def _b64(a: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(a).tobytes()).decode("ascii")


def _payload(clouds: list[ViewerCloud], title: str, fps: float) -> dict:
    """JSON-able description of the clouds (arrays as base64 little-endian bytes)."""
    allp = np.concatenate([c.points for c in clouds]).astype(np.float64)
    lo, hi = allp.min(0), allp.max(0)
    items = []
    for c in clouds:
        item = {"name": c.name, "n": int(len(c.points)), "total": int(c.total),
                "pos": _b64(c.points.astype("<f4"))}  # fmt: skip
        if c.normals is not None:
            nrm = c.normals / np.maximum(np.linalg.norm(c.normals, axis=1, keepdims=True), 1e-12)
            item["nrm"] = _b64(np.clip(np.round((nrm + 1.0) * 127.5), 0, 255).astype(np.uint8))
        if c.labels is not None:
            item["lab"] = _b64(np.clip(c.labels, 0, 255).astype(np.uint8))
        items.append(item)
    return {
        "version": 1, "title": title, "fps": float(fps), "clouds": items,
        "center": ((lo + hi) / 2).tolist(), "radius": float(max(np.linalg.norm(hi - lo) / 2, 1e-6)),
        "zrange": [float(lo[2]), float(hi[2])],
        "animation": all(_FRAME.match(c.name) for c in clouds) and len(clouds) > 1,
    }  # fmt: skip


def _asset(name: str) -> str:
    return resources.files("pocoloco").joinpath("assets", "viewer", name).read_text(encoding="utf-8")


def build_viewer_html(clouds: list[ViewerCloud], title: str = "pocoloco viewer", fps: float = 10.0) -> str:
    """The complete HTML page (inline CSS, JS and data) for ``clouds``."""
    if not clouds:
        raise ValueError("no clouds to show")
    if not fps > 0:
        raise ValueError(f"--fps must be > 0, got {fps}")
    # "<" escaped so no "</script>" can end the data block early; base64 has no "<" anyway.
    data = json.dumps(_payload(clouds, title, fps), separators=(",", ":")).replace("<", "\\u003c")
    safe_title = title.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
    parts = {"TITLE": safe_title, "CSS": _asset("viewer.css"), "JS": _asset("viewer.js"), "DATA": data}
    # one pass, so a placeholder-like text inside the inserted parts is left alone
    return re.sub(r"\{\{(TITLE|CSS|JS|DATA)\}\}", lambda m: parts[m.group(1)], _asset("viewer.html"))


def write_viewer(
    result_dir: str | os.PathLike, out: str | os.PathLike | None = None, max_points: int = 20000, fps: float = 10.0
) -> tuple[Path, list[ViewerCloud]]:
    """Build the viewer for ``result_dir`` and write it atomically to ``out``
    (default ``RESULT_DIR/viewer.html``). Returns (path, clouds shown)."""
    files = find_clouds(result_dir)
    clouds = load_clouds(files, max_points=max_points)
    html = build_viewer_html(clouds, title=f"pocoloco: {Path(result_dir).resolve().name}", fps=fps)
    target = Path(out) if out is not None else Path(result_dir) / "viewer.html"
    if target.is_dir():
        raise ValueError(f"--out {target}: is a folder")
    write_text_atomic(target, html)
    return target, clouds


def serve_file(path: str | os.PathLike, open_browser: bool = True, port: int = 0) -> None:
    """Serve ``path``'s folder on http://127.0.0.1:PORT (a free port when 0) until Ctrl-C."""
    import functools
    import http.server
    import webbrowser

    path = Path(path).resolve()
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(path.parent))
    with http.server.ThreadingHTTPServer(("127.0.0.1", port), handler) as httpd:
        url = f"http://127.0.0.1:{httpd.server_address[1]}/{path.name}"
        print(f"serving {url} (Ctrl-C to stop)", flush=True)
        if open_browser:
            try:
                webbrowser.open(url)
            except Exception:  # no browser is fine: the URL is printed
                pass
        try:
            httpd.serve_forever()
        except KeyboardInterrupt:
            print("stopped")
