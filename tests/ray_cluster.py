"""A real two-node Ray cluster on the loopback, for the tests: the head in this machine's view of the files, and
a second node in a private mount namespace (``unshare --mount``) with an empty tmpfs over the folders the driver
reads inputs from and writes the store to, as a node of a cluster that shares no files with the driver.

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
OBJECT_STORE_BYTES = 200 * 2**20  # per node: the tests' objects are small; Ray's default takes 30 % of the memory


def mount_namespaces_refused(folder: Path) -> str | None:
    """Why this machine cannot give a process a private mount namespace with a tmpfs in it (the reason a
    test skips), or None when it can."""
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
    """The head (``num_cpus`` 1) and a second node (``num_cpus`` 1) that sees none of ``hidden`` (each an empty
    tmpfs there); ``address`` joins it. ``env``: what a driver needs in its environment to join (the token)."""

    def __init__(self, hidden: list[Path]):
        self.hidden = [Path(h) for h in hidden]
        # Ray's session folder holds its sockets, whose paths must stay short (108 bytes): not under pytest's tmp_path
        self.temp_dir = Path(tempfile.mkdtemp(prefix="evr"))
        self.port = _free_port()
        self.address = f"127.0.0.1:{self.port}"
        self.env = {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": secrets.token_hex(32)}
        self.head = self.node = None
        self.head = self._start(["--head", "--port", str(self.port),
                                 "--include-dashboard", "false", "--temp-dir", str(self.temp_dir)], "head", [])
        self.node = self.start_node()

    def _start(self, flags: list[str], name: str, hidden: list[Path]) -> subprocess.Popen:
        command = ["ray", "start", "--block", "--node-ip-address", "127.0.0.1", "--num-cpus", "1", "--disable-usage-stats",
                   "--object-store-memory", str(OBJECT_STORE_BYTES), "--dashboard-agent-listen-port", str(_free_port()),
                   "--node-manager-port", str(_free_port()), "--object-manager-port", str(_free_port()), *flags]
        command[0] = str(Path(sys.executable).with_name("ray"))
        if hidden:
            mounts = " && ".join(f"mount -t tmpfs evsemmap-hidden '{h}'" for h in hidden)
            command = ["unshare", "--mount", "--propagation", "private", "sh", "-c", f"{mounts} && exec \"$@\"", "sh", *command]
        log = self.temp_dir / f"{name}.log"
        process = subprocess.Popen(command, stdout=log.open("w"), stderr=subprocess.STDOUT, env=os.environ | self.env,
                                   start_new_session=True)
        deadline = time.monotonic() + START_TIMEOUT_S
        while "Ray runtime started" not in log.read_text():
            if process.poll() is not None or time.monotonic() > deadline:
                said = log.read_text()[-2000:]
                self._stop(process)
                self.close()
                raise RuntimeError(f"ray start ({name}) did not start the node: {said}")
            time.sleep(0.2)
        return process

    def start_node(self) -> subprocess.Popen:
        """A (new) second node, in its own mount namespace."""
        return self._start(["--address", self.address], "node", self.hidden)

    def stop_node(self) -> None:
        """The second node gone at once (SIGKILL to its raylet, agents and workers), as a machine that fails."""
        self._stop(self.node)
        self.node = None

    @staticmethod
    def _stop(process) -> None:
        # SIGKILL: a node told to stop (SIGTERM) drains for up to 30 s first; these nodes hold nothing to keep
        if process is None or process.poll() is not None:
            return
        try:
            os.killpg(process.pid, signal.SIGKILL)
        except ProcessLookupError:
            return
        process.wait(timeout=30)

    def close(self) -> None:
        """Both nodes stopped (their process groups), the session folder removed."""
        self._stop(self.node)
        self._stop(self.head)
        self.node = self.head = None
        shutil.rmtree(self.temp_dir, ignore_errors=True)
