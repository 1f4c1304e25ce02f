"""What ``evsemmap live`` publishes back, in the robot's key format, as ROS 2 messages its own tools read:

- ``/evsemmap/map`` (sensor_msgs/PointCloud2): the occupied voxels' centers (x y z float32, the map's world
  frame) with ``label`` (uint16 class id), ``probability`` (float32, of that class) and ``variance``
  (float32, of that class), every ``map_period_s``;
- ``/evsemmap/grid_map`` (grid_map_msgs/GridMap, every terrain band a layer) and ``/evsemmap/costmap``
  (nav_msgs/OccupancyGrid of the traversability cost: 0..99, lethal 100, unknown -1) over a square window
  around the robot, every ``grid_period_s``;
- ``/evsemmap/diagnostics`` (diagnostic_msgs/DiagnosticArray): scans received, mapped, dropped (by reason)
  and the latency percentiles, every ``diagnostics_period_s``.

Reading the map out and encoding it happens on a thread of its own (``MapPublisher``), from a host copy
of the map's tables taken between two scans: publishing never holds mapping back, and an offer made while
the previous one is still being encoded replaces it."""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from ..apps.viewer.live import LatestOnlyWorker, reading_template
from ..core.mapper import VoxelState
from ..core.voxel_map import VoxelArrays, sum_shard_rows
from ..data.ros_messages import encode_cloud
from ..terrain.outputs import grid_map_data, occupancy_values

MAP_TOPIC = "/evsemmap/map"
GRID_MAP_TOPIC = "/evsemmap/grid_map"
COSTMAP_TOPIC = "/evsemmap/costmap"
DIAGNOSTICS_TOPIC = "/evsemmap/diagnostics"


def _time(T, stamp_ns: int):
    return T["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)


def _header(T, stamp_ns: int, frame_id: str):
    return T["std_msgs/msg/Header"](stamp=_time(T, stamp_ns), frame_id=frame_id)


def _pose(T, x: float, y: float):
    return T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0),
                                      orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))


def map_cloud_message(store, centers: np.ndarray, summary, stamp_ns: int, frame_id: str):
    """The occupied voxels of a read-out as a PointCloud2 (fields as the module text says)."""
    T = store.types
    occupied = summary.state == VoxelState.OCCUPIED
    label = summary.label[occupied]
    probability = summary.probabilities[occupied][np.arange(len(label)), label] if len(label) else np.zeros(0)
    columns = {"x": centers[occupied, 0].astype(np.float32), "y": centers[occupied, 1].astype(np.float32),
               "z": centers[occupied, 2].astype(np.float32), "label": label.astype(np.uint16),
               "probability": probability.astype(np.float32), "variance": summary.variance[occupied].astype(np.float32)}
    attrs = encode_cloud(columns)
    fields = [T["sensor_msgs/msg/PointField"](name=n, offset=o, datatype=d, count=c) for n, o, d, c in attrs.pop("fields")]
    return T["sensor_msgs/msg/PointCloud2"](header=_header(T, stamp_ns, frame_id), fields=fields, is_dense=True, **attrs)


def grid_map_message(store, layers, stamp_ns: int, frame_id: str):
    """ROS 2 grid_map_msgs/GridMap of terrain layers: every band a layer, in grid_map's storage order."""
    T = store.types
    grid = layers.grid
    dims = [T["std_msgs/msg/MultiArrayDimension"](label="column_index", size=grid.height, stride=grid.width * grid.height),
            T["std_msgs/msg/MultiArrayDimension"](label="row_index", size=grid.width, stride=grid.width)]
    layout = T["std_msgs/msg/MultiArrayLayout"](dim=dims, data_offset=0)
    data = [T["std_msgs/msg/Float32MultiArray"](layout=layout, data=grid_map_data(layers.bands[name])) for name in layers.band_names]
    info = T["grid_map_msgs/msg/GridMapInfo"](resolution=float(grid.cell_m), length_x=float(grid.width * grid.cell_m),
                                              length_y=float(grid.height * grid.cell_m),
                                              pose=_pose(T, (grid.x0_m + grid.x1_m) / 2, (grid.y0_m + grid.y1_m) / 2))
    return T["grid_map_msgs/msg/GridMap"](header=_header(T, stamp_ns, frame_id), info=info, layers=list(layers.band_names),
                                          basic_layers=["elevation"], data=data, outer_start_index=0, inner_start_index=0)


def occupancy_grid_message(store, layers, stamp_ns: int, frame_id: str):
    """nav_msgs/OccupancyGrid of the layers' traversability cost (row 0 at the southern edge)."""
    T = store.types
    grid = layers.grid
    values = occupancy_values(layers.bands["traversability_cost"], layers.bands["lethal"])
    header = _header(T, stamp_ns, frame_id)
    info = T["nav_msgs/msg/MapMetaData"](map_load_time=header.stamp, resolution=float(grid.cell_m), width=grid.width, height=grid.height,
                                         origin=_pose(T, grid.x0_m, grid.y0_m))
    return T["nav_msgs/msg/OccupancyGrid"](header=header, info=info, data=np.ascontiguousarray(values[::-1]).reshape(-1))


def diagnostics_message(store, values: dict, stamp_ns: int, *, level: int = 0, message: str = "mapping"):
    """diagnostic_msgs/DiagnosticArray with one status, ``evsemmap live``, holding ``values`` as key-value pairs."""
    T = store.types
    pairs = [T["diagnostic_msgs/msg/KeyValue"](key=str(k), value=str(v)) for k, v in values.items()]
    status = T["diagnostic_msgs/msg/DiagnosticStatus"](level=level, name="evsemmap live", message=message, hardware_id="evsemmap",
                                                       values=pairs)
    return T["diagnostic_msgs/msg/DiagnosticArray"](header=_header(T, stamp_ns, ""), status=[status])


class MapPublisher(LatestOnlyWorker):
    """Publishes the map and the terrain layers of offered map copies on ``node`` (module text). ``window_m``:
    the layers' square around the robot (m a side); ``on_published(kind, scans_in_it, wall_ns)`` after each."""

    def __init__(self, node, mapper, *, map_period_s: float, grid_period_s: float, window_m: float, terrain_config=None,
                 on_published=None):
        self.node, self.store = node, node.store
        self.template = reading_template(mapper)
        self.map_period_s, self.grid_period_s, self.window_m = map_period_s, grid_period_s, window_m
        self.terrain_config = terrain_config
        self.on_published = on_published
        self._next = {"map": 0.0, "grid": 0.0}
        self.published = {"map": 0, "grid": 0}
        self.last_error: str | None = None
        for topic, msgtype in ((MAP_TOPIC, "sensor_msgs/msg/PointCloud2"), (GRID_MAP_TOPIC, "grid_map_msgs/msg/GridMap"),
                               (COSTMAP_TOPIC, "nav_msgs/msg/OccupancyGrid")):
            node.advertise(topic, msgtype)
        super().__init__("evsemmap-live-publish")

    def due(self, now: float | None = None) -> tuple[str, ...]:
        """What is due for publishing now (map, grid), by the periods."""
        now = time.monotonic() if now is None else now
        return tuple(k for k in ("map", "grid") if now >= self._next[k] and (self.map_period_s if k == "map" else self.grid_period_s) > 0)

    def offer(self, mapper, robot_xy, stamp_ns: int, scans: int, *, force: bool = False) -> bool:
        """Between two scans, on the mapping thread: hand over a copy of the map when something is due (``force``:
        everything, now); returns whether a copy was handed over."""
        kinds = ("map", "grid") if force else self.due()
        if not kinds or mapper.origin_index is None:
            return False
        if self.busy and not force:
            return False
        now = time.monotonic()
        for k in kinds:
            self._next[k] = now + (self.map_period_s if k == "map" else self.grid_period_s)
        self.template.frame = mapper.frame
        self.hand_over((kinds, mapper.shard_rows(), np.array(mapper.origin_index), np.asarray(robot_xy, np.float64), stamp_ns, scans))
        return True

    def _draw(self, item) -> None:
        kinds, shards, origin_index, robot_xy, stamp_ns, scans = item
        local = sum_shard_rows(shards)
        voxels = dataclasses.replace(local, index=local.index + origin_index)
        frame_id = self.template.frame.name if self.template.frame is not None else "map"
        if "map" in kinds:
            summary = self.template.summarize(voxels.evidence, voxels.touched)
            self.node.publish_message(MAP_TOPIC, map_cloud_message(self.store, self.template.voxel_centers(voxels.index), summary,
                                                                   stamp_ns, frame_id))
            self._published("map", scans)
        if "grid" in kinds and self.window_m > 0:
            from ..terrain.api import compute_layers

            half = self.window_m / 2
            bounds = [robot_xy[0] - half, robot_xy[1] - half, robot_xy[0] + half, robot_xy[1] + half]
            # only the columns of the window: a cell's layers come from the voxels above it alone (no halo)
            self.template.load_voxels(self._columns_within(voxels, bounds), origin_index=origin_index)
            layers = compute_layers(self.template, bounds=bounds, config=self.terrain_config)
            self.node.publish_message(GRID_MAP_TOPIC, grid_map_message(self.store, layers, stamp_ns, frame_id))
            self.node.publish_message(COSTMAP_TOPIC, occupancy_grid_message(self.store, layers, stamp_ns, frame_id))
            self._published("grid", scans)

    def _columns_within(self, voxels: VoxelArrays, bounds) -> VoxelArrays:
        """The voxels whose x-y column lies within ``bounds`` [x0, y0, x1, y1] (m), two voxels of margin."""
        resolution, offset = self.template.config.resolution_m, self.template.grid_offset_m
        low = np.floor((np.asarray(bounds[:2]) - offset) / resolution).astype(np.int64) - 2
        high = np.floor((np.asarray(bounds[2:]) - offset) / resolution).astype(np.int64) + 2
        xy = voxels.index[:, :2]
        inside = np.all((xy >= low) & (xy <= high), axis=1)
        return VoxelArrays.from_rows(voxels.index[inside], voxels.rows()[inside])

    def _published(self, kind: str, scans: int) -> None:
        self.published[kind] += 1
        if self.on_published is not None:
            self.on_published(kind, scans, time.time_ns())

    def _show_error(self, message: str) -> None:
        from .feed import say

        if message != self.last_error:
            say(f"publishing the map failed: {message} (mapping goes on)")
        self.last_error = message
