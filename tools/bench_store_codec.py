"""How a map store's tiles could be encoded, measured on a real store: bytes per voxel, write and read speed,
and the time to open one tile, for the store's own voxel file (``core/tile_codec.py``: zstd of the columns)
and the alternatives it was chosen over. Writes its record under docs/bench/ (``bench_record``).

    python tools/bench_store_codec.py STORE [--repeats 3] [--record-dir DIR]

STORE: a format-2 store (``evsemmap batch`` writes one; ``tools/bench_batch.py`` and ``tools/bench_layers.py``
make the bench's). Every encoding holds the same thing: each voxel's index inside its tile, the float64 sums
(evidence per class, weight, weighted uncertainty, contribution count) and the touched flag, and each is
checked to give them back bit for bit. Tiles are taken one at a time (memory stays at one tile's), and each
encoding writes every tile to files and reads them back, ``--repeats`` times after a warm-up; the figures
are medians. Only the store's own encoding checks what it reads (CRC-32, zstd's checksum, indices, finite
sums): its read figure includes that work, the others' do not. Parquet is measured where ``pyarrow`` is
installed (it is not a dependency: ``pip install pyarrow``).
"""

from __future__ import annotations

import argparse
import io
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_record import write_record  # noqa: E402

from evsemmap_warp.core import tile_codec  # noqa: E402
from evsemmap_warp.core.map_store import MapStore  # noqa: E402


def _zstd(data: bytes) -> bytes:
    import zstandard

    return zstandard.ZstdCompressor(level=tile_codec.ZSTD_LEVEL).compress(data)


def _unzstd(data: bytes) -> bytes:
    import zstandard

    return zstandard.ZstdDecompressor().decompress(data)


class Tile:
    """One tile's content: local indices [V, 3] uint8/uint16, sums [V, C] float64, touched [V] bool."""

    def __init__(self, name, index, rows, tile, tile_voxels):
        self.name, self.tile, self.tile_voxels = name, tuple(int(t) for t in tile), int(tile_voxels)
        self.index, self.rows = index, rows
        self.local = (index - np.asarray(tile, np.int64) * tile_voxels).astype(tile_codec.index_dtype(tile_voxels))
        self.sums = np.ascontiguousarray(rows[:, :-1])
        self.touched = rows[:, -1] > 0

    def same(self, local, sums, touched) -> bool:
        return (np.array_equal(np.asarray(local, np.int64), self.local.astype(np.int64)) and np.array_equal(sums.view(np.uint64), self.sums.view(np.uint64))
                and np.array_equal(np.asarray(touched, bool), self.touched))


# ---------------------------------------------------------------------------------------------- encodings
# Each: (encode(tile) -> bytes, decode(bytes, tile) -> (local, sums, touched)); decode may read shapes from the tile.
def _vox_encode(t: Tile) -> bytes:
    return tile_codec.encode_voxels(t.index, t.rows, t.tile, t.tile_voxels, {"kind": "tile"})


def _vox_decode(data: bytes, t: Tile):
    _, index, rows = tile_codec.decode_voxels(data, t.name)
    return index - np.asarray(t.tile, np.int64) * t.tile_voxels, rows[:, :-1], rows[:, -1] > 0


def _npz_encode(compressed: bool):
    def encode(t: Tile) -> bytes:
        buffer = io.BytesIO()
        (np.savez_compressed if compressed else np.savez)(buffer, local=t.local, sums=t.sums, touched=np.packbits(t.touched))
        return buffer.getvalue()

    return encode


def _npz_decode(data: bytes, t: Tile):
    with np.load(io.BytesIO(data)) as z:
        return z["local"], z["sums"], np.unpackbits(z["touched"], count=len(z["local"])).astype(bool)


def _rows_encode(t: Tile) -> bytes:
    return _zstd(t.local.tobytes() + t.sums.tobytes() + np.packbits(t.touched).tobytes())


def _rows_decode(data: bytes, t: Tile):
    raw = _unzstd(data)
    v, c = t.sums.shape
    at = t.local.nbytes
    local = np.frombuffer(raw[:at], t.local.dtype).reshape(v, 3)
    sums = np.frombuffer(raw, np.float64, count=v * c, offset=at).reshape(v, c)
    return local, sums, np.unpackbits(np.frombuffer(raw, np.uint8, offset=at + v * c * 8), count=v).astype(bool)


def _shuffled_encode(t: Tile) -> bytes:
    columns = np.ascontiguousarray(t.sums.T)
    shuffled = np.ascontiguousarray(columns.view(np.uint8).reshape(-1, 8).T)  # byte k of every value together, as blosc does
    return _zstd(np.ascontiguousarray(t.local.T).tobytes() + shuffled.tobytes() + np.packbits(t.touched).tobytes())


def _shuffled_decode(data: bytes, t: Tile):
    raw = _unzstd(data)
    v, c = t.sums.shape
    at = t.local.nbytes
    local = np.frombuffer(raw[:at], t.local.dtype).reshape(3, v).T
    shuffled = np.frombuffer(raw, np.uint8, count=v * c * 8, offset=at).reshape(8, v * c)
    sums = np.ascontiguousarray(shuffled.T).view(np.float64).reshape(c, v).T
    return local, sums, np.unpackbits(np.frombuffer(raw, np.uint8, offset=at + v * c * 8), count=v).astype(bool)


def _parquet_encode(t: Tile) -> bytes:
    import pyarrow as pa
    import pyarrow.parquet as pq

    columns = {f"i{a}": t.local[:, a] for a in range(3)} | {f"s{k}": t.sums[:, k] for k in range(t.sums.shape[1])}
    columns["touched"] = t.touched
    buffer = io.BytesIO()
    pq.write_table(pa.table(columns), buffer, compression="zstd", use_byte_stream_split=[f"s{k}" for k in range(t.sums.shape[1])],
                   use_dictionary=False)
    return buffer.getvalue()


def _parquet_decode(data: bytes, t: Tile):
    import pyarrow.parquet as pq

    table = pq.read_table(io.BytesIO(data))
    local = np.stack([table.column(f"i{a}").to_numpy() for a in range(3)], axis=1)
    sums = np.stack([table.column(f"s{k}").to_numpy() for k in range(t.sums.shape[1])], axis=1)
    return local, sums, table.column("touched").to_numpy(zero_copy_only=False)


def encodings() -> dict:
    found = {
        "this store's .vox (zstd of the columns, checked on reading)": (_vox_encode, _vox_decode),
        "npz of the same arrays": (_npz_encode(False), _npz_decode),
        "npz, deflated (np.savez_compressed)": (_npz_encode(True), _npz_decode),
        "zstd of the voxel rows": (_rows_encode, _rows_decode),
        "zstd of byte-shuffled columns (as blosc)": (_shuffled_encode, _shuffled_decode),
    }
    try:
        import pyarrow  # noqa: F401

        found["Parquet (pyarrow, zstd, byte-stream-split floats)"] = (_parquet_encode, _parquet_decode)
    except ImportError:
        pass
    return found


# ---------------------------------------------------------------------------------------------- measuring
def tiles_of(store: MapStore) -> list[str]:
    if store.format_version != 2:
        raise SystemExit(f"{store.path}: a format-{store.format_version} store; this measures format-2 tiles (evsemmap batch writes them)")
    return sorted(store.tiles)


def load_tile(store: MapStore, name: str) -> Tile:
    header, index, rows = tile_codec.read_voxel_file(store.tile_path(name))
    return Tile(name, index, rows, header["tile"], header["tile_voxels"])


def measure(store: MapStore, repeats: int, work: Path, log) -> dict:
    names = tiles_of(store)
    found = encodings()
    results = {name: {"bytes": 0, "write_s": [], "read_s": []} for name in found}
    voxels = 0
    sizes = {}
    for k, tile_name in enumerate(names):
        tile = load_tile(store, tile_name)
        voxels += len(tile.index)
        sizes[tile_name] = len(tile.index)
        for name, (encode, decode) in found.items():
            data = encode(tile)
            if not tile.same(*decode(data, tile)):
                raise SystemExit(f"{name}: tile {tile_name} does not read back bit for bit")
            results[name]["bytes"] += len(data)
            # a warm-up above (encode, decode); then write to a file and read it back, repeats times
            path = work / f"{k}.bin"
            writes, reads = [], []
            for _ in range(repeats):
                start = time.perf_counter()
                path.write_bytes(encode(tile))
                writes.append(time.perf_counter() - start)
                start = time.perf_counter()
                decode(path.read_bytes(), tile)
                reads.append(time.perf_counter() - start)
            results[name]["write_s"].append(writes)
            results[name]["read_s"].append(reads)
            path.unlink()
        if (k + 1) % 10 == 0 or k + 1 == len(names):
            log(f"{k + 1}/{len(names)} tiles, {voxels:,} voxels")
    # one tile's opening: the tile of median size, read and decoded, repeats x 5 times
    median_tile = sorted(sizes, key=sizes.get)[len(sizes) // 2]
    tile = load_tile(store, median_tile)
    for name, (encode, decode) in found.items():
        path = work / "one.bin"
        path.write_bytes(encode(tile))
        decode(path.read_bytes(), tile)
        times = []
        for _ in range(5 * repeats):
            start = time.perf_counter()
            decode(path.read_bytes(), tile)
            times.append(time.perf_counter() - start)
        results[name]["one_tile_s"] = times
    table = {}
    for name, r in results.items():
        # per repeat, the whole store's time (the tiles' times added up), then the median over repeats
        write = statistics.median(sum(t[i] for t in r["write_s"]) for i in range(repeats))
        read = statistics.median(sum(t[i] for t in r["read_s"]) for i in range(repeats))
        table[name] = {"bytes": r["bytes"], "bytes_per_voxel": round(r["bytes"] / voxels, 2), "write_s": round(write, 3),
                       "read_s": round(read, 3), "write_voxels_per_s": round(voxels / write), "read_voxels_per_s": round(voxels / read),
                       "one_tile_ms": round(1e3 * statistics.median(r["one_tile_s"]), 2),
                       "raw": {"write_s_per_tile": r["write_s"], "read_s_per_tile": r["read_s"], "one_tile_s": r["one_tile_s"]}}
    return {"store": str(store.path), "tiles": len(names), "voxels": voxels, "columns": int(tile.rows.shape[1]), "repeats": repeats,
            "one_tile": {"name": median_tile, "voxels": sizes[median_tile]}, "encodings": table}


def markdown(results: dict) -> str:
    lines = [f"{results['voxels']:,} voxels in {results['tiles']} tiles; one tile: {results['one_tile']['voxels']:,} voxels", "",
             "| encoding | bytes/voxel | write (voxels/s) | read (voxels/s) | one tile |", "|---|---|---|---|---|"]
    for name, r in results["encodings"].items():
        lines.append(f"| {name} | {r['bytes_per_voxel']:.1f} | {r['write_voxels_per_s'] / 1e6:.2f} M | {r['read_voxels_per_s'] / 1e6:.2f} M | "
                     f"{r['one_tile_ms']:.1f} ms |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("store", type=Path)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--record-dir", type=Path, default=None, help="where the run's record goes (default docs/bench)")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        print(f"--repeats {args.repeats}: must be 1 or more", file=sys.stderr)
        return 2
    started = time.time()
    try:
        store = MapStore(args.store)
    except (OSError, ValueError) as exc:
        print(exc, file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="bench_store_codec_", dir=args.store.parent) as work:
        results = measure(store, args.repeats, Path(work), lambda m: print(m, file=sys.stderr, flush=True))
    print(markdown(results))
    kwargs = {} if args.record_dir is None else {"folder": args.record_dir}
    print(f"record: {write_record('bench_store_codec', results, started=started, **kwargs)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
