"""Screenshots of the viewer, one per mode, for the docs (docs/viewer/*.png): made in Debian's chromium driven
by Playwright, the way tests/test_viewer_browser.py drives it (and that test runs this tool on tiny data).

Modes: ``map`` (a map with its drive), ``drive`` (playback: a scan, the pose, the camera with its labels and
uncertainty, the map as it stood then), ``live`` (a map being made, half way), ``store`` (a store's overview
with a tile in full), ``compare`` (two maps against the ground truth), ``terrain`` (the traversability cost
as a height surface). The data is a synthetic drive (``--world``, ``--frames``), mapped here.

    python tools/viewer_screenshots.py [--world demo] [--frames 16] [--out docs/viewer] [--modes map drive ...]
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import threading
import time
from io import BytesIO
from pathlib import Path
from types import SimpleNamespace

import numpy as np

REPO = Path(__file__).resolve().parents[1]
CHROMIUM_ARGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--disable-gpu",
                 "--disable-background-networking", "--disable-component-update", "--no-first-run"]


def build_data(work: Path, preset: str, frames: int) -> SimpleNamespace:
    """A synthetic drive, alpha files standing in for a network's, two maps of it, its ground truth and a store."""
    from evsemmap_warp.apps.cli import main as evsemmap
    from evsemmap_warp.synthetic.preset import load_preset
    from evsemmap_warp.synthetic.writer import generate_sequence, write_stand_in_alpha

    data = SimpleNamespace(sequence=work / "sequence", alpha=work / "alpha", ebs=work / "ebs.npz", sbki=work / "s-bki.npz",
                           alpha_map=work / "ebs_alpha.npz", truth=work / "project" / "ground_truth.npz", store=work / "store")
    generate_sequence(load_preset(preset, trajectory__frames=frames), data.sequence, progress=False)
    write_stand_in_alpha(data.sequence, data.alpha)  # sure on the right half of each image, unsure on the left
    quiet = ["--quiet"]
    for method, out in (("ebs", data.ebs), ("s-bki", data.sbki)):
        assert evsemmap(["map", str(data.sequence), "rellis3d", "--method", method, "--out", str(out)] + quiet) == 0
    assert evsemmap(["map", str(data.sequence), "rellis3d", "--method", "ebs", "--alpha-dir", str(data.alpha), "--bin-frames", "1",
                     "--out", str(data.alpha_map)] + quiet) == 0
    assert evsemmap(["project", str(data.sequence), "--out", str(work / "project"), "--overlays", "0"]) == 0
    assert evsemmap(["batch", str(data.sequence), "rellis3d", "--method", "ebs", "--out", str(data.store), "--tile-voxels", "64",
                     "--workers", "1"] + quiet) == 0
    return data


def _wait(predicate, timeout: float = 60.0) -> bool:
    end = time.time() + timeout
    while time.time() < end:
        if predicate():
            return True
        time.sleep(0.1)
    return False


def class_pixels(png: bytes) -> int:
    """Pixels of the scene (left of the GUI panel) within 30 of a class color."""
    from PIL import Image

    from evsemmap_warp.apps.viewer.colors import CLASS_COLORS

    image = np.asarray(Image.open(BytesIO(png)).convert("RGB")).astype(int)[:, :900]
    near = np.zeros(image.shape[:2], bool)
    for name, color in CLASS_COLORS.items():
        if name not in ("void", "sky"):
            near |= np.abs(image - np.array(color)).max(axis=2) < 30
    return int(near.sum())


def _open(browser, viewer):
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    page.goto(viewer.url)
    page.get_by_text("Color by").first.wait_for(timeout=180_000)
    return page


def _shoot(page, path: Path, *, drawn=lambda png: class_pixels(png) > 2000) -> Path:
    """Wait for the scene, let it settle, dismiss the software-rendering notice, and write the screenshot."""
    assert _wait(lambda: drawn(page.screenshot()), 120), f"{path.name}: the scene was never drawn"
    for close in page.locator("button.mantine-Notification-closeButton").all():
        close.click()
    time.sleep(2.0)
    path.write_bytes(page.screenshot())
    return path


def _shoot_map(data: SimpleNamespace, browser, path: Path) -> Path:
    from evsemmap_warp.apps.viewer import MapViewer, free_port

    viewer = MapViewer([data.ebs], port=free_port(), trajectory=data.sequence / "poses.txt")
    try:
        return _shoot(_open(browser, viewer), path)
    finally:
        viewer.close()


def _shoot_drive(data: SimpleNamespace, browser, path: Path) -> Path:
    from evsemmap_warp.apps.viewer import MapViewer, free_port
    from evsemmap_warp.apps.viewer.drive import DrivePlayback, open_drive

    drive, replay = open_drive(data.alpha_map, [data.sequence, "rellis3d"], alpha_dir=data.alpha, bin_frames=1, snapshot_every=4)
    viewer = MapViewer([data.alpha_map], port=free_port())
    playback = DrivePlayback(viewer, drive, replay, precompute=False)
    try:
        page = _open(browser, viewer)
        playback.show(len(drive) // 2)
        assert playback.wait_until_drawn(len(drive) // 2, 120), playback.errors
        page.get_by_text("predicted labels").first.scroll_into_view_if_needed()
        return _shoot(page, path)
    finally:
        playback.close()
        viewer.close()


def _shoot_live(data: SimpleNamespace, browser, path: Path) -> Path:
    """The live map half way through the drive: its mapping held there until the screenshot is taken."""
    from evsemmap_warp import Mapper
    from evsemmap_warp.apps.scan_sources import open_scan_source
    from evsemmap_warp.apps.viewer import MapLayer, MapViewer, free_port
    from evsemmap_warp.apps.viewer.live import LiveMap, map_live
    from evsemmap_warp.config import load_config

    run = load_config([str(data.sequence), "rellis3d"], method="ebs")
    source = open_scan_source(run)
    mapper = Mapper.for_dataset(source, run.mapping)
    target = data.ebs.with_name("live.npz")
    viewer = MapViewer([MapLayer.from_mapper("live", target, mapper)], port=free_port())
    live = LiveMap(viewer, mapper, name="live", path=target, scan_total=len(source))
    half = threading.Event()

    def held_at_half():
        for k, scan in enumerate(source):
            if k == len(source) // 2:
                half.wait(300)
            yield scan

    mapping = threading.Thread(target=map_live, args=(mapper, held_at_half(), live), kwargs={"every": 2}, daemon=True)
    try:
        page = _open(browser, viewer)
        mapping.start()
        assert _wait(lambda: live.updates >= 1 and not live.busy, 120), live.errors
        return _shoot(page, path)
    finally:
        half.set()
        mapping.join(300)
        live.close()
        viewer.close()


def _shoot_store(data: SimpleNamespace, browser, path: Path) -> Path:
    from evsemmap_warp.apps.viewer import MapViewer, free_port

    viewer = MapViewer([data.store], port=free_port(), max_voxels=20_000)
    overview = viewer.stores[0]
    try:
        page = _open(browser, viewer)
        assert _wait(lambda: overview.complete)
        middle = viewer.layers[0].centers.mean(axis=0)
        viewer.tiles.request(0, overview.tiles_at(middle))
        assert _wait(lambda: "tile(s) in full" in viewer.gui_status.content)
        return _shoot(page, path)
    finally:
        viewer.close()


def _shoot_compare(data: SimpleNamespace, browser, path: Path) -> Path:
    """The map from the camera's labels against the map from the LiDAR's, and who agrees with the projected truth."""
    from evsemmap_warp.apps.viewer.comparison import DIFF_COLORS
    from evsemmap_warp.apps.viewer import MapViewer, free_port

    viewer = MapViewer([data.alpha_map, data.sbki], port=free_port(), truth=data.truth)
    try:
        page = _open(browser, viewer)
        viewer.gui_diff.value = "labels differ"
        page.get_by_text("labels differ in").first.scroll_into_view_if_needed()

        def drawn(png):
            from PIL import Image

            image = np.asarray(Image.open(BytesIO(png)).convert("RGB")).astype(int)[:, :900]
            return sum(int((np.abs(image - np.array(c)).max(axis=2) < 30).sum()) for c in DIFF_COLORS.values()) > 200

        return _shoot(page, path, drawn=drawn)
    finally:
        viewer.close()


def _shoot_terrain(data: SimpleNamespace, browser, path: Path) -> Path:
    from evsemmap_warp.apps.viewer import MapViewer, free_port

    viewer = MapViewer([data.ebs], port=free_port(), terrain=True)
    try:
        page = _open(browser, viewer)
        viewer.gui_terrain_mode.value = "surface instead of the voxels"
        viewer.gui_terrain_band.value = "traversability_cost"
        return _shoot(page, path, drawn=lambda png: _drawn_surface(png))
    finally:
        viewer.close()


SHOTS = {"map": _shoot_map, "drive": _shoot_drive, "live": _shoot_live, "store": _shoot_store, "compare": _shoot_compare,
         "terrain": _shoot_terrain}
MODES = tuple(SHOTS)


def shoot(mode: str, data: SimpleNamespace, browser, out: Path) -> Path:
    """The screenshot of ``mode`` (one of MODES) written to ``out``/MODE.png."""
    if mode not in SHOTS:
        raise ValueError(f"mode {mode!r}: one of {', '.join(MODES)}")
    return SHOTS[mode](data, browser, out / f"{mode}.png")


def _drawn_surface(png: bytes) -> bool:
    """Enough colored (not grey or white) pixels in the scene: the cost surface is drawn."""
    from PIL import Image

    image = np.asarray(Image.open(BytesIO(png)).convert("RGB")).astype(int)[:, :900]
    return int((image.max(axis=2) - image.min(axis=2) > 60).sum()) > 5000


def main(argv=None) -> list[Path]:
    from playwright.sync_api import sync_playwright

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--world", default="demo", help="the synthetic world (default demo)")
    parser.add_argument("--frames", type=int, default=16, help="frames of its drive (default 16)")
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "viewer")
    parser.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES))
    args = parser.parse_args(argv)
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        raise SystemExit("viewer_screenshots: no chromium on PATH (apt-get install chromium)")
    args.out = args.out.resolve()
    args.out.mkdir(parents=True, exist_ok=True)
    written = []
    with tempfile.TemporaryDirectory(prefix="evsemmap_screenshots_") as work:
        cwd = os.getcwd()
        os.chdir(work)  # the GUI shows the paths as a user typing the commands there would give them
        try:
            data = build_data(Path("."), args.world, args.frames)
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path=chromium, headless=True, args=CHROMIUM_ARGS)
                try:
                    for mode in args.modes:
                        started = time.perf_counter()
                        written.append(shoot(mode, data, browser, args.out))
                        print(f"wrote {written[-1]} ({time.perf_counter() - started:.0f} s)")
                finally:
                    browser.close()
        finally:
            os.chdir(cwd)
    return written


if __name__ == "__main__":
    main()
