"""Writing files atomically: every file the package writes for later use (maps, store tiles and index,
partial maps, checkpoints, the experiment cache, alpha, ground truth) goes through ``write_atomically``.

The content is written under a temporary name in the final file's folder and renamed into place, so a
writer killed or failing halfway never leaves a file that looks whole under the final name, and an
existing file stays as it was until the new one is complete. On failure the temporary is removed and
the error names the final path (never the temporary one). By default no fsync: this guards against
killed processes and failed writes, not against power loss; ``durable=True`` also flushes the file and
its folder to disk before returning, for a write that another file's deletion will rely on (a store
tile that has absorbed partial maps about to be deleted).
"""

from __future__ import annotations

import json
import os
import secrets
from pathlib import Path
from typing import BinaryIO, Callable

import numpy as np


def _temporary_name(path: Path) -> Path:
    # unique per process and call: writers in several processes or threads never share one
    return path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")


def write_atomically(path, write: Callable[[BinaryIO], object], *, durable: bool = False) -> Path:
    """``write(file)`` into a temporary file (binary) beside ``path``, then rename it to ``path``
    (``durable``: on disk, file and rename, when this returns).

    Any failure removes the temporary and leaves ``path`` as it was (absent, or the old content); an
    OSError is raised again as an OSError (same errno, so the same subclass) naming ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = _temporary_name(path)
    try:
        with open(temporary, "xb") as f:
            write(f)
            if durable:
                f.flush()
                os.fsync(f.fileno())
        os.replace(temporary, path)
        if durable:
            folder = os.open(path.parent, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
            try:
                os.fsync(folder)
            finally:
                os.close(folder)
    except OSError as exc:
        if exc.errno is not None:
            raise OSError(exc.errno, exc.strerror or "write failed", str(path)) from exc
        raise OSError(f"{path}: write failed ({str(exc).replace(str(temporary), str(path))})") from exc
    finally:
        temporary.unlink(missing_ok=True)
    return path


def write_bytes_atomically(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (``write_atomically``); returns the path."""
    return write_atomically(path, lambda f: f.write(data))


def write_text_atomically(path, text: str, encoding: str = "utf-8") -> Path:
    """``text`` encoded as is (no newline translation)."""
    return write_bytes_atomically(path, text.encode(encoding))


def write_json_atomically(path, data, **json_kwargs) -> Path:
    """``json.dumps(data, **json_kwargs)`` and a final newline."""
    return write_text_atomically(path, json.dumps(data, **json_kwargs) + "\n")


def save_npy_atomically(path, array, *, allow_pickle: bool = False) -> Path:
    """``np.save``'s format under exactly ``path`` (no ``.npy`` is appended)."""
    return write_atomically(path, lambda f: np.save(f, np.asanyarray(array), allow_pickle=allow_pickle))


def savez_atomically(path, *, compressed: bool = False, **arrays) -> Path:
    """``np.savez`` (or ``np.savez_compressed``) of ``arrays`` under exactly ``path``."""
    save = np.savez_compressed if compressed else np.savez
    return write_atomically(path, lambda f: save(f, **arrays))


# Identity by content --------------------------------------------------------------------------------
# What a resumable run (evsemmap batch) must find unchanged: the SHA-256 of every file it may read. A
# file's size and mtime would be cheaper, but an edit that keeps both (cp -p, rsync -t, tar x, a clock
# step back) would resume a run over the old data, silently; a run that reads every byte anyway hashes
# them for a small share of its time (docs/performance.md, "Measurements behind the code's choices").
_HASH_BLOCK = 1 << 20


def _files_under(path: Path) -> list[Path]:
    """A file itself, or a folder's files (recursively, in name order), hidden ones (.name) left out:
    no loader reads them, and writers keep their temporaries there."""
    if not path.is_dir():
        return [path]
    found = []
    for root, folders, names in os.walk(path):
        folders[:] = sorted(f for f in folders if not f.startswith("."))
        found += [Path(root) / n for n in sorted(names) if not n.startswith(".")]
    return found


def file_sha256(path) -> str:
    """The SHA-256 of a file's content, hex, read in blocks."""
    import hashlib

    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(_HASH_BLOCK):
            digest.update(block)
    return digest.hexdigest()


def content_identity(path) -> dict:
    """A file's or a folder's identity by content: its resolved path, file count, bytes and one
    SHA-256 over every file's relative path and content (see the trade-off above). A path that does
    not exist (a preset name) is identified by its text."""
    import hashlib

    path = Path(path)
    if not path.exists():
        return {"name": str(path)}
    digest = hashlib.sha256()
    files, size = 0, 0
    for item in _files_under(path):
        relative = item.relative_to(path).as_posix() if path.is_dir() else ""
        digest.update(f"{relative}\0{file_sha256(item)}\n".encode())
        files, size = files + 1, size + item.stat().st_size
    return {"path": str(path.resolve()), "files": files, "bytes": size, "sha256": digest.hexdigest()}


def check_not_inside(out, inputs, what: str) -> None:
    """Refuse a write to ``out`` when it is one of ``inputs`` or lies inside one (a folder): ``what``
    names the command and flag, e.g. "export --out"."""
    target = Path(out).resolve()
    for given in inputs:
        source = Path(given)
        if not source.exists():
            continue
        source = source.resolve()
        if target == source or source in target.parents:
            raise ValueError(f"{what} {out}: {'is' if target == source else 'lies inside'} the input {given}; "
                             f"write to a path outside the inputs")


def error_naming(exc: OSError, path, what: str) -> OSError:
    """``exc`` (a failed write, e.g. a full disk) as an OSError naming ``path`` (what the user gave, not a
    temporary or staging name) and ``what`` was being written; the same errno (numpy's short writes have none)."""
    detail = exc.strerror or str(exc)
    if exc.errno is None:
        return OSError(f"{path}: {what} failed ({detail})")
    return OSError(exc.errno, f"{detail} ({what})", str(path))
