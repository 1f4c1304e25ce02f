"""ROS sensor messages as numpy arrays: PointCloud2 (every field type, padding, byte order,
organised clouds), Image and CompressedImage, CameraInfo. Works on the deserialised message objects
``rosbags`` yields (any object with the message's attributes), so nothing here needs ROS or rosbags.
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np
from PIL import Image

from ..geometry.camera import PinholeCamera

# sensor_msgs/PointField datatypes
POINTFIELD_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
POINTFIELD_CODES = {np.dtype(v).str[1:]: k for k, v in POINTFIELD_DTYPES.items()}


class MessageError(ValueError):
    """A message cannot be decoded; the message names what is wrong with it."""


def cloud_dtype(fields, point_step: int, big_endian: bool) -> np.dtype:
    """A structured dtype with the fields at their offsets and the point step as item size, so
    padding between and after fields is skipped without copying."""
    order = ">" if big_endian else "<"
    names, formats, offsets = [], [], []
    for f in fields:
        if f.datatype not in POINTFIELD_DTYPES:
            raise MessageError(f"PointCloud2 field {f.name!r} has unknown datatype {f.datatype}")
        if f.name in names:
            raise MessageError(f"PointCloud2 field {f.name!r} appears twice")
        base = np.dtype(order + POINTFIELD_DTYPES[f.datatype])
        count = max(int(f.count), 1)
        size = base.itemsize * count
        if f.offset + size > point_step:
            raise MessageError(f"PointCloud2 field {f.name!r} (offset {f.offset}, {size} bytes) reaches past point_step {point_step}")
        names.append(f.name)
        formats.append(base if count == 1 else (base, (count,)))
        offsets.append(int(f.offset))
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": int(point_step)})


def decode_cloud(msg) -> np.ndarray:
    """A PointCloud2 message -> structured array [height * width] in row-major order (organised
    clouds flattened row by row); rows padded beyond width * point_step are cut without a copy of
    the payload."""
    height, width, point_step, row_step = int(msg.height), int(msg.width), int(msg.point_step), int(msg.row_step)
    data = np.frombuffer(memoryview(msg.data), np.uint8) if not isinstance(msg.data, np.ndarray) else msg.data.view(np.uint8)
    if height * width == 0:
        return np.zeros(0, cloud_dtype(msg.fields, max(point_step, 1), bool(msg.is_bigendian)))
    if point_step <= 0 or row_step < width * point_step:
        raise MessageError(f"PointCloud2 with point_step {point_step} and row_step {row_step} cannot hold {width} points per row")
    if len(data) < height * row_step:
        raise MessageError(f"PointCloud2 data has {len(data)} bytes, but {height} rows of {row_step} bytes were declared (truncated?)")
    dtype = cloud_dtype(msg.fields, point_step, bool(msg.is_bigendian))
    rows = data[: height * row_step].reshape(height, row_step)[:, : width * point_step]
    return np.ascontiguousarray(rows).view(dtype).reshape(-1)


def cloud_xyz(cloud: np.ndarray, where: str) -> np.ndarray:
    """[N, 3] float64 x y z of a decoded cloud."""
    missing = [n for n in "xyz" if n not in (cloud.dtype.names or ())]
    if missing:
        raise MessageError(f"{where}: the cloud has no field(s) {missing}; fields: {list(cloud.dtype.names or ())}")
    return np.stack([cloud[n].astype(np.float64) for n in "xyz"], axis=1)


def encode_cloud(fields: dict[str, np.ndarray], *, point_step: int | None = None, height: int = 1,
                 big_endian: bool = False, offsets: dict[str, int] | None = None) -> dict:
    """The attributes of a PointCloud2 for columns ``fields`` (name -> [N] array): the inverse of
    ``decode_cloud``, with optional padding (``point_step`` and ``offsets`` as an Ouster driver lays
    them out). Returns plain values for the caller's message class."""
    order = ">" if big_endian else "<"
    offsets = dict(offsets or {})
    layout, at = [], 0
    for name, column in fields.items():
        base = np.dtype(column.dtype).newbyteorder(order)
        offset = offsets.get(name, at)
        layout.append((name, offset, base, column))
        at = max(at, offset + base.itemsize)
    step = point_step or at
    n = len(next(iter(fields.values())))
    if n % height:
        raise MessageError(f"{n} points do not make {height} rows")
    dtype = np.dtype({"names": [l[0] for l in layout], "formats": [l[2] for l in layout], "offsets": [l[1] for l in layout], "itemsize": step})
    packed = np.zeros(n, dtype)
    for name, _, base, column in layout:
        packed[name] = column.astype(base)
    return {"height": height, "width": n // height, "point_step": step, "row_step": step * (n // height), "is_bigendian": big_endian,
            "fields": [(name, offset, POINTFIELD_CODES[np.dtype(base).str[1:]], 1) for name, offset, base, _ in layout],
            "data": packed.view(np.uint8).reshape(-1)}


# Images ------------------------------------------------------------------------------------------
_CHANNELS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "8UC1": 1, "8UC3": 3, "mono16": 1, "16UC1": 1}


def decode_image(msg, where: str) -> np.ndarray:
    """sensor_msgs/Image (rgb8, bgr8, rgba8, bgra8, mono8, mono16) or CompressedImage (jpeg, png)
    -> [H, W, 3] uint8 RGB for color encodings, [H, W] for one-channel ones."""
    if hasattr(msg, "encoding"):
        encoding = msg.encoding
        if encoding not in _CHANNELS:
            raise MessageError(f"{where}: image encoding {encoding!r} is not supported (known: {sorted(_CHANNELS)})")
        channels = _CHANNELS[encoding]
        dtype = np.dtype(">u2" if msg.is_bigendian else "<u2") if "16" in encoding else np.dtype(np.uint8)
        height, width, step = int(msg.height), int(msg.width), int(msg.step)
        data = np.frombuffer(memoryview(msg.data), np.uint8) if not isinstance(msg.data, np.ndarray) else msg.data.view(np.uint8)
        row = width * channels * dtype.itemsize
        if step < row or len(data) < height * step:
            raise MessageError(f"{where}: {len(data)} bytes for a {width}x{height} {encoding} image with step {step} (truncated?)")
        pixels = np.ascontiguousarray(data[: height * step].reshape(height, step)[:, :row]).view(dtype)
        pixels = pixels.reshape(height, width, channels) if channels > 1 else pixels.reshape(height, width)
        if encoding.startswith("bgr"):
            pixels = pixels[..., [2, 1, 0]]
        elif encoding.startswith("rgba"):
            pixels = pixels[..., :3]
        return np.ascontiguousarray(pixels.astype(np.uint16) if "16" in encoding else pixels)
    try:
        with Image.open(io.BytesIO(bytes(msg.data))) as img:
            return np.asarray(img.convert("RGB") if img.mode not in ("L", "I;16", "I") else img)
    except OSError as exc:
        raise MessageError(f"{where}: compressed image ({msg.format!r}) cannot be decoded: {exc}") from None


@dataclass(frozen=True)
class CameraInfo:
    """A decoded sensor_msgs/CameraInfo: the pinhole camera with its distortion, and the header's frame id."""

    camera: PinholeCamera
    frame_id: str


def camera_from_info(msg, where: str) -> CameraInfo:
    """sensor_msgs/CameraInfo -> pinhole camera (plumb_bob / rational_polynomial's first five
    coefficients k1 k2 p1 p2 k3)."""
    k = np.asarray(msg.K if hasattr(msg, "K") else msg.k, np.float64).reshape(-1)
    d = np.asarray(msg.D if hasattr(msg, "D") else msg.d, np.float64).reshape(-1)
    if len(k) != 9 or not np.isfinite(k).all() or k[0] <= 0 or k[4] <= 0:
        raise MessageError(f"{where}: camera matrix K {k.tolist()} is not a pinhole camera")
    if not np.isfinite(d).all():
        raise MessageError(f"{where}: distortion D has NaN or inf: {d.tolist()}")
    model = msg.distortion_model
    if len(d) and model not in ("plumb_bob", "rational_polynomial"):
        raise MessageError(f"{where}: distortion model {model!r} is not supported (plumb_bob or rational_polynomial)")
    if model == "rational_polynomial" and np.any(d[5:] != 0):
        raise MessageError(f"{where}: rational_polynomial with k4..k6 = {d[5:8].tolist()} is not supported (only k1 k2 p1 p2 k3)")
    distortion = tuple(float(v) for v in np.pad(d[:5], (0, max(0, 5 - len(d)))))
    width, height = int(msg.width), int(msg.height)
    if width <= 0 or height <= 0:
        raise MessageError(f"{where}: camera info without an image size ({width}x{height})")
    return CameraInfo(PinholeCamera(float(k[0]), float(k[4]), float(k[2]), float(k[5]), width, height, distortion), msg.header.frame_id)


def header_stamp_ns(raw: bytes | memoryview, ros2: bool) -> int:
    """The header stamp of a serialised message whose first field is a std_msgs/Header, read from
    the raw bytes so clouds and images can be indexed without decoding them."""
    view = memoryview(raw)
    if ros2:  # CDR: 4-byte encapsulation header (byte 1: 0 big-, 1 little-endian), then int32 sec, uint32 nanosec
        order = ">" if view[1] == 0 else "<"
        sec, nanosec = np.frombuffer(view[4:12], np.dtype(order + "i4")).astype(np.int64)
    else:  # ROS 1: uint32 seq, then uint32 secs, uint32 nsecs, little-endian
        sec, nanosec = np.frombuffer(view[4:12], np.dtype("<u4")).astype(np.int64)
    return int(sec) * 1_000_000_000 + int(nanosec)
