"""Writing files atomically: every file the package writes for later use (maps, store tiles and index,
partial maps, checkpoints, the experiment cache, alpha, ground truth) goes through ``write_atomically``.

The content is written under a temporary name in the final file's folder and renamed into place, so a
writer killed or failing halfway never leaves a file that looks whole under the final name, and an
existing file stays as it was until the new one is complete. On failure the temporary is removed and
the error names the final path (never the temporary one). No fsync: this guards against killed
processes and failed writes, not against power loss.
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


def write_atomically(path, write: Callable[[BinaryIO], object]) -> Path:
    """``write(file)`` into a temporary file (binary) beside ``path``, then rename it to ``path``.

    Any failure removes the temporary and leaves ``path`` as it was (absent, or the old content); an
    OSError is raised again as an OSError (same errno, so the same subclass) naming ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = _temporary_name(path)
    try:
        with open(temporary, "xb") as f:
            write(f)
        os.replace(temporary, path)
    except OSError as exc:
        if exc.errno is not None:
            raise OSError(exc.errno, exc.strerror or "write failed", str(path)) from exc
        raise OSError(f"{path}: write failed ({str(exc).replace(str(temporary), str(path))})") from exc
    finally:
        temporary.unlink(missing_ok=True)
    return path


def write_bytes_atomically(path, data: bytes) -> Path:
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
