"""A real two-node Ray cluster on the loopback, for the tests (tests/test_ray_cluster.py) and the two-node rows of
tools/bench_batch.py: the head in this machine's view of the files, and a second node in a private mount namespace
(``unshare --mount``) with an empty tmpfs over the folders the driver reads inputs from and writes the store to, as
a node of a cluster that shares no files with the driver. Mount namespaces need root (or a user namespace allowed
to mount): mount_namespaces_refused says why not, where not.

Each node is a ``ray start --block`` process in its own process group: stopping a node kills its group (raylet,
agents and workers at once), as a machine that goes away. ``ray stop`` is never used: it stops every Ray
process of the machine, other runs' too."""

from __future__ import annotations

import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

START_TIMEOUT_S = 90.0  # a node's ``ray start`` on a loaded 2-core machine takes 3-20 s
OBJECT_STORE_BYTES = 200 * 2**20  # per node, by default: the tests' objects are small; Ray's default takes 30 % of the memory


def mount_namespaces_refused(folder: Path) -> str | None:
    """Why this machine cannot give a process a private mount namespace with a tmpfs in it (the reason the
    cluster tests and the bench's two-node rows are skipped), or None when it can."""
    if shutil.which("unshare") is None:
        return "the unshare command is not installed (util-linux)"
    probe = subprocess.run(["unshare", "--mount", "--propagation", "private", "mount", "-t", "tmpfs", "none", str(folder)],
                           capture_output=True, text=True, timeout=30)
    if probe.returncode != 0:
        return f"a private mount namespace with a tmpfs is not allowed here ({probe.stderr.strip() or probe.returncode})"
    return None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class TwoNodeCluster:
    """The head and a second node (``node``), one CPU and ``object_store_bytes`` of object store each; the second node
    sees none of ``hidden`` (each an empty tmpfs there). ``address`` joins it; ``env``: what a driver needs in its
    environment to join (the token)."""

    def __init__(self, hidden: list[Path], object_store_bytes: int = OBJECT_STORE_BYTES):
        self.hidden = [Path(h) for h in hidden]
        self.object_store_bytes = object_store_bytes
        # Ray's session folder holds its sockets, whose paths must stay short (108 bytes): not under pytest's tmp_path
        self.temp_dir = Path(tempfile.mkdtemp(prefix="evr"))
        self.port = _free_port()
        self.address = f"127.0.0.1:{self.port}"
        self.env = {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": secrets.token_hex(32)}
        self.started = 0
        self.head = self.node = None
        self.head = self._start(["--head", "--port", str(self.port), "--include-dashboard", "false", "--temp-dir", str(self.temp_dir)])
        self.node = self.start_node()

    def _start(self, flags: list[str], shell: str = "") -> subprocess.Popen:
        """A ``ray start --block`` with ``flags``; ``shell``: commands run before it in a private mount namespace."""
        command = [str(Path(sys.executable).with_name("ray")), "start", "--block", "--node-ip-address", "127.0.0.1", "--num-cpus", "1",
                   "--disable-usage-stats", "--object-store-memory", str(self.object_store_bytes), "--dashboard-agent-listen-port",
                   str(_free_port()), "--node-manager-port", str(_free_port()), "--object-manager-port", str(_free_port()), *flags]
        if shell:
            command = ["unshare", "--mount", "--propagation", "private", "sh", "-c", f"{shell} && exec \"$@\"", "sh", *command]
        self.started += 1
        log = self.temp_dir / f"node{self.started}.log"
        with log.open("w") as log_file:  # the node writes on its own copy of the descriptor
            process = subprocess.Popen(command, stdout=log_file, stderr=subprocess.STDOUT, env=os.environ | self.env,
                                       start_new_session=True)
        deadline = time.monotonic() + START_TIMEOUT_S
        while "Ray runtime started" not in log.read_text():
            if process.poll() is not None or time.monotonic() > deadline:
                said = log.read_text()[-2000:]
                self.stop(process)
                self.close()
                raise RuntimeError(f"ray start did not start the node: {said}")
            time.sleep(0.2)
        return process

    def start_node(self, *, replicated: Path | None = None, installed: dict | None = None) -> subprocess.Popen:
        """A node that sees none of the hidden folders, joined to the head; ``replicated``: one of them, which it
        sees instead as a copy of its own (replicated data at the same path); ``installed``: path -> what the node
        sees there instead (a file bound over a file, or None: an empty folder over a folder)."""
        mounts = [f"mount -t tmpfs evsemmap-hidden '{h}'" for h in self.hidden]
        mounts += [f"mount --bind '{other}' '{path}'" if other else f"mount -t tmpfs evsemmap-hidden '{path}'"
                   for path, other in (installed or {}).items()]
        if replicated is not None:
            stage = self.temp_dir / f"stage{self.started}"
            stage.mkdir()
            mounts = [f"mount -t tmpfs evsemmap-stage '{stage}'", f"cp -a '{replicated}/.' '{stage}'", *mounts,
                      f"cp -a '{stage}/.' '{replicated}'"]
        return self._start(["--address", self.address], " && ".join(mounts))

    @staticmethod
    def runs_a_task(node) -> bool:
        """Whether a worker of ``node`` (a child of its raylet, which is in the node's process group; workers have
        groups of their own) runs a batch task now: Ray titles a worker ``ray::FUNCTION`` while it runs one."""
        for entry in Path("/proc").iterdir():
            try:
                if not entry.name.isdigit() or not (entry / "cmdline").read_bytes().startswith(b"ray::_ray_task"):
                    continue
                parent = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
                if os.getpgid(parent) == node.pid:
                    return True
            except (OSError, ValueError, IndexError):  # a process that ended meanwhile
                continue
        return False

    @staticmethod
    def stop(process) -> None:
        """A node gone at once (SIGKILL to its raylet, agents and workers), as a machine that fails. SIGKILL: a node
        told to stop (SIGTERM) drains for up to 30 s first, and these nodes hold nothing to keep."""
        if process is None or process.poll() is not None:
            return
        try:
            os.killpg(process.pid, signal.SIGKILL)
        except ProcessLookupError:
            return
        process.wait(timeout=30)

    def close(self) -> None:
        """Both nodes stopped (their process groups), the session folder removed."""
        self.stop(self.node)
        self.stop(self.head)
        self.node = self.head = None
        shutil.rmtree(self.temp_dir, ignore_errors=True)
