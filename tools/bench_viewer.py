"""Viewer benchmark in real Chromium: how soon a map store's first frame shows, how the viewer answers while the
overview fills in, and what the server and the browser hold.

The stores are the synthetic ``long`` drive's (``evsemmap synth --world long --no-camera --frames N`` then
``evsemmap batch``), one per ``--frames`` number, built once under ``--work`` unless ``--store`` names them;
each is opened with the same ``--max-voxels``, so that what the server holds can be compared across sizes. ``evsemmap view STORE`` runs as
a user starts it (a fresh process, imports included); Debian's chromium, driven by Playwright as
tests/test_viewer_browser.py drives it, opens the page. Measured:

- ``ready_s``: from starting the command to its "open http://..." line (the server serves);
- ``first_frame_s``: from starting the command to the first screenshot showing voxels in class colors
  (screenshots are polled, so this is an upper bound by about one screenshot's time);
- ``overview_complete_s``: until the page's counter no longer says tiles are being read;
- ``control_round_trip_s``: a click on *Show FREE* until the page's counter changes (during the filling
  in when it is still under way, and after it);
- ``approach_s``: zooming in with the mouse wheel until the page says a tile is shown in full;
- ``fly_to_tile_s``: choosing the first tile along the store in *Store tile in full* until the page's line on
  what lies under the screen's center names a point over that tile (the camera flown there);
- memory: the server process's resident set (``VmRSS``, and its peak ``VmHWM``) at each stage, the
  browser's processes' resident sets summed, and the page's JavaScript heap.

Chromium renders with SwiftShader here (no GPU): drawing is the CPU's, and slow for large scenes; the
times are this machine's, stated with its load in the record. The results go to a run record
(docs/bench/bench_viewer-<UTC>.json, tools/bench_record.py); the last line printed is its path.

    python tools/bench_viewer.py [--frames 200 400] [--store DIR ...] [--work DIR] [--max-voxels 200000]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import threading
import time
from io import BytesIO
from pathlib import Path

import numpy as np

from bench_record import write_record

REPO = Path(__file__).resolve().parents[1]
EVSEMMAP = [sys.executable, "-m", "evsemmap_warp.apps.cli"]
CHROMIUM_ARGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--disable-gpu",
                 "--disable-background-networking", "--disable-component-update", "--no-first-run"]


def build_store(work: Path, frames: int) -> Path:
    """The long drive's first ``frames`` frames as a store (kept under ``work`` for later runs)."""
    drive, store = work / f"long_{frames}", work / f"long_{frames}_store"
    if not (drive / "poses.txt").is_file():
        subprocess.run(EVSEMMAP + ["synth", "--world", "long", "--no-camera", "--frames", str(frames), "--out", str(drive), "--quiet"],
                       check=True)
    if not (store / "store.json").is_file():
        shutil.rmtree(store, ignore_errors=True)
        subprocess.run(EVSEMMAP + ["batch", str(drive), "--method", "ebs", "--out", str(store), "--quiet"], check=True,
                       stdout=subprocess.DEVNULL)
    return store


def memory_kb(pid: int) -> dict:
    """VmRSS and VmHWM of a process (kB), from /proc."""
    out = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            out[key] = int(value.split()[0])
    return out


def descendants(pid: int) -> list[int]:
    parents = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                parents[int(entry.name)] = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                pass
    found, frontier = [], [pid]
    while frontier:
        children = [p for p, parent in parents.items() if parent in frontier]
        found += children
        frontier = children
    return found


def browser_rss_mb(server_pid: int) -> float:
    """The resident sets of Chromium's processes (this process's descendants other than the server), summed."""
    total = 0
    for pid in descendants(os.getpid()):
        if pid == server_pid:
            continue
        try:
            if "chrom" in Path(f"/proc/{pid}/comm").read_text():
                total += memory_kb(pid).get("VmRSS", 0)
        except OSError:
            pass
    return round(total / 1024, 1)


def voxel_pixels(page, colors: np.ndarray) -> int:
    """Pixels of the scene (left of the GUI panel) within 30 of a class color."""
    from PIL import Image

    image = np.asarray(Image.open(BytesIO(page.screenshot())).convert("RGB")).astype(int)[:, :900]
    near = np.zeros(image.shape[:2], bool)
    for color in colors:
        near |= np.abs(image - color).max(axis=2) < 30
    return int(near.sum())


def counter(page) -> str:
    match = re.search(r"[\d,]+ voxels drawn of about [^\n]*|[\d,]+ of [\d,]+ visible voxels drawn[^\n]*", page.inner_text("body"))
    return match.group(0) if match else ""


def click_round_trip(page, timeout: float = 120.0) -> float | None:
    """Seconds from a click on *Show FREE* until the page's counter changes (None: it did not within ``timeout``)."""
    before = counter(page)
    started = time.perf_counter()
    page.get_by_label("Show FREE", exact=True).click()
    while time.perf_counter() - started < timeout:
        if counter(page) != before:
            return round(time.perf_counter() - started, 2)
        time.sleep(0.05)
    return None


def fly_to_first_tile(page, index, timeout: float = 120.0) -> tuple[str, float | None]:
    """Choose the first tile along the store in *Store tile in full*: (its label, seconds until the page says the
    screen's center is over it; None: not within ``timeout``)."""
    page.get_by_label("Store tile in full", exact=True).click()
    option = page.get_by_role("option").filter(has_text="tile (").first
    label = option.inner_text().strip()
    name = "_".join(re.search(r"tile \((-?\d+), (-?\d+), (-?\d+)\)", label).groups())
    low, high = (np.asarray(corner, np.float64) for corner in index.tiles[name]["bounds_m"])
    started = time.perf_counter()
    option.click()
    while time.perf_counter() - started < timeout:
        found = re.search(r"under the screen's center \([^)]*\): x=([-\d.]+), y=([-\d.]+)", page.inner_text("body"))
        if found and np.all((np.array(found.groups(), float) >= low[:2]) & (np.array(found.groups(), float) <= high[:2])):
            return label, round(time.perf_counter() - started, 2)
        time.sleep(0.1)
    return label, None


def measure(store: Path, max_voxels: int, port: int) -> dict:
    from playwright.sync_api import sync_playwright

    from evsemmap_warp.apps.viewer.colors import CLASS_COLORS
    from evsemmap_warp.core.map_store import MapStore

    index = MapStore(store)
    colors = np.array([CLASS_COLORS[name] for name in index.class_names if name in CLASS_COLORS and name not in ("void", "sky")])
    results = {"store": {"path": str(store), "voxels": index.voxel_count, "tiles": len(index.tiles), "scans": int(index.index["scans"]),
                         "tile_voxels": index.tile_voxels},
               "max_voxels": max_voxels}
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        raise SystemExit("bench_viewer: no chromium on PATH (apt-get install chromium)")
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium, headless=True, args=CHROMIUM_ARGS)
        page = browser.new_page(viewport={"width": 1280, "height": 800})
        started = time.perf_counter()
        server = subprocess.Popen(EVSEMMAP + ["view", str(store), "--port", str(port), "--max-voxels", str(max_voxels)],
                                  stderr=subprocess.PIPE, text=True)
        try:
            lines = []
            for line in server.stderr:  # the URL line says the server serves
                lines.append(line)
                if "open http" in line:
                    break
            else:
                raise SystemExit("bench_viewer: the viewer ended before serving:\n" + "".join(lines))
            threading.Thread(target=lambda: [None for _ in server.stderr], daemon=True).start()  # keep its pipe drained
            results["ready_s"] = round(time.perf_counter() - started, 2)
            url = re.search(r"http://\S+", lines[-1]).group(0)
            page.goto(url)
            page.get_by_text("Color by").first.wait_for(timeout=120_000)
            while voxel_pixels(page, colors) < 2000:
                if time.perf_counter() - started > 600:
                    raise SystemExit("bench_viewer: no voxels drawn after 600 s")
                time.sleep(0.1)
            results["first_frame_s"] = round(time.perf_counter() - started, 2)
            results["first_frame_counter"] = counter(page)
            stages = {"first_frame": {"server": memory_kb(server.pid), "browser_rss_mb": browser_rss_mb(server.pid),
                                      "js_heap_mb": page.evaluate("() => performance.memory.usedJSHeapSize / 2**20")}}
            results["control_round_trip_s"] = {}
            if "reading its tiles" in results["first_frame_counter"]:
                results["control_round_trip_s"]["while_filling_in"] = click_round_trip(page)
            while "reading its tiles" in counter(page):
                time.sleep(0.1)
            results["overview_complete_s"] = round(time.perf_counter() - started, 2)
            results["overview_counter"] = counter(page)
            time.sleep(2.0)
            stages["overview"] = {"server": memory_kb(server.pid), "browser_rss_mb": browser_rss_mb(server.pid),
                                  "js_heap_mb": page.evaluate("() => performance.memory.usedJSHeapSize / 2**20")}
            results["control_round_trip_s"]["after_filling_in"] = click_round_trip(page)
            # zoom in on the middle of the view until a tile is shown in full
            approach = time.perf_counter()
            page.mouse.move(450, 400)
            steps = 0
            while "tile(s) in full" not in counter(page) and time.perf_counter() - approach < 300:
                page.mouse.wheel(0, -1500)
                steps += 1
                time.sleep(0.5)
            results["approach_s"] = round(time.perf_counter() - approach, 2) if "tile(s) in full" in counter(page) else None
            results["approach_wheel_steps"] = steps
            results["approach_counter"] = counter(page)
            time.sleep(2.0)
            stages["tile_in_full"] = {"server": memory_kb(server.pid), "browser_rss_mb": browser_rss_mb(server.pid),
                                      "js_heap_mb": page.evaluate("() => performance.memory.usedJSHeapSize / 2**20")}
            results["chosen_tile"], results["fly_to_tile_s"] = fly_to_first_tile(page, index)
            for stage in stages.values():
                stage["server_rss_mb"] = round(stage["server"].pop("VmRSS") / 1024, 1)
                stage["server_peak_rss_mb"] = round(stage["server"].pop("VmHWM") / 1024, 1)
                stage["js_heap_mb"] = round(stage["js_heap_mb"], 1)
                del stage["server"]
            results["memory"] = stages
        finally:
            server.terminate()
            server.wait(timeout=30)
            browser.close()
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, nargs="+", default=[200, 400],
                        help="frames of the long drive to build a store from, one store per number (default 200 400)")
    parser.add_argument("--store", type=Path, nargs="+", default=None, help="stores to open instead of building them")
    parser.add_argument("--work", type=Path, default=Path("/tmp/evsemmap_bench_viewer"), help="where the drive and store are built and kept")
    parser.add_argument("--max-voxels", type=int, default=200_000, help="the viewer's --max-voxels (its overview's size; default 200000)")
    parser.add_argument("--port", type=int, default=8097)
    args = parser.parse_args()
    started = time.time()
    stores = args.store or [build_store(args.work, frames) for frames in args.frames]
    results = {"runs": []}
    for store in stores:  # the same overview size for stores of different sizes: the server's memory should not follow the store's
        results["runs"].append(measure(store, args.max_voxels, args.port))
        print(json.dumps(results["runs"][-1], indent=1))
    print(write_record("bench_viewer", results, started=started))


if __name__ == "__main__":
    main()
