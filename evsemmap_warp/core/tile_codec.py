"""The compact voxel file of map stores (tiles and partial maps), format 3: what a map needs, exactly,
in about 19 bytes a voxel where the map-file schema takes 230 (docs/formats.md).

A file is ``MAGIC``, a little-endian uint32 header length, a JSON header, then one zstd frame (with
zstd's content checksum). The
header says what the payload holds (voxels, classes, tile, tile size, payload size and CRC-32) and
carries the caller's identity fields (store identity, frame, chunk), so a file that does not belong
is refused before it is used. The payload holds only what cannot be derived:

* each voxel's index inside its tile (uint8 per axis for tiles of up to 256 voxels), axis by axis;
* the [V, K + 4] float64 sums of ``VoxelArrays.rows()`` (evidence, weight sum, weighted-uncertainty
  sum, contribution count, weighted height sum), column by column, so that a class's many zeros run
  together; float64 is kept because a store must export the map ``evsemmap map`` writes, to float64
  rounding;
* the touched flags, one bit each.

Centers, concentrations, labels, states and variance are derived on reading, as a Mapper does.

Why this and not a library format (the measurements: docs/formats.md, "Why this encoding"): the same
arrays in an npz are several times larger; deflated (``np.savez_compressed``) they are still larger
and far slower to write; zstd of the voxel rows is larger than zstd of the columns; Parquet (pyarrow,
zstd, byte-stream-split floats) is larger, slower to read, and a 40 MB dependency; byte-shuffling the
columns first (as blosc does) does not pay for a format of its own. So: columns and zstd, with
``zstandard`` (a dependency of its own, 0.9 MB) and numpy.
"""

from __future__ import annotations

import json
import struct
import zlib
from collections.abc import Iterable

import numpy as np

from ..files import write_atomically
from ..limits import check_tile_voxels

# Zstd of the columns: near the smallest of the encodings tools/bench_store_codec.py compares, with
# zstandard and numpy only (docs/formats.md, "Why this encoding", with its record).
MAGIC = b"EVSMVOX2"
CODEC_FORMAT = "evsemmap_warp.voxels"
CODEC_VERSION = 1
ZSTD_LEVEL = 3
_HEADER_LIMIT = 1 << 24  # a header beyond 16 MB is not one this writes
# zstd's format: a block holds at most 128 KiB of content and takes at least a 3-byte header and one byte
_ZSTD_BLOCK_MAX = 128 * 1024
_ZSTD_BLOCK_OVERHEAD = 4
# The rows' layout (``VoxelArrays.rows()``): the weighted height sum, the one signed sum, is the column
# before the touched flag; every column before it is non-negative. Two classes and five more columns at least.
SIGNED_COLUMN = -2
MIN_COLUMNS = 7


class VoxelFileError(ValueError):
    """A store voxel file that is truncated, corrupt, of another format or of another store."""


def index_dtype(extent: int):
    """The narrowest unsigned integer holding indices 0 .. extent - 1 (a tile's or a map's extent in voxels)."""
    return np.uint8 if extent <= 256 else np.uint16 if extent <= 65536 else np.uint32


def compress_columns(local: np.ndarray, rows: np.ndarray, dtype) -> bytes:
    """The payload of ``local`` [V, 3] (non-negative voxel indices that fit the unsigned ``dtype``) and their
    ``rows`` [V, K + 5] (``VoxelArrays.rows()``): one zstd frame (content size and checksum in its header)
    of the indices axis by axis, the sums column by column and the touched flags as bits. The map file
    (core/map_file.py) holds the same payload."""
    import zstandard

    parts = [np.ascontiguousarray(np.asarray(local).T, dtype=dtype).tobytes()]
    parts.append(np.ascontiguousarray(rows[:, :-1].T, dtype="<f8").tobytes())  # column by column: a class's zeros run together
    parts.append(np.packbits(rows[:, -1] > 0).tobytes())
    return zstandard.ZstdCompressor(level=ZSTD_LEVEL, write_checksum=True).compress(b"".join(parts))


def compress_parts(parts: Iterable, total: int) -> bytes:
    """One zstd frame (content size and checksum in its header) of the concatenation of ``parts`` (byte
    buffers, ``total`` bytes in all), compressed as they come, so that the concatenation is never held:
    ``compress_columns``'s payload, given its parts column by column, decompresses to the same bytes
    (zstd may split the frame's blocks otherwise, so the compressed bytes may differ)."""
    import zstandard

    compressor = zstandard.ZstdCompressor(level=ZSTD_LEVEL, write_checksum=True).compressobj(size=total)
    out = [compressor.compress(part) for part in parts]
    out.append(compressor.flush())
    return b"".join(out)


def decompress_columns(payload: bytes, count: int, columns: int, dtype, where) -> tuple[np.ndarray, np.ndarray]:
    """(local indices [V, 3] int64, rows [V, columns] float64) of a ``compress_columns`` payload that
    the caller's header says holds ``count`` voxels. The size those need is checked against the zstd
    frame's declared content size and against the most a frame of the payload's size can expand to,
    before anything of that size is allocated: a lying count or frame header is refused, not allocated."""
    import zstandard

    dtype = np.dtype(dtype)
    expected = 3 * count * dtype.itemsize + (columns - 1) * count * 8 + (count + 7) // 8
    try:
        declared = zstandard.frame_content_size(payload)
    except zstandard.ZstdError as exc:
        raise VoxelFileError(f"{where}: payload is not a zstd frame ({exc})") from None
    if declared != expected:
        raise VoxelFileError(f"{where}: the payload declares {declared:,} bytes, {count} voxels of {columns} columns need {expected:,} "
                             f"(corrupt or truncated)")
    if expected > _most_content(len(payload)):
        raise VoxelFileError(f"{where}: {len(payload):,} payload bytes cannot hold the {expected:,} bytes of {count} voxels "
                             f"(corrupt: a lying size)")
    try:
        raw = zstandard.ZstdDecompressor().decompress(payload, max_output_size=expected)
    except zstandard.ZstdError as exc:
        raise VoxelFileError(f"{where}: payload does not decompress ({exc})") from None
    if len(raw) != expected:
        raise VoxelFileError(f"{where}: payload holds {len(raw)} bytes, {count} voxels of {columns} columns need {expected}")
    at = 3 * count * dtype.itemsize
    local = np.frombuffer(raw[:at], dtype).reshape(3, count).T.astype(np.int64)
    rows = np.empty((count, columns), np.float64)
    rows[:, :-1] = np.frombuffer(raw, "<f8", count=(columns - 1) * count, offset=at).reshape(columns - 1, count).T
    at += (columns - 1) * 8 * count
    rows[:, -1] = np.unpackbits(np.frombuffer(raw, np.uint8, offset=at), count=count)
    return local, rows


def _most_content(payload_bytes: int) -> int:
    """The most bytes a zstd frame of ``payload_bytes`` can decompress to: every block (at least
    _ZSTD_BLOCK_OVERHEAD bytes, one byte of it content for an RLE block) holds at most _ZSTD_BLOCK_MAX."""
    return (payload_bytes // _ZSTD_BLOCK_OVERHEAD + 1) * _ZSTD_BLOCK_MAX


def encode_voxels(index: np.ndarray, rows: np.ndarray, tile: tuple[int, int, int], tile_voxels: int, header: dict) -> bytes:
    """One file's bytes: voxels of ``tile`` (global ``index`` [V, 3] in key order, ``rows`` [V, K + 5]
    as ``VoxelArrays.rows()``), with ``header``'s identity fields."""
    tile_voxels = check_tile_voxels(tile_voxels)  # the readers' limit: a writer never writes what they refuse
    index = np.asarray(index, np.int64).reshape(-1, 3)
    rows = np.asarray(rows, np.float64)
    tile_key = np.asarray(tile, np.int64).reshape(3)
    local = index - tile_key * tile_voxels
    if len(local) and (local.min() < 0 or local.max() >= tile_voxels):
        raise ValueError(f"voxels outside tile {tuple(int(t) for t in tile_key)} of {tile_voxels} voxels")
    count, columns = len(index), rows.shape[1]
    payload = compress_columns(local, rows, index_dtype(tile_voxels))
    head = header | {"format": CODEC_FORMAT, "version": CODEC_VERSION, "voxels": count, "columns": columns,
                     "tile": [int(t) for t in tile_key], "tile_voxels": int(tile_voxels), "payload_bytes": len(payload),
                     "payload_crc32": zlib.crc32(payload)}
    return framed(MAGIC, head, payload)


def framed(magic: bytes, header: dict, payload: bytes) -> bytes:
    """Bytes framed as the store's voxel files and the map files are: ``magic``, a little-endian uint32 header
    length, the header as JSON (keys sorted, so that the same header gives the same bytes), the payload."""
    text = json.dumps(header, sort_keys=True).encode()
    return magic + struct.pack("<I", len(text)) + text + payload


def split_framed(data: bytes, magic: bytes, header_limit: int, fail) -> tuple[dict, int]:
    """The header (a JSON object) of ``framed`` bytes and where their payload starts; ``fail(text)`` raises the
    caller's error for bytes without the signature, a header cut short or beyond ``header_limit``, or not JSON."""
    start = len(magic) + 4
    if len(data) < start or data[:len(magic)] != magic:
        fail(f"no {magic.decode()} signature ({len(data)} bytes: truncated, or another format)")
    (length,) = struct.unpack_from("<I", data, len(magic))
    if length > header_limit or start + length > len(data):
        fail(f"truncated header ({len(data) - start} bytes left for a {length}-byte header)")
    try:
        header, problem = json.loads(data[start:start + length]), None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        header, problem = None, f"the header is not valid JSON ({exc})"
    if problem is not None or not isinstance(header, dict):
        fail(problem or "the header is not a JSON object")
    return header, start + length


def decode_header(data: bytes, where) -> tuple[dict, int]:
    """The header of a voxel file's bytes (checked), and where its payload starts."""
    def fail(text):
        raise VoxelFileError(f"{where}: not a store voxel file: {text}")

    header, start = split_framed(data, MAGIC, _HEADER_LIMIT, fail)
    if header.get("format") != CODEC_FORMAT or header.get("version") != CODEC_VERSION:
        raise VoxelFileError(f"{where}: header of another format or version ({str(header)[:120]})")
    for key in ("voxels", "columns", "tile_voxels", "payload_bytes", "payload_crc32"):
        value = header.get(key)
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise VoxelFileError(f"{where}: header key {key!r} = {value!r} must be a whole number >= 0")
    tile = header.get("tile")
    if not (isinstance(tile, list) and len(tile) == 3 and all(isinstance(t, int) and not isinstance(t, bool) for t in tile)):
        raise VoxelFileError(f"{where}: header key 'tile' = {tile!r} must be three whole numbers")
    if header["columns"] < MIN_COLUMNS:
        raise VoxelFileError(f"{where}: header says {header['columns']} columns (at least {MIN_COLUMNS})")
    try:
        check_tile_voxels(header["tile_voxels"], "header key 'tile_voxels'")
    except ValueError as exc:
        raise VoxelFileError(f"{where}: {exc}") from None
    return header, start


def check_payload(payload: bytes, header: dict, where) -> None:
    """Refuse a payload of another size or CRC-32 than its header's ``payload_bytes`` and ``payload_crc32``."""
    if len(payload) != header["payload_bytes"]:
        raise VoxelFileError(f"{where}: {len(payload)} payload bytes, the header says {header['payload_bytes']} (truncated?)")
    if zlib.crc32(payload) != header["payload_crc32"]:
        raise VoxelFileError(f"{where}: payload checksum mismatch (the file is corrupt)")


def decode_voxels(data: bytes, where) -> tuple[dict, np.ndarray, np.ndarray]:
    """(header, global index [V, 3] int64, rows [V, K + 5] float64) of a voxel file's bytes, checked:
    signature, header, payload size and CRC, zstd's content checksum, indices inside the tile and in
    strict key order, finite sums, non-negative but for the weighted height sum."""
    header, start = decode_header(data, where)
    payload = data[start:]
    check_payload(payload, header, where)
    count, columns, tile_voxels = header["voxels"], header["columns"], header["tile_voxels"]
    local, rows = decompress_columns(payload, count, columns, index_dtype(tile_voxels), where)
    if count:
        if local.max() >= tile_voxels:
            raise VoxelFileError(f"{where}: voxel indices outside the tile")
        keys = (local[:, 0] * tile_voxels + local[:, 1]) * tile_voxels + local[:, 2]
        if np.any(np.diff(keys) <= 0):
            raise VoxelFileError(f"{where}: voxels out of key order or repeated")
        if not np.isfinite(rows).all() or rows[:, :SIGNED_COLUMN].min() < 0:
            raise VoxelFileError(f"{where}: sums that are negative, NaN or inf")
    index = local + np.asarray(header["tile"], np.int64) * tile_voxels
    return header, index, rows


def write_voxel_file(path, index, rows, tile, tile_voxels: int, header: dict, *, durable: bool = False):
    """``encode_voxels`` written atomically (a temporary name, then a rename; ``durable``: on disk
    when this returns, see files.write_atomically)."""
    data = encode_voxels(index, rows, tile, tile_voxels, header)
    return write_atomically(path, lambda f: f.write(data), durable=durable)


def read_voxel_header(path) -> dict:
    """A voxel file's header alone (checked as ``decode_header`` checks it), without its payload: what
    a store's index pass and a resumed run need to know of a tile."""
    try:
        with open(path, "rb") as f:
            start = f.read(len(MAGIC) + 4)
            length = struct.unpack_from("<I", start, len(MAGIC))[0] if len(start) == len(MAGIC) + 4 else 0
            data = start + f.read(min(length, _HEADER_LIMIT + 1))
    except OSError as exc:
        raise VoxelFileError(f"{path}: cannot read ({exc.strerror})") from None
    return decode_header(data, path)[0]


def read_voxel_file(path, expect: dict | None = None) -> tuple[dict, np.ndarray, np.ndarray]:
    """``decode_voxels`` of a file; ``expect``: header fields that must match (the store's identity,
    the tile, the chunk), named when one does not."""
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError as exc:
        raise VoxelFileError(f"{path}: cannot read ({exc.strerror})") from None
    return check_expected(decode_voxels(data, path), path, expect)


def check_expected(decoded: tuple[dict, np.ndarray, np.ndarray], where, expect: dict | None) -> tuple[dict, np.ndarray, np.ndarray]:
    """``decoded`` (decode_voxels' answer for ``where``) unless a header field differs from ``expect``'s (the store's
    identity, the tile, the chunk), named then."""
    header = decoded[0]
    for key, value in (expect or {}).items():
        if header.get(key) != value:
            raise VoxelFileError(f"{where}: {key} is {header.get(key)!r}, this store's is {value!r}: the file belongs to another "
                                 f"store or run")
    return decoded
