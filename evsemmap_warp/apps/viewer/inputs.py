"""What a viewer is given beside its maps: a trajectory and a scan to draw, and the address to serve on."""

from __future__ import annotations

import socket
from pathlib import Path

import numpy as np

from ...data.point_files import read_npy, read_point_file


def load_trajectory(path) -> np.ndarray:
    """Positions [N, 3] from a KITTI/RELLIS poses.txt (12 numbers per line), or N x 3 .txt/.npy."""
    path = Path(path)
    if path.suffix == ".npy":
        data = read_npy(path)
    else:
        try:
            data = np.loadtxt(path, ndmin=2)
        except ValueError as exc:  # UnicodeDecodeError included: binary junk
            raise ValueError(f"{path}: not a table of numbers ({exc})") from None
    if data.ndim == 2 and data.shape[1] == 12:
        return data[:, [3, 7, 11]]
    if data.ndim == 2 and data.shape[1] == 3:
        return data
    raise ValueError(f"{path}: a trajectory needs 3 (x y z) or 12 (3x4 pose) numbers per row, got shape {list(data.shape)}")


def load_points(path) -> np.ndarray:
    """Points [N, 3] from any plain point file (.pcd, .ply, .npy, KITTI .bin)."""
    return read_point_file(path).points


def check_address(host: str, port: int) -> None:
    """Refuse a host this machine cannot serve on (viser would wait forever on it) or a port out of range."""
    if not 0 < int(port) < 65536:
        raise ValueError(f"port {port} is outside 1..65535")
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)[0]
        with socket.socket(family, kind, proto) as probe:
            probe.bind((address[0], 0))  # any free port: only whether the address is ours is in question
    except (OSError, UnicodeError) as exc:
        raise ValueError(f"cannot serve on host {host!r}: {exc}") from None


def free_port() -> int:
    """A TCP port on 127.0.0.1 that is free now (for tests and examples that serve on their own port)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
