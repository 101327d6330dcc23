"""The interactive HTML viewer: self-contained, and drawn by a real headless browser."""

from __future__ import annotations

import base64
import json
import re
import shutil
import subprocess

import numpy as np
import pytest
import trimesh
from PIL import Image

from ultraboneudf.evaluation import reference_points, viewer_html, write_viewer


def scene():
    gt = trimesh.creation.icosphere(subdivisions=3, radius=10.0)
    recon = trimesh.Trimesh(gt.vertices * 1.05, gt.faces, process=False)
    pts = gt.vertices + np.random.default_rng(0).normal(size=gt.vertices.shape) * 0.2
    return recon, gt, pts


def test_page_is_self_contained_and_embeds_the_data():
    recon, gt, pts = scene()
    page = viewer_html(recon, reference=reference_points(gt, samples=20_000), ground_truth=gt, points=pts,
                       title="a <b> title", max_points=100)
    assert "http://" not in page and "https://" not in page and "<script src" not in page
    assert "a &lt;b&gt; title" in page
    meta = json.loads(re.search(r'<script type="application/json" id="meta">(.*?)</script>', page, re.S).group(1))
    data = base64.b64decode(re.search(r'id="data">(.*?)</script>', page, re.S).group(1))
    L = meta["recon"]
    assert L["vertices"] == len(recon.vertices) and L["triangles"] == len(recon.faces)
    idx = np.frombuffer(data, dtype="<u4", count=3 * L["triangles"], offset=L["indices"])
    assert np.array_equal(idx.reshape(-1, 3), recon.faces)
    vals = np.frombuffer(data, dtype="<f4", count=L["vertices"], offset=L["values"])
    assert vals.min() > 0.45 and vals.max() < 0.9  # 1.05 × a 10 mm sphere (+ facet sag)
    assert meta["points"]["count"] == 100 and "gt" in meta
    assert 0.45 < meta["mean"] < 0.7
    assert all(o % 4 == 0 for o in (L["positions"], L["indices"], L["values"], meta["gt"]["positions"]))


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def _chromium(tmp_path, *args: str) -> subprocess.CompletedProcess:
    flags = ["--headless", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader",
             "--enable-unsafe-swiftshader", "--disable-background-networking", "--disable-component-update",
             "--disable-sync", "--no-first-run", "--disable-extensions", "--mute-audio",
             f"--user-data-dir={tmp_path / 'profile'}"]
    return subprocess.run([CHROMIUM, *flags, *args], capture_output=True, text=True, timeout=120)


@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (.ci/run installs Debian's)")
def test_viewer_draws_in_a_headless_browser_offline(tmp_path):
    recon, gt, pts = scene()
    page = tmp_path / "viewer.html"
    write_viewer(page, recon, reference=reference_points(gt, samples=20_000), ground_truth=gt, points=pts)
    dom = _chromium(tmp_path, "--dump-dom", page.as_uri())
    status = re.search(r'<div id="status"[^>]*>([^<]*)<', dom.stdout)
    assert status, dom.stderr[-2000:]
    assert status.group(1).startswith("ready webgl2"), status.group(1)
    assert "<canvas" in dom.stdout
    drawn = int(re.search(r"centre_pixels_drawn=(\d+)", status.group(1)).group(1))
    assert drawn > 1000  # the middle 64×64 pixels show the mesh
    shot = tmp_path / "shot.png"
    _chromium(tmp_path, f"--screenshot={shot}", "--window-size=800,600", page.as_uri())
    img = np.asarray(Image.open(shot).convert("RGB")).astype(int)
    assert img.shape[:2] == (600, 800)
    coloured = (np.abs(img - 255).sum(-1) > 60).mean()
    assert coloured > 0.05  # not blank
    bluish = ((img[..., 2] - img[..., 0]) > 60).mean()
    assert bluish > 0.03  # distance colours (0.5 mm → blue) are on screen


@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (.ci/run installs Debian's)")
@pytest.mark.parametrize("window", ["1280,800", "600,900"])
def test_first_view_frames_a_long_bone_whole(tmp_path, window):
    """A 400 mm × 40 mm shaft, long axis vertical, is on screen end to end in a landscape and a
    portrait window, not cut off at the top and bottom."""
    shaft = trimesh.creation.cylinder(radius=20.0, height=400.0, sections=32)
    page = tmp_path / "shaft.html"
    write_viewer(page, shaft)
    shot = tmp_path / "shaft.png"
    _chromium(tmp_path, f"--screenshot={shot}", f"--window-size={window}", page.as_uri())
    img = np.asarray(Image.open(shot).convert("RGB")).astype(int)
    drawn = np.abs(img - 255).sum(-1) > 60
    h, centre = drawn.shape[0], drawn.shape[1] // 2   # the shaft's column, beside the panel
    rows = np.flatnonzero(drawn[: h - 20, centre - 4: centre + 5].any(axis=1))   # above the status line
    assert rows.size and rows[0] > 0.02 * h and rows[-1] < h - 30, (rows[:1], rows[-1:], h)
    assert rows[-1] - rows[0] > 0.5 * h   # and not lost in the distance
