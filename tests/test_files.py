"""One atomic writer (evsemmap_warp/files.py): a writer that fails halfway leaves neither a file under
the final name nor a temporary, an existing file stays as it was, errors name the final path, and the
package's files (maps, stores, checkpoints, the experiment cache, alpha, ground truth) go through it."""

import ast
import errno
import json
import os
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO
from evsemmap_warp import files

PACKAGE = REPO / "evsemmap_warp"


class _Halfway(RuntimeError):
    pass


def _write_half_then_fail(f):
    f.write(b"the first half of a file")
    raise _Halfway("killed halfway")


def _leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


class _OsWithFailingReplace:
    """``os`` for files.py whose rename into place fails (as a full disk or a lost mount would)."""

    def __init__(self):
        self.renamed = []

    def __getattr__(self, name):
        return getattr(os, name)

    def replace(self, src, dst):
        self.renamed.append(Path(dst))
        raise OSError(errno.EIO, "Input/output error", str(src), None, str(dst))


@pytest.fixture
def failing_rename(monkeypatch):
    fake = _OsWithFailingReplace()
    monkeypatch.setattr(files, "os", fake)
    return fake


def test_a_writer_failing_halfway_leaves_nothing_and_the_old_file_as_it_was(tmp_path):
    new = tmp_path / "sub" / "new.bin"
    with pytest.raises(_Halfway):
        files.write_atomically(new, _write_half_then_fail)
    assert not new.exists() and _leftovers(new.parent) == []
    old = tmp_path / "old.json"
    files.write_json_atomically(old, {"a": 1})
    before = old.read_bytes()
    with pytest.raises(_Halfway):
        files.write_atomically(old, _write_half_then_fail)
    assert old.read_bytes() == before and _leftovers(tmp_path) == []
    def interrupted(f):
        f.write(b"x")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):  # a Ctrl-C mid-write too
        files.write_atomically(old, interrupted)
    assert old.read_bytes() == before and _leftovers(tmp_path) == []


def test_a_failing_write_names_the_final_path_not_the_temporary(tmp_path, failing_rename):
    path = tmp_path / "map.npz"
    with pytest.raises(OSError) as caught:
        files.write_bytes_atomically(path, b"content")
    assert str(path) in str(caught.value) and ".tmp" not in str(caught.value)
    assert caught.value.errno == errno.EIO and caught.value.filename == str(path)
    assert failing_rename.renamed == [path] and not path.exists() and _leftovers(tmp_path) == []


def test_an_os_error_inside_the_writer_names_the_final_path(tmp_path):
    path = tmp_path / "full.npy"

    def disk_full(f):
        f.write(b"some")
        raise OSError(errno.ENOSPC, "No space left on device", f.name)

    with pytest.raises(OSError, match=re.escape(str(path))) as caught:
        files.write_atomically(path, disk_full)
    assert caught.value.errno == errno.ENOSPC and ".tmp" not in str(caught.value)
    assert not path.exists() and _leftovers(tmp_path) == []
    def failing_without_errno(f):
        raise OSError(f"cannot write {f.name}")

    with pytest.raises(OSError, match=re.escape(str(path))) as caught:
        files.write_atomically(path, failing_without_errno)
    assert ".tmp" not in str(caught.value) and _leftovers(tmp_path) == []


def test_the_helpers_write_what_numpy_and_json_would(tmp_path):
    array = np.arange(12, dtype=np.float16).reshape(3, 4)
    assert files.save_npy_atomically(tmp_path / "a.npy", array) == tmp_path / "a.npy"
    np.testing.assert_array_equal(np.load(tmp_path / "a.npy"), array)
    files.save_npy_atomically(tmp_path / "no_suffix", array)  # exactly the path given, as a file object would
    assert (tmp_path / "no_suffix").exists() and not (tmp_path / "no_suffix.npy").exists()
    for compressed in (False, True):
        path = files.savez_atomically(tmp_path / f"z{compressed}.npz", compressed=compressed, points=array, labels=np.arange(3))
        with np.load(path) as data:
            np.testing.assert_array_equal(data["points"], array)
            np.testing.assert_array_equal(data["labels"], np.arange(3))
    files.write_json_atomically(tmp_path / "a.json", {"b": 1, "a": [1, 2]}, indent=1, sort_keys=True)
    assert (tmp_path / "a.json").read_text() == json.dumps({"b": 1, "a": [1, 2]}, indent=1, sort_keys=True) + "\n"
    files.write_text_atomically(tmp_path / "a.csv", "x,y\r\n1,2\r\n")
    assert (tmp_path / "a.csv").read_bytes() == b"x,y\r\n1,2\r\n"  # no newline translation
    assert oct((tmp_path / "a.csv").stat().st_mode & 0o777) == oct(0o666 & ~_umask())  # as open() makes it
    assert _leftovers(tmp_path) == []


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_files_is_a_foundation_module():
    """It may import the standard library, numpy and evsemmap_warp.config, nothing else."""
    tree = ast.parse((PACKAGE / "files.py").read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            names = [("." * node.level) + (node.module or "")]
        else:
            continue
        for name in names:
            top = name.lstrip(".").split(".")[0]
            allowed = name in (".config", "evsemmap_warp.config") or top == "numpy" or (not name.startswith(".") and top in sys.stdlib_module_names)
            assert allowed, f"files.py imports {name}"


WRITES = re.compile(r"\.write_text\(|\.write_bytes\(|np\.save\(|np\.savez(?:_compressed)?\(|torch\.save\([^)]*,\s*path\)|(?<![\w.])open\([^)]*[\"']w|os\.replace\(")


@pytest.mark.parametrize("module", ["apps/experiment.py", "segmentation/train.py", "methods/convbki.py", "core/map_file.py",
                                    "core/map_store.py"])
def test_these_modules_write_only_through_the_atomic_writer(module):
    text = (PACKAGE / module).read_text()
    assert not WRITES.findall(text), f"{module} writes around evsemmap_warp.files: {WRITES.findall(text)}"


def test_the_experiment_cache_writes_through_it(tmp_path, failing_rename, monkeypatch):
    """A ground-truth cache file that fails to be written is not there afterwards, half or whole, and
    the error names it (np.savez_compressed straight to the cache path would leave a file that a rerun
    takes for finished)."""
    from evsemmap_warp.apps.experiment import Experiment, load_experiment

    config_path = tmp_path / "study.yaml"
    config_path.write_text("""
name: cache-study
sequences:
  test: {world: tiny, frames: 2}
networks:
  net: {checkpoint: /nonexistent.pt}
conditions:
  in-domain: {network: net, sequence: test}
methods: [s-csm]
""")
    config, _ = load_experiment(config_path)
    study = Experiment(config, tmp_path / "out", progress=False, log=lambda m: None)
    monkeypatch.setattr(files, "os", os)  # rendering the sequence is not under test
    study.sequence_dir("test")
    monkeypatch.setattr(files, "os", failing_rename)
    with pytest.raises(OSError) as caught:
        study.ground_truth("test")
    assert len(failing_rename.renamed) == 1
    path = failing_rename.renamed[0]
    assert path.parent == tmp_path / "out" / "cache" / "ground_truth" and path.suffix == ".npz"
    assert str(path) in str(caught.value) and not path.exists() and _leftovers(path.parent) == []
    monkeypatch.setattr(files, "os", os)
    points, labels = study.ground_truth("test")  # and a working disk writes it
    assert path.exists() and len(points) == len(labels) > 0
