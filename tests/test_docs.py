"""The documentation site: it builds warning-free, and in a browser its landing page shows the first
figure and its CLI reference names every subcommand and option (screenshots under the build folder)."""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import pocoloco
from pocoloco.cli import build_parser

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """The site built with warnings as errors, as scripts/docs.sh builds it."""
    pytest.importorskip("sphinx")
    out = tmp_path_factory.mktemp("site") / "html"
    r = subprocess.run([sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html", str(ROOT / "docs"),
                        str(out)], capture_output=True, text=True, timeout=600)  # fmt: skip
    assert r.returncode == 0, r.stderr[-4000:]
    return out


def _chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        if shutil.which(name):
            return shutil.which(name)
    return None


def _browse(page: Path, shot: Path) -> str:
    """The DOM of ``page`` as headless Chromium renders it, and a screenshot at ``shot``."""
    exe = _chromium()
    if exe is None:
        pytest.skip("chromium is not installed (apt-get install chromium) - the site is not opened in a browser")
    flags = [exe, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
             "--disable-component-update", "--disable-sync", "--window-size=1200,900", "--hide-scrollbars"]  # fmt: skip
    dom = subprocess.run([*flags, "--dump-dom", page.as_uri()], capture_output=True, text=True, timeout=120)
    subprocess.run([*flags, f"--screenshot={shot}", page.as_uri()], capture_output=True, text=True, timeout=120)
    assert "</html>" in dom.stdout, dom.stderr[-2000:]
    return dom.stdout


def _subcommands(parser: argparse.ArgumentParser, prefix: str = "") -> dict[str, argparse.ArgumentParser]:
    out = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                out[f"{prefix}{name}"] = sub
                out.update(_subcommands(sub, f"{prefix}{name} "))
    return out


def test_landing_page_shows_the_first_figure_and_the_two_commands(site):
    dom = _browse(site / "index.html", site / "screenshot_index.png")
    img = re.search(r'<img[^>]+src="([^"]*default_model_demo_skirt\.png)"', dom)
    assert img, "the first figure is not on the landing page"
    assert (site / img.group(1)).is_file()
    text = re.sub(r"<[^>]+>", "", dom)  # code blocks are split into highlighted spans
    assert "scripts/setup.sh" in text and "pocoloco.load" in text
    assert (site / "screenshot_index.png").stat().st_size > 10_000


def test_cli_reference_names_every_subcommand_and_option(site):
    dom = _browse(site / "reference" / "cli.html", site / "screenshot_cli.png")
    text = re.sub(r"<[^>]+>", "", dom)  # usage lines are split into highlighted spans
    text = re.sub(r"\s+", " ", text.replace("&nbsp;", " "))
    subs = _subcommands(build_parser())
    assert len(subs) >= 20
    missing = [name for name in subs if f"pocoloco {name}" not in text]
    assert not missing, f"subcommands missing from the CLI reference: {missing}"
    options = {o for sub in subs.values() for a in sub._actions for o in a.option_strings if o.startswith("--")}
    absent = sorted(o for o in options if o not in text)
    assert not absent, f"options missing from the CLI reference: {absent}"


def test_api_reference_documents_every_public_name(site):
    html = (site / "reference" / "api.html").read_text()
    for name in pocoloco.__all__:
        if name.startswith("__"):
            continue
        assert re.search(rf'id="pocoloco\.(\w+\.)*{name}"', html), f"pocoloco.{name} is not in the API reference"
        assert getattr(pocoloco, name).__doc__, name
    assert 'id="pocoloco.methods.base.Method.sample"' in html or 'id="pocoloco.methods.Method.sample"' in html
