"""Drive playback in the viewer: where a map's voxels came from.

``evsemmap view MAP --drive SOURCE...`` replays the integration of the map file ``MAP`` from the scans it
was made from (a sequence folder or a robot log, labelled as ``evsemmap map`` labelled them: per-point
labels, ``--checkpoint`` or ``--alpha-dir``), read through the same scan sources (``scan_sources``) with the
map's own mapping parameters. A time slider picks a scan; the viewer then shows

- the robot's LiDAR pose at that scan (axes) on the drive's path, and the scan's points colored by
  label or by input uncertainty (K/S of the alpha; 1 - max p for probabilities);
- the frame's camera image, and when a checkpoint or alpha files label the scans, the predicted labels
  and their uncertainty beside it (GUI images);
- the map as it stood after that scan: ``DriveReplay`` keeps a copy of the voxels every
  ``snapshot_every`` scans and integrates forward from the nearest one at or before the scan asked for,
  so a scrub costs at most ``snapshot_every`` scans of mapping; recent maps are cached.

One worker thread does all of it (reading scans, inference, mapping): GUI callbacks only say which scan
is wanted, and a newer wish cancels older work between scans. While nobody scrubs, the worker fills in
the snapshots to the drive's end and then checks that the replay gives the map file back.
"""

from __future__ import annotations

import math
import re
import threading
import time
import traceback
from collections import OrderedDict
from pathlib import Path

import numpy as np

from ...config import ConfigError, PayloadType
from ...core.integrators import ScanPayload
from ...core.mapper import Mapper, prepare_payload, scan_fingerprint
from .colors import TRAJECTORY_COLOR, colormap
from .map_layer import MapLayer, frame_of

SCAN_COLORINGS = ("label", "input uncertainty")
PLAYBACK_BUTTONS = ("◀", "play", "pause", "▶")  # previous scan, play, pause, next scan
_STAMP = re.compile(r"-(\d+)_(\d+)$")  # RELLIS-3D image names: frameNNNNNN-<seconds>_<milliseconds>


class Drive:
    """A scan source's insertions as a drive in time: each insertion's frames, the LiDAR pose (4x4, world
    frame of the source) and time of its last frame, its camera image, and what labels that image.

    ``source``: what ``scan_sources.open_scan_source`` opened: a labelled sequence folder or log, or
    camera-labelled scans (a checkpoint or alpha files). Other sources (point files, a bench npz) have no
    poses: a ValueError naming ``where`` says so."""

    def __init__(self, source, where: str):
        from ...data.datasets import LabelledSequence
        from ..scan_sources import AlphaFileScans, CheckpointScans

        self.source = source
        if isinstance(source, (CheckpointScans, AlphaFileScans)):
            self.sequence, self.world = source.sequence, source.sequence.world
            self.insertions = [source.insertion_frames(k) for k in range(len(source))]
            self.labelled_by = "checkpoint" if isinstance(source, CheckpointScans) else "alpha files"
        elif isinstance(source, LabelledSequence):
            self.sequence, self.world = source.sequence, source.world
            self.insertions = [[frame] for frame in source.frames]
            self.labelled_by = None
        else:
            raise ValueError(f"{where}: a {type(source).__name__} has no poses or camera: playback needs a sequence "
                             "folder (with poses.txt) or a robot log")
        if getattr(self.sequence, "poses", "") is None:
            raise ValueError(f"{where}: no poses.txt: playback needs the drive's poses")
        if not self.insertions:
            raise ValueError(f"{where}: no scans to play back")
        self.payload_type = PayloadType(getattr(source, "payload_type", PayloadType.LABEL))
        self.poses = np.stack([self.world.to_world(self.sequence.pose(frames[-1])) for frames in self.insertions])
        stamps = [self._stamp_s(frames[-1]) for frames in self.insertions]
        self.times_s = None if any(t is None for t in stamps) else np.asarray(stamps) - stamps[0]

    def __len__(self) -> int:
        return len(self.insertions)

    @staticmethod
    def _stamp_s(frame) -> float | None:
        if getattr(frame, "stamp_ns", None) is not None:  # a log's cloud
            return frame.stamp_ns * 1e-9
        match = _STAMP.search(getattr(frame.image, "stem", "") or "")
        return None if match is None else int(match.group(1)) + int(match.group(2)) / 10 ** len(match.group(2))

    def scan(self, k: int):
        """Insertion ``k`` exactly as the map integrated it (``scan_sources``' Scan)."""
        return next(iter(self.source.scans(k, k + 1)))

    def camera(self, k: int) -> tuple[np.ndarray, np.ndarray | None] | None:
        """(image [H, W, 3] uint8, values [K, h, w] or None) of the last frame of insertion ``k`` that
        has an image; None without one. ``values``: the checkpoint's or alpha file's, when those label the scans."""
        frames = [f for f in self.insertions[k] if f.image is not None]
        if not frames:
            return None
        image = self.sequence.read_image(frames[-1])
        return image, (self.source.frame_values(frames[-1]) if self.labelled_by else None)

    def describe(self, k: int) -> str:
        """Markdown for the panel: which scan ``k`` is, its frames and (when the source has stamps) its time."""
        frames = self.insertions[k]
        which = f"frame {frames[0].index}" if len(frames) == 1 else f"frames {frames[0].index}..{frames[-1].index}"
        when = f", t = {self.times_s[k]:.2f} s" if self.times_s is not None else ""
        return f"scan **{k + 1}** of {len(self)} ({which}{when})"


def pixel_values(values: np.ndarray, payload_type: PayloadType) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel of a [K, H, W] alpha (or probability) image: the predicted class [H, W] and its input
    uncertainty [H, W] in [0, 1] (K/S for alpha, 1 - max p for probabilities)."""
    values = np.asarray(values, np.float64)
    labels = values.argmax(axis=0)
    if payload_type is PayloadType.PROB:
        return labels, 1.0 - values.max(axis=0) / np.maximum(values.sum(axis=0), 1e-12)
    return labels, values.shape[0] / np.maximum(values.sum(axis=0), 1e-12)


def at_image_size(per_pixel: np.ndarray, height: int, width: int) -> np.ndarray:
    """A per-pixel array [h, w] of the network's output size at the camera image's size [height, width]
    (nearest pixel): a checkpoint labels its input size, and its labels and uncertainty are shown beside the
    camera image at the image's scale."""
    rows = np.arange(height) * per_pixel.shape[0] // height
    columns = np.arange(width) * per_pixel.shape[1] // width
    return per_pixel[rows[:, None], columns[None, :]]


def rotation_wxyz(rotation: np.ndarray) -> np.ndarray:
    """The unit quaternion (w, x, y, z) of a 3x3 rotation matrix."""
    import viser.transforms as tf

    return np.asarray(tf.SO3.from_matrix(np.asarray(rotation, np.float64)).wxyz)


class DriveReplay:
    """The map after any number of a drive's scans, by replaying its integration with ``config``.

    A copy of the voxels is kept after every ``snapshot_every`` scans (at most ``max_snapshots`` copies:
    the interval grows for long drives); ``map_after(n)`` integrates from the nearest copy at or before
    ``n``, or carries on from the map it built last when that is nearer. Not thread-safe: one thread
    (the playback's worker) uses it."""

    def __init__(self, source, config, *, origin_m, snapshot_every: int = 10, max_snapshots: int = 64, device: str = "cpu"):
        if snapshot_every < 1:
            raise ValueError(f"snapshot_every must be at least 1, got {snapshot_every}")
        self.source, self.config, self.origin_m, self.device = source, config, np.asarray(origin_m, np.float64), device
        self.scan_count = len(source)
        self.snapshot_every = max(int(snapshot_every), math.ceil(self.scan_count / max_snapshots))
        self.snapshots: dict[int, object] = {0: None}  # scans integrated -> VoxelArrays (None: the empty map)
        self.mapper = None
        self.integrated = 0  # scans ``mapper`` holds
        self.last_start = 0  # where the last map_after started from (a snapshot, or the map it carried on)

    def _restored(self, scans: int):
        mapper = Mapper.for_dataset(self.source, self.config, device=self.device, origin=self.origin_m)
        if self.snapshots[scans] is not None:
            mapper.load_voxels(self.snapshots[scans], origin_index=mapper.origin_index)
        return mapper

    def map_after(self, scans: int, cancelled=lambda: False):
        """The Mapper holding the drive's first ``scans`` scans, or None when ``cancelled()`` turned true first."""
        if not 0 <= scans <= self.scan_count:
            raise ValueError(f"scans must lie in 0..{self.scan_count}, got {scans}")
        start = max(c for c in self.snapshots if c <= scans)
        if self.mapper is None or not start <= self.integrated <= scans:
            self.mapper, self.integrated = self._restored(start), start
        self.last_start = self.integrated
        while self.integrated < scans:
            # up to the next snapshot boundary, so that a snapshot is taken with no scan in flight
            stop = min(scans, (self.integrated // self.snapshot_every + 1) * self.snapshot_every)
            self._integrate(stop, cancelled)
            if self.integrated % self.snapshot_every == 0 or self.integrated == self.scan_count:
                self.snapshots.setdefault(self.integrated, self.mapper.voxels()[0])
            if self.integrated < stop:
                return None
        return self.mapper

    def _integrate(self, stop: int, cancelled) -> None:
        def until_cancelled():
            for scan in self.source.scans(self.integrated, stop):
                if cancelled():
                    return
                yield scan

        def count(_scan, _stats):
            self.integrated += 1

        self.mapper.integrate_many(until_cancelled(), progress=count)

    def next_missing_snapshot(self) -> int | None:
        """The first snapshot boundary (or the drive's end) not yet reached; None when all are."""
        for scans in list(range(self.snapshot_every, self.scan_count, self.snapshot_every)) + [self.scan_count]:
            if scans not in self.snapshots:
                return scans
        return None


def same_map(layer: MapLayer, other: MapLayer) -> bool:
    """The same voxels with the same labels and states, and concentrations equal up to float64 summation order."""
    return (np.array_equal(layer.voxel_index, other.voxel_index) and np.array_equal(layer.label, other.label)
            and np.array_equal(layer.state, other.state) and np.allclose(layer.alpha, other.alpha, rtol=1e-9, atol=1e-12))


class DrivePlayback:
    """A time slider over ``drive`` on ``viewer``, which shows the map file the drive made as map
    ``map_index``: the robot's pose and scan, the camera, and the map as it stood after the chosen scan
    (``replay``). Handles: ``gui_scan`` (the slider), ``gui_play``, ``gui_scan_color``,
    ``gui_map_as_of``, ``gui_status``, ``gui_camera`` / ``gui_labels`` / ``gui_uncertainty`` (images),
    ``pose_handle``, ``scan_handle``, ``path_handle``. ``precompute``: fill in the snapshots while idle."""

    PLAY_INTERVAL_S = 0.5
    CACHED_MAPS = 8

    def __init__(self, viewer, drive: Drive, replay: DriveReplay, *, map_index: int = 0, precompute: bool = True):
        self.viewer, self.drive, self.replay, self.map_index = viewer, drive, replay, map_index
        self.file_layer = viewer.layers[map_index]
        self.precompute = precompute
        self.palette = np.array([viewer.palette[name] for name in self.file_layer.classes], np.uint8)
        self._maps: OrderedDict[int, MapLayer] = OrderedDict()  # scans integrated -> layer, most recent last
        self._cond = threading.Condition()
        self._wanted = len(drive) - 1
        self._drawn_scan: tuple | None = None  # (scan, coloring) drawn
        self._drawn_map: int | None = None  # scans in the map drawn; None: the map file's own layer
        self._playing = False
        self._stopped = False
        self.replay_check = ""  # the replay's own check against the map file, once it reached the end
        self.map_text = "the map file (all scans)"
        self.errors: list[str] = []
        self._build_gui()
        self.viewer.map_fade = self.MAP_FADE
        self.viewer.refresh()
        self._draw_path()
        self._worker = threading.Thread(target=self._work, name="evsemmap-drive", daemon=True)
        self._worker.start()

    # ------------------------------------------------------------------ GUI
    def _build_gui(self) -> None:
        gui, n = self.viewer.server.gui, len(self.drive)
        folder = self.viewer.gui_drive_folder
        folder.label, folder.visible = "Drive", True
        with folder:
            # the slider counts scans from 1, as the status line names them ("scan 21 of 89")
            self.gui_scan = gui.add_slider("Scan", min=1, max=max(n, 2), step=1, initial_value=n, disabled=n == 1)
            self.gui_play = gui.add_button_group("Playback", PLAYBACK_BUTTONS)
            colorings = SCAN_COLORINGS if self.drive.payload_type is not PayloadType.LABEL else SCAN_COLORINGS[:1]
            self.gui_scan_color = gui.add_dropdown("Color scan by", options=colorings, initial_value="label")
            self.gui_scan_on_top = gui.add_checkbox("Scan over a faded map", initial_value=True)
            self.gui_map_as_of = gui.add_checkbox("Map as of this scan", initial_value=True)
            self.gui_status = gui.add_markdown("")
            blank = np.full((2, 2, 3), 255, np.uint8)
            self.gui_camera = gui.add_image(blank, label="camera", format="jpeg", visible=False)
            self.gui_labels = gui.add_image(blank, label="predicted labels", format="png", visible=False)
            self.gui_uncertainty = gui.add_image(blank, label="uncertainty", format="png", visible=False)
        self.gui_scan.on_update(lambda _event: self.show(self.slider_scan()))
        self.gui_scan_on_top.on_update(lambda _event: self._scan_on_top())
        self.gui_scan_color.on_update(lambda _event: self._wake())
        self.gui_map_as_of.on_update(lambda _event: self._wake())
        self.gui_play.on_click(lambda event: self._on_button(event.target.value))

    def slider_scan(self) -> int:
        """The scan the slider is at, 0-based (the slider counts from 1)."""
        return int(self.gui_scan.value) - 1

    def set_slider(self, k: int) -> None:
        """Move the slider to scan ``k`` (0-based)."""
        self.gui_scan.value = int(k) + 1

    # the map's colors this share of the way to white while the scan is drawn over it: the scan's own colors
    # (the same class colors) stand out, and its points, drawn larger than a voxel, show round the voxels they fall in
    MAP_FADE = 0.65
    SCAN_POINT_VOXELS = 1.5

    def _scan_on_top(self) -> None:
        self.viewer.map_fade = self.MAP_FADE if self.gui_scan_on_top.value else 0.0
        self.viewer.refresh()
        self._drawn_scan = None  # drawn again at its new size
        self._wake()

    def _on_button(self, which: str) -> None:
        k = self.slider_scan()
        if which == PLAYBACK_BUTTONS[0]:
            self._playing = False
            self.set_slider(max(k - 1, 0))
        elif which == PLAYBACK_BUTTONS[3]:
            self._playing = False
            self.set_slider(min(k + 1, len(self.drive) - 1))
        elif which == PLAYBACK_BUTTONS[1]:
            self._playing = True
            if k == len(self.drive) - 1:
                self.set_slider(0)  # from the start again
            self._wake()
        else:
            self._playing = False

    def show(self, k: int) -> None:
        """Show the drive at insertion ``k`` (0-based); the worker draws it."""
        with self._cond:
            self._wanted = int(np.clip(k, 0, len(self.drive) - 1))
            self._cond.notify_all()

    def _wake(self) -> None:
        with self._cond:
            self._cond.notify_all()

    def close(self) -> None:
        """Stop the replay thread (the playback shows nothing new after this)."""
        with self._cond:
            self._stopped = True
            self._cond.notify_all()
        self._worker.join(timeout=30)

    def wait_until_drawn(self, k: int, timeout: float = 60.0) -> bool:
        """Whether scan ``k`` and its map were drawn within ``timeout`` seconds (for tests and scripts)."""
        end = time.time() + timeout
        while time.time() < end:
            wants_map = self.gui_map_as_of.value
            map_done = (self._drawn_map == k + 1) or (k == len(self.drive) - 1 and self._drawn_map is None) if wants_map else \
                self._drawn_map is None
            if self._drawn_scan is not None and self._drawn_scan[0] == k and map_done:
                return True
            time.sleep(0.05)
        return False

    # ------------------------------------------------------------------ worker
    def _current(self) -> int:
        with self._cond:
            return self._wanted

    def _work(self) -> None:
        while True:
            with self._cond:
                while not self._stopped and not self._has_work():
                    self._cond.wait(timeout=0.5)
                if self._stopped:
                    return
                k = self._wanted
            try:
                self._step(k)
            except Exception as exc:  # shown, not raised: the viewer keeps serving
                message = f"{type(exc).__name__}: {exc}"
                self.errors.append(traceback.format_exc())
                self.gui_status.content = f"**Playback stopped:** {message}"
                self._playing = False
                with self._cond:
                    while not self._stopped and self._wanted == k:
                        self._cond.wait(timeout=0.5)

    def _has_work(self) -> bool:
        k = self._wanted
        if self._drawn_scan != (k, self.gui_scan_color.value) or self._map_wanted(k) != self._drawn_map or self._playing:
            return True
        return self.precompute and self.replay.next_missing_snapshot() is not None

    def _map_wanted(self, k: int) -> int | None:
        """Scans in the map to show at scan ``k``; None: the map file's own layer."""
        if not self.gui_map_as_of.value or k == len(self.drive) - 1:
            return None
        return k + 1

    def _step(self, k: int) -> None:
        if self._drawn_scan != (k, self.gui_scan_color.value):
            self._draw_scan(k)
        wanted = self._map_wanted(k)
        if wanted != self._drawn_map:
            self._draw_map(wanted, lambda: self._current() != k)
        elif self._playing:
            time.sleep(self.PLAY_INTERVAL_S)
            if self._playing and self._current() == k:
                if k + 1 < len(self.drive):
                    self.set_slider(k + 1)
                else:
                    self._playing = False
        elif self.precompute:
            self._fill_in_snapshot(lambda: self._current() != k or self._playing)

    def _draw_scan(self, k: int) -> None:
        drive, viewer = self.drive, self.viewer
        coloring = self.gui_scan_color.value
        scan = drive.scan(k)
        payload: ScanPayload = prepare_payload(scan.points, scan.payload, scan.payload_type, len(self.file_layer.classes))
        if coloring == "label":
            colors = self.palette[np.clip(payload.labels, 0, len(self.palette) - 1)]
        else:
            colors = colormap(payload.uncertainty, 0.0, 1.0)
        origin = viewer.origin
        points = (payload.points - origin).astype(np.float32)
        if len(points) == 0:
            points, colors = np.zeros((1, 3), np.float32), np.zeros((1, 3), np.uint8)
        scene = viewer.server.scene
        size = (self.SCAN_POINT_VOXELS if self.gui_scan_on_top.value else 0.5) * self.file_layer.resolution
        with viewer.server.atomic():
            self.scan_handle = scene.add_point_cloud("/drive/scan", points, colors, point_size=size, point_shape="circle",
                                                     precision="float32", visible=len(payload.points) > 0)
            pose = drive.poses[k]
            axes = float(np.clip(8 * self.file_layer.resolution, 0.5, 5.0))
            self.pose_handle = scene.add_frame("/drive/pose", axes_length=axes, axes_radius=axes / 15, wxyz=rotation_wxyz(pose[:3, :3]),
                                               position=tuple(pose[:3, 3] - origin))
        self._draw_camera(k)
        self._drawn_scan = (k, coloring)
        self._status(k)

    def _draw_camera(self, k: int) -> None:
        camera = self.drive.camera(k)
        self.gui_camera.visible = camera is not None
        self.gui_labels.visible = self.gui_uncertainty.visible = camera is not None and camera[1] is not None
        if camera is None:
            return
        image, values = camera
        self.gui_camera.image = image
        if values is not None:
            labels, uncertainty = (at_image_size(v, *image.shape[:2]) for v in pixel_values(values, self.drive.payload_type))
            self.gui_labels.image = self.palette[np.clip(labels, 0, len(self.palette) - 1)]
            self.gui_uncertainty.image = colormap(uncertainty.reshape(-1), 0.0, 1.0).reshape(*uncertainty.shape, 3)
            what = "1 - max p" if self.drive.payload_type is PayloadType.PROB else "K/S"
            self.gui_uncertainty.label = f"uncertainty ({what}: 0 dark, 1 yellow)"
            self.gui_labels.label = f"predicted labels ({self.drive.labelled_by})"

    def _draw_map(self, scans: int | None, cancelled) -> None:
        if scans is None:
            self.viewer.replace_layer(self.map_index, self.file_layer)
            self.map_text = "the map file (all scans)"
            self._drawn_map = None
            self._status(self._current())
            return
        started = time.perf_counter()
        layer = self._maps.get(scans)
        if layer is None:
            mapper = self.replay.map_after(scans, cancelled)
            if mapper is None:
                return  # a newer scan is wanted
            layer = MapLayer.from_mapper(f"{self.file_layer.name} after scan {scans}", self.file_layer.path, mapper)
            self._maps[scans] = layer
            while len(self._maps) > self.CACHED_MAPS:
                self._maps.popitem(last=False)
            source = "the start" if self.replay.last_start == 0 else f"{self.replay.last_start} scans"
            how = f"replayed from {source} in {time.perf_counter() - started:.2f} s"
        else:
            self._maps.move_to_end(scans)
            how = "cached"
        self.viewer.replace_layer(self.map_index, layer)
        self.map_text = f"as it stood after scan {scans} ({len(layer.state):,} voxels; {how})"
        self._drawn_map = scans
        self._status(self._current())

    def _fill_in_snapshot(self, cancelled) -> None:
        scans = self.replay.next_missing_snapshot()
        if scans is None:
            return
        mapper = self.replay.map_after(scans, cancelled)
        if mapper is not None and scans == self.replay.scan_count:
            replayed = MapLayer.from_mapper(self.file_layer.name, self.file_layer.path, mapper)
            if same_map(replayed, self.file_layer):
                self.replay_check = f"replay checked: all {scans} scans give the map file back ({len(replayed.state):,} voxels)"
            else:
                self.replay_check = (f"**the replay differs from the map file** ({len(replayed.state):,} against "
                                     f"{len(self.file_layer.state):,} voxels): was it made from this drive with these options?")
            self._status(self._current())

    def _status(self, k: int) -> None:
        pose = self.drive.poses[k]
        heading = math.degrees(math.atan2(pose[1, 0], pose[0, 0]))
        lines = [self.drive.describe(k),
                 "robot at " + ", ".join(f"{a}={v:.2f}" for a, v in zip("xyz", pose[:3, 3])) + f" m, heading {heading:.0f}°",
                 f"map: {self.map_text}"]
        if self.replay_check:
            lines.append(self.replay_check)
        self.gui_status.content = "\n\n".join(lines)

    def _draw_path(self) -> None:
        positions = (self.drive.poses[:, :3, 3] - self.viewer.origin).astype(np.float32)
        scene = self.viewer.server.scene
        if len(positions) >= 2:
            self.path_handle = scene.add_spline_catmull_rom("/drive/path", positions, color=TRAJECTORY_COLOR, thickness=3.0,
                                                            thickness_units="screen")
        else:
            self.path_handle = scene.add_point_cloud("/drive/path", positions, colors=TRAJECTORY_COLOR, point_size=0.3, precision="float32")


def open_drive(map_path, sources, *, checkpoint=None, alpha_dir=None, bin_frames=None, snapshot_every: int = 10,
               device: str = "cpu") -> tuple[Drive, DriveReplay]:
    """The drive ``sources`` (a sequence folder or robot logs, with the configs or presets they need) that
    made the map file ``map_path``, labelled as it was (``checkpoint`` / ``alpha_dir`` / ``bin_frames`` as
    for ``evsemmap map``), placed in the map's world frame and replayed with the map's mapping parameters.
    Refused (ValueError / ConfigError naming both) when the drive cannot have made the map."""
    from ...config import available_methods, load_config
    from ...core.map_file import mapping_config, read_map_file
    from ...frames import FIRST_SCAN, check_same_frame
    from ..scan_sources import open_scan_source

    map_path = Path(map_path)
    contents = read_map_file(map_path)  # its origin and meta: the read-out is not needed
    meta = contents.meta
    where = " ".join(str(s) for s in sources)
    frame = frame_of(meta, map_path)
    # the drive is placed in the map's own frame (a folder's poses frame by name, or the first scan's)
    name = None if frame is None else FIRST_SCAN if frame.name.startswith(f"{FIRST_SCAN} of ") else frame.name
    # the map's own method, so that the sources' presets are checked against it (its parameters come from the map)
    method = meta["method"] if meta["method"] in available_methods() else None
    run = load_config([str(s) for s in sources], method=method, frame=name, crs=frame.crs if frame is not None else None)
    if run.dataset is None:
        raise ConfigError(f"--drive {where}: no dataset: name a sequence folder or a robot log (with its preset)")
    source = open_scan_source(run, checkpoint=checkpoint, alpha_dir=alpha_dir, bin_frames=bin_frames)
    drive = Drive(source, f"--drive {where}")
    # a map written before runs were recorded takes the drive's run: its scan ids below tell whether the drive made it
    check_same_frame("play back", (str(map_path), frame), (where, source.frame), same_frame=frame is not None and frame.run is None)
    classes = list(meta["classes"])
    if source.num_classes != len(classes):
        raise ValueError(f"--drive {where}: {source.num_classes} classes, but {map_path} has {len(classes)}")
    scan_ids = meta.get("scan_ids")
    if scan_ids:
        first = drive.scan(0)
        payload = prepare_payload(first.points, first.payload, first.payload_type, source.num_classes)
        if scan_fingerprint(payload.points, payload.payload) not in set(scan_ids):
            raise ValueError(f"--drive {where}: its first scan is not one of the scans {map_path} holds: the map was not made from "
                             "this drive (or with other --checkpoint / --alpha-dir / --bin-frames)")
    config = mapping_config(map_path, meta)
    replay = DriveReplay(source, config, origin_m=contents.origin, snapshot_every=snapshot_every, device=device)
    return drive, replay
