"""The viewer in a real browser: Debian's chromium, headless, driven by Playwright.

Skipped with a reason where chromium or Playwright is absent (``.ci/run`` installs both). Scenes stay
small (a few thousand voxels): SwiftShader renders 1M points too slowly for a test suite.
"""

import shutil
import time
from io import BytesIO

import numpy as np
import pytest

from evsemmap_warp.apps.viewer import CLASS_COLORS, MapViewer, free_port

from test_viewer import make_map

sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (pip install playwright)")
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="no chromium on PATH (apt-get install chromium)")
ARGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--disable-gpu",
        "--disable-background-networking", "--disable-component-update", "--no-first-run"]


def _pixels_near(png: bytes, rgb, tol=40) -> int:
    from PIL import Image

    img = np.asarray(Image.open(BytesIO(png)).convert("RGB")).astype(int)[:, :900]  # the scene, not the GUI panel
    return int((np.abs(img - np.array(rgb)).max(axis=2) < tol).sum())


def _wait(predicate, timeout=20.0):
    end = time.time() + timeout
    while time.time() < end:
        if predicate():
            return True
        time.sleep(0.1)
    return False


def test_scene_renders_and_controls_change_it(tmp_path):
    make_map(tmp_path / "m.npz")
    viewer = MapViewer([tmp_path / "m.npz"], port=free_port())
    try:
        with sync_api.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=ARGS)
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            page.goto(viewer.url)
            page.get_by_text("Colour by").first.wait_for(timeout=30_000)

            def shot_has(rgb, at_least=2000):
                return lambda: _pixels_near(page.screenshot(), rgb) >= at_least

            assert _wait(shot_has(CLASS_COLORS["grass"])), "grass voxels never appeared"
            assert _pixels_near(page.screenshot(), CLASS_COLORS["object"]) > 500

            # A class checkbox in the page hides that class in the scene.
            page.get_by_label("object", exact=True).click()
            assert _wait(lambda: not viewer.gui_classes["object"].value)
            assert _wait(lambda: _pixels_near(page.screenshot(), CLASS_COLORS["object"]) < 50)

            # The colouring dropdown switches to the variance colour map.
            page.get_by_label("Colour by").click()
            page.get_by_role("option", name="variance").click()
            assert _wait(lambda: viewer.gui_color_by.value == "variance")
            assert _wait(lambda: _pixels_near(page.screenshot(), CLASS_COLORS["grass"]) < 200)
            browser.close()
    finally:
        viewer.server.stop()


def test_far_map_shows_its_frame_origin_and_world_coordinates_of_a_click(tmp_path):
    from test_viewer import FAR, UTM

    make_map(tmp_path / "utm.npz", offset=FAR, frame=UTM)
    viewer = MapViewer([tmp_path / "utm.npz"], port=free_port())
    try:
        with sync_api.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=ARGS)
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            page.goto(viewer.url)
            page.get_by_text("Colour by").first.wait_for(timeout=30_000)
            # 500 km / 4000 km from 0, the voxels still render (float32 positions about the local origin)
            assert _wait(lambda: _pixels_near(page.screenshot(), CLASS_COLORS["grass"]) >= 2000), "grass voxels never appeared"
            page.get_by_text("map (EPSG:32617)").first.wait_for(timeout=10_000)  # the GUI names the frame
            page.get_by_text(viewer.origin_text()).first.wait_for(timeout=10_000)  # the axes' label, and the GUI line
            # a click on the map reports the voxel's centre in world coordinates of the frame
            page.mouse.click(450, 450)
            assert _wait(lambda: "centre in frame 'map' (EPSG:32617): x=500" in viewer.gui_selection.content), viewer.gui_selection.content
            assert "y=4000" in viewer.gui_selection.content
            browser.close()
    finally:
        viewer.server.stop()
