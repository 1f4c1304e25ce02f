"""The Ray executor: a batch's tasks on a local Ray instance it starts and stops, or on a running instance or
cluster it joins by address.

The nodes need not share files with the driver. A task maps its chunk into a scratch folder of its node
(map_chunk, as everywhere) and returns the chunk's files, encoded as the store encodes them, through Ray's
object store; the driver alone writes them into the store's ``work/`` (then folds them as the other executors'
chunks), so resuming and the streaming reduction are the same. The inputs reach the workers at the same path
(a shared or replicated folder) when a probe at the start finds them, by content, on every node; otherwise the
driver reads each chunk's scans and sends them through the object store. The probe also refuses a node that
cannot import this project or has another version of it."""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import socket
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, replace
from pathlib import Path

from ... import __version__, files
from ...config import ConfigError
from ...frames import WorldFrame
from ...limits import CHUNK_TIMEOUT_S, RAY_CONNECT_TIMEOUT_S
from .executors import MATH_THREAD_VARIABLES, stuck_error
from .store import chunk_dir
from .worker import Context, handoff_recorder, init_worker, process_tag, reset_tasks_started

# While waiting for chunks, the driver asks the head every HEAD_CHECK_S whether it still answers, and stops in one line
# when it has not for HEAD_SILENT_S (Ray itself ends the driver after 60 s, without a line of ours).
HEAD_CHECK_S = 2.0
HEAD_SILENT_S = 10.0
SAME_PATH = "same path"  # the inputs' modes (RayExecutor.cluster["inputs"])
FROM_DRIVER = "from the driver"


class ClusterError(OSError):
    """The cluster cannot run the batch (a node without the project or with another version of it, without the
    inputs it was found to have, out of object store memory, gone with the driver's connection): one line naming
    the node and what to do. An OSError, as a missing file: the command line reports it in one line."""


@contextlib.contextmanager
def _environment(values: dict):
    """``values`` in os.environ while the block runs; what was there before, after."""
    before = {name: os.environ.get(name) for name in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for name, value in before.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


@dataclass
class SentScans:
    """A chunk's scans as the driver read them (``items``, insertions ``start..stop-1`` of its input), with what
    Mapper.for_dataset needs of the input: the source of a task on a node that does not see the inputs."""

    items: list
    start: int
    stop: int
    num_classes: int
    class_names: tuple | None
    frame: WorldFrame | None

    def scans(self, start: int, stop: int):
        """The scans read for insertions ``start..stop-1`` (the chunk's; no others were sent)."""
        if (start, stop) != (self.start, self.stop):
            raise ValueError(f"insertions {start}..{stop - 1} asked of the scans sent for {self.start}..{self.stop - 1}")
        return iter(self.items)


def read_scans(source, chunk) -> SentScans:
    """The driver's reading of ``chunk``'s scans from ``source``, to send to a node that does not see the inputs."""
    return SentScans(list(source.scans(chunk.start, chunk.stop)), chunk.start, chunk.stop, source.num_classes,
                     source.class_names, source.frame)


def scratch_name(store) -> str:
    """The name of the folder, in each node's temporary folder, where the tasks of a run into ``store`` map their
    chunks: one per driver machine and store path (two drivers' runs never share one), the same for every worker
    process of a node (the tests' fault plan marks a killed attempt there) and for every run into ``store``, so that
    what a killed task leaves there (remove_dead_tasks_leftovers) is cleared by the node's next task into that store."""
    digest = hashlib.sha256(f"{socket.gethostname()}:{Path(store).resolve()}".encode()).hexdigest()[:16]
    return f"evsemmap-batch-{digest}"


def node_scratch(store) -> Path:
    """That folder (scratch_name) on this machine."""
    return Path(tempfile.gettempdir()) / scratch_name(store)


def _node_name() -> str:
    """This worker's node as the messages and the summary name it: host, address and Ray's node id (nodes on one
    host share the first two)."""
    import ray

    return f"{socket.gethostname()} ({ray.util.get_node_ip_address()}, node {ray.get_runtime_context().get_node_id()[:8]})"


def probe_node(paths: list[str]) -> dict:
    """A probe task, run once on every node at the start: this node's name, its version of the project and the
    content identity (files.content_identity) of each of ``paths`` (the inputs the workers read) as it sees them."""
    return {"node": _node_name(), "version": __version__, "inputs": {path: files.content_identity(path) for path in paths}}


def remove_dead_tasks_leftovers(scratch: Path) -> None:
    """What tasks killed on this node (a stuck task cancelled, a worker out of memory) left in its scratch folder
    ``scratch``: their temporary chunk folders, each named by its process (worker.process_tag), removed once that
    process is gone; a live task's are its own, and those of processes in another PID namespace (another node's, in a
    container sharing the folder) are that node's to judge. With them gone the folder empties, and the task that
    leaves it so removes it."""
    namespace = process_tag().rpartition("-")[0]
    for leftover in (scratch / "work").glob(".chunk_*.tmp"):
        their_namespace, _, pid = leftover.name.split(".")[2].rpartition("-")
        if their_namespace == namespace and pid.isdigit() and not _process_runs(int(pid)):
            shutil.rmtree(leftover, ignore_errors=True)


def _process_runs(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def missing_input(exc: FileNotFoundError, node: str, probed: list[str] | None) -> OSError:
    """What a task that reads the inputs at the same path says of a file it did not find: where the probe at the start
    found the inputs on every node (``probed``: their paths) and the file is one of them, a ClusterError naming the node;
    otherwise (a local instance, which nothing probed: this machine's files; a file that is no input) ``exc`` as it is."""
    inside = probed is not None and any(Path(exc.filename) == Path(path) or Path(path) in Path(exc.filename).parents
                                        for path in probed)
    if not inside:
        return exc
    return ClusterError(f"node {node} does not see the input file {exc.filename}, which the probe at the start found at the same "
                        f"path on every node (removed since, or a node that joined later?): give every node the inputs at the same "
                        f"path, or rerun (a node without them makes the driver send the scans)")


_RAY_CONTEXTS: dict = {}  # object id -> the context with the node's scratch folder as its store, per Ray worker process


def _ray_task(fn, threads: int, context_box: list, submitted: float, sent: SentScans | None, chunk):
    """A Ray task: ``fn`` (map_chunk) maps ``chunk`` into the node's scratch folder; returns its result with the
    chunk's files (``files``: name -> bytes) and the node (``node``). ``sent``: the chunk's scans, when the driver
    sends them. The context (put once by the driver) comes boxed in a list with the scratch folder's name
    (scratch_name) and the inputs the probe found on every node (missing_input; None where it did not run), so Ray
    does not fetch and unpickle it for every task: each worker process fetches it once
    (unboxed, unpickling the sources for every task made short tasks several times slower, docs/performance.md).
    ``submitted``: when the driver submitted it (time.time()), for the hand-off costs (handoff_recorder)."""
    import ray

    key = context_box[0].hex()
    if key not in _RAY_CONTEXTS:
        reset_tasks_started()  # a cluster's worker that served an earlier run: this run's first task in it
    handoff = handoff_recorder(submitted)  # before fetching the context: a worker's start includes it
    if key not in _RAY_CONTEXTS:
        _RAY_CONTEXTS.clear()
        _RAY_CONTEXTS[key] = replace(ray.get(context_box[0]), store=Path(tempfile.gettempdir()) / context_box[1])
        init_worker(_RAY_CONTEXTS[key], threads)
    context = _RAY_CONTEXTS[key]
    if sent is not None:
        context = replace(context, sources=[sent if i == chunk.sequence else s for i, s in enumerate(context.sources)])
    folder = chunk_dir(context.store, chunk.number)
    shutil.rmtree(folder, ignore_errors=True)  # never an earlier run's chunk: this attempt maps it
    remove_dead_tasks_leftovers(context.store)
    (context.store / "work").mkdir(parents=True, exist_ok=True)
    try:
        result = fn(chunk, context=context)
        chunk_files = {path.name: path.read_bytes() for path in sorted(folder.iterdir())}
    except FileNotFoundError as exc:
        if sent is not None or exc.filename is None:
            raise
        raise missing_input(exc, _node_name(), context_box[2]) from None
    finally:
        shutil.rmtree(folder, ignore_errors=True)
        if context.fault is None:  # the scratch folder goes once empty (the tests' fault plan keeps its marks there)
            for empty in (context.store / "work", context.store):
                with contextlib.suppress(OSError):  # not empty: another task of the node maps into it
                    empty.rmdir()
    return handoff(result | {"files": chunk_files, "node": _node_name()})


def write_chunk_files(store: Path, number: int, chunk_files: dict[str, bytes]) -> None:
    """A chunk's files, as a task returned them, written into the store's ``work/`` as map_chunk writes them: under a
    temporary folder renamed into place, so the chunk counts all of it or nothing."""
    temporary = store / "work" / f".chunk_{number:06d}.{process_tag()}.tmp"
    shutil.rmtree(temporary, ignore_errors=True)
    try:
        for name, data in chunk_files.items():
            files.write_bytes_atomically(temporary / name, data)
        os.rename(temporary, chunk_dir(store, number))
    except OSError as exc:  # a full disk: nothing of the chunk stays
        shutil.rmtree(temporary, ignore_errors=True)
        raise files.error_naming(exc, store, f"writing chunk {number}'s partial maps; the mapped chunks are kept, rerun to resume") from None


class RayExecutor:
    """The same tasks on Ray: a local instance (started and stopped here) or a cluster (``address``:
    "auto" or "ray://host:port"). Ray retries a task whose worker died."""

    name = "ray"
    chunk_timeout_s = CHUNK_TIMEOUT_S  # how long run() waits for some task to finish (__init__ sets the run's)

    def __init__(self, workers: int | None, address: str | None, log=None, connect_timeout_s: float = RAY_CONNECT_TIMEOUT_S,
                 chunk_timeout_s: float = CHUNK_TIMEOUT_S):
        """Start (or join) Ray; ``attach`` gives it the run's context. Apart, so that a run starts Ray while it
        plans (_run_batch). ``connect_timeout_s``: how long ``address`` may take to answer (check_ray_address)."""
        try:
            import ray
        except ImportError:
            raise ConfigError('--executor ray needs Ray: pip install "evsemmap_warp[ray]"') from None
        self.ray, self.log, self.chunk_timeout_s = ray, log or (lambda m: None), chunk_timeout_s
        self.started = not ray.is_initialized()
        self.own_instance = self.started and not address  # a local instance of exactly ``workers`` CPUs
        if self.started:
            env = {k: v for k, v in os.environ.items() if k in ("WARP_CACHE_PATH", "XDG_CACHE_HOME")}
            # Ray workers import numpy before any task runs, so its BLAS pool is sized by the environment
            # the worker starts with: at its share of the cores, as the pool's workers (LocalExecutor._submit;
            # Ray sets OMP_NUM_THREADS alone). A task takes one CPU of a cluster; a local instance splits this
            # machine. A user's own setting is kept.
            share = max(1, (os.cpu_count() or 1) // (workers or os.cpu_count() or 1)) if not address else 1
            env |= {name: os.environ.get(name, str(share)) for name in MATH_THREAD_VARIABLES}
            options = {"include_dashboard": False, "logging_level": "ERROR", "log_to_driver": False}
            if address:
                check_ray_address(address, connect_timeout_s)
                try:
                    ray.init(address=address, runtime_env={"env_vars": env}, **options)
                except ConnectionError as exc:
                    # Ray authenticates by token by default, and joins by address (not "auto") only with it asked for
                    hint = "" if os.environ.get("RAY_AUTH_MODE") else (
                        "; a Ray instance that authenticates by token (Ray's default) is joined by address with RAY_AUTH_MODE=token "
                        "set here (and its token in ~/.ray/auth_token or RAY_AUTH_TOKEN), or with --ray-address auto on its own machine")
                    raise ConfigError(f"--ray-address {address}: could not join the Ray instance ({exc}){hint}") from None
            else:
                # A local instance's processes, and the workers it starts ahead of the first tasks, inherit this
                # process's environment at ray.init: set for it alone. A runtime_env made Ray start other workers for
                # the first tasks instead of using those (0.5 s more before the first chunk ran).
                with _environment(env):  # "local": a new instance, never one that RAY_ADDRESS or a `ray start` here names
                    ray.init(address="local", num_cpus=workers or os.cpu_count(), **options)
        try:
            self.workers = workers or int(ray.cluster_resources().get("CPU", 1))
            # The head, which run() checks still answers; through Ray Client (ray://) its address is the cluster's
            # own, often closed to the client's machine, and the client's connection reports its loss itself.
            self.gcs_address = None if str(address).startswith("ray://") else ray.get_runtime_context().gcs_address
            self._task = ray.remote(num_cpus=1, max_retries=3)(_ray_task)
        except BaseException:
            if self.started:
                ray.shutdown()
            raise
        self.context_box = None  # attach's: the context's object reference, the scratch folder's name and the probed inputs
        self._stdout = None
        if self.started:  # Ray prints a task's retry (a node lost) on stdout, which carries the run's summary alone
            self._stdout, sys.stdout = sys.stdout, sys.stderr

    def attach(self, context: Context, identity: dict) -> "RayExecutor":
        """Choose how the inputs reach the workers (``identity``: the run's plan, which records the inputs' content),
        then put the run's context in Ray's object store, once for all tasks."""
        self.context, self.read_seconds = context, 0.0
        inputs = probed_inputs(identity)
        nodes, self.inputs, why = self._choose_inputs(inputs, learned_lengths(identity))
        self.log(f"inputs: {self.inputs} ({why})")
        self.cluster = {"nodes": nodes, "inputs": self.inputs, "inputs_why": why, "chunks_per_node": Counter()}
        probed = list(inputs) if self.inputs == SAME_PATH and not self.own_instance else None
        self.context_box = [self.put(context), scratch_name(context.store), probed]
        return self

    def _choose_inputs(self, inputs: dict, required: dict | None = None) -> tuple[int, str, str]:
        """The nodes, how the inputs reach their workers (SAME_PATH or FROM_DRIVER) and why: at the same path when
        every node sees ``inputs`` (path -> the plan's content identity) there with the same content (probe_node).
        ``required``: files every node must see so (the learned lengths, which workers read by the mapping's path)."""
        if self.own_instance:  # its one node is this machine, in this process's view of the files: nothing to probe
            return 1, SAME_PATH, "a local Ray instance, started by this run: this machine's files"
        nodes = self._probe(inputs | (required or {}))
        for node in nodes:
            for path, entry in (required or {}).items():
                if not _same_content(node["inputs"][path], entry):
                    raise ClusterError(f"node {node['node']} does not see the learned lengths {path} (mapping.convbki.lengths_file) "
                                       f"with the driver's content: give every node that file at the same path")
        missing = [(node, path) for node in nodes for path, entry in inputs.items() if not _same_content(node["inputs"][path], entry)]
        if not missing:
            return len(nodes), SAME_PATH, f"every node ({len(nodes)}) sees the inputs at the driver's paths, with the same content"
        (node, path), more = missing[0], len(missing) - 1
        there = node["inputs"][path]  # an empty folder: a mount point with nothing mounted, say
        seen = "does not see" if "sha256" not in there else "sees an empty folder at" if there["files"] == 0 else "sees other content at"
        return len(nodes), FROM_DRIVER, (f"node {node['node']} {seen} {path}" + (f" ({more} more such)" if more else "")
                                         + ": the driver reads and sends each chunk's scans")

    def _probe(self, inputs: dict) -> list[dict]:
        """probe_node's answer from every node with CPUs; a node that cannot import this project, has another
        version of it or does not answer within the chunk timeout stops the run (ClusterError)."""
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        nodes = [n for n in self.ray.nodes() if n.get("Alive") and n.get("Resources", {}).get("CPU", 0) > 0]
        task = self.ray.remote(num_cpus=0, max_retries=0)(probe_node)
        refs = {task.options(scheduling_strategy=NodeAffinitySchedulingStrategy(n["NodeID"], soft=False)).remote(list(inputs)): n
                for n in nodes}
        ready, late = self.ray.wait(list(refs), num_returns=len(refs), timeout=self.chunk_timeout_s)
        if late:
            raise ClusterError(f"node {_describe(refs[late[0]])} did not answer the probe at the start in {self.chunk_timeout_s:g} s "
                               f"(--chunk-timeout-s): is it overloaded or cut off from the driver?")
        answers = []
        for ref in ready:
            try:
                answer = self.ray.get(ref)
            except (self.ray.exceptions.TaskUnschedulableError, self.ray.exceptions.NodeDiedError):
                continue  # a node that died since Ray listed it as alive: no task goes there
            except self.ray.exceptions.RayError as exc:
                cause = getattr(exc, "cause", None) or exc
                raise ClusterError(f"node {_describe(refs[ref])} cannot run this project's tasks ({first_line(cause)}): install "
                                   f"evsemmap_warp {__version__}, the driver's version, on every node") from None
            if answer["version"] != __version__:
                raise ClusterError(f"node {answer['node']} has evsemmap_warp {answer['version']}, the driver {__version__}: install "
                                   f"the same version on every node")
            answers.append(answer)
        return answers

    def put(self, value):
        """``value`` in the object store, its reference; a full store or a lost connection as one line."""
        try:
            return self.ray.put(value)
        except (self.ray.exceptions.ObjectStoreFullError, self.ray.exceptions.OutOfDiskError) as exc:
            raise _object_store_full(exc) from None
        except OSError as exc:
            raise _connection_lost(exc) from None

    def run(self, fn, items: list, on_done) -> None:
        """``fn(*item)`` for every item as Ray tasks (``fn``: map_chunk; each item a chunk, whose files the task returns
        and this driver writes, write_chunk_files); ``on_done(item, result)``. A local instance has as many
        CPUs as workers, so two tasks per worker are in flight (the next one waits in Ray, not in this loop);
        on a running instance or a cluster, which may have more CPUs, one per worker, so that ``workers``
        bounds what the run takes of it (two per worker ran a 1-worker run on both CPUs of a 2-CPU instance).
        A finished task's successor is submitted before ``on_done`` folds its result, so that no worker waits for
        the driver's fold (with one task per worker in flight a worker idled through every fold; docs/performance.md).
        Ray runs a task again (up to 3 times) when its worker or node dies; its chunk is written only once, here."""
        queue = list(items)
        flight = {}
        # a task's math threads: its share of this machine for a local instance, one CPU of a cluster's node
        threads = max(1, (os.cpu_count() or 1) // self.workers) if self.own_instance else 1
        most_in_flight = (2 if self.own_instance else 1) * self.workers

        def submit():
            while queue and len(flight) < most_in_flight:
                item = queue.pop(0)
                flight[self._task.remote(fn, threads, self.context_box, time.time(), self._sent(item[0]), *item)] = item

        submit()
        while flight:
            finished = self.wait(list(flight))
            if not finished:
                for ref in flight:
                    self.ray.cancel(ref, force=True)
                raise stuck_error(self.chunk_timeout_s)
            results = [(flight.pop(ref), self._receive(ref)) for ref in finished]
            submit()
            for item, result in results:
                on_done(item, result)

    def wait(self, refs: list) -> list:
        """The first of ``refs`` to finish (ray.wait), or none after the chunk timeout. Asked in short waits, between
        which the head must answer: Ray ends a driver whose head has gone after a minute, from its C++ core, with a
        message of its own and exit code 1, which no Python code can turn into the run's one line."""
        deadline, silent_since = time.monotonic() + self.chunk_timeout_s, None
        while True:
            try:
                finished, _ = self.ray.wait(refs, num_returns=1, timeout=max(0.0, min(HEAD_CHECK_S, deadline - time.monotonic())))
            except OSError as exc:  # Ray's calls fail so ("Broken pipe") once this machine's Ray node is gone
                raise _connection_lost(exc) from None
            if finished or time.monotonic() >= deadline:
                return finished
            if self.gcs_address is None or _answers(self.gcs_address):
                silent_since = None
            elif silent_since is None:
                silent_since = time.monotonic()
            elif time.monotonic() - silent_since > HEAD_SILENT_S:
                raise _connection_lost(ConnectionError(f"the head at {self.gcs_address} has not answered for {HEAD_SILENT_S:g} s"))

    def _sent(self, chunk):
        """The chunk's scans in the object store, read here, when the nodes do not see the inputs; else None."""
        if self.inputs == SAME_PATH:
            return None
        started = time.perf_counter()
        scans = read_scans(self.context.sources[chunk.sequence], chunk)
        self.read_seconds += time.perf_counter() - started
        return self.put(scans)

    def _receive(self, ref) -> dict:
        """A finished task's result, its chunk's files written into the store."""
        result = self.fetch(ref)
        write_chunk_files(self.context.store, result["number"], result.pop("files"))
        self.cluster["chunks_per_node"][result["node"]] += 1
        return result

    def fetch(self, ref):
        """A finished task's result; a task's failure as one line."""
        try:
            return self.ray.get(ref)
        except self.ray.exceptions.RayTaskError as exc:
            if isinstance(exc.cause, (ValueError, OSError)):  # bad data, a missing input, a full disk: as the task said it
                raise exc.cause from None
            raise ClusterError(f"a task failed on node {exc.ip}: {first_line(exc.cause or exc)}") from None
        except (self.ray.exceptions.ObjectStoreFullError, self.ray.exceptions.OutOfDiskError) as exc:
            raise _object_store_full(exc) from None
        except self.ray.exceptions.RayError as exc:  # the retries spent (nodes lost)
            raise ClusterError(f"Ray could not finish a task ({first_line(exc)}); the chunks mapped so far are kept, and a rerun "
                               f"resumes from them") from None
        except OSError as exc:
            raise _connection_lost(exc) from None

    def summary(self) -> dict:
        """What the run's summary says of the cluster: its nodes, how the inputs reached them and why, the chunks each
        mapped, and the driver's time reading scans to send."""
        return self.cluster | {"chunks_per_node": dict(sorted(self.cluster["chunks_per_node"].items())),
                               "driver_read_s": round(self.read_seconds, 3)}

    def close(self) -> None:
        """Shut down the Ray instance this executor started (a cluster given by address is left running); once.
        Here, not on a thread while the tiles are written: shutting Ray down while the driver may still release
        object references ends the process (tried: stopping it as the last result came in). A local instance's
        node is this machine: its scratch folder goes with it, with what tasks killed in it left (a stuck or
        interrupted run's), unless the tests' fault plan keeps its marks there."""
        if self.started:
            self.started = False
            try:
                self.ray.shutdown()
            finally:
                sys.stdout = self._stdout
            if self.own_instance and self.context_box is not None and self.context.fault is None:
                shutil.rmtree(node_scratch(self.context.store), ignore_errors=True)


def probed_inputs(identity: dict) -> dict:
    """What a worker reads of the run's inputs (a plan's identity entries that have a path, but not the configs, which
    the driver alone reads): path -> the driver's content identity of it (files.content_identity)."""
    payload = [entries for entries in identity["payload"].values() if isinstance(entries, list)]  # checkpoint, alpha files
    entries = [e for entries in identity["inputs"] + payload for e in entries]
    return {e["path"]: e for e in entries if "path" in e and Path(e["path"]).suffix not in (".yaml", ".yml")}


def learned_lengths(identity: dict) -> dict:
    """The learned lengths' file a plan's identity records (convbki, ebs-learned): path -> its content identity."""
    return {e["path"]: e for e in identity.get("learned_lengths") or [] if "path" in e}


def _same_content(seen: dict, expected: dict) -> bool:
    return all(seen.get(k) == expected.get(k) for k in ("files", "bytes", "sha256"))


def _describe(node: dict) -> str:
    """A node of ray.nodes() named as _node_name names it."""
    return f"{node.get('NodeManagerHostname', '?')} ({node.get('NodeManagerAddress', '?')}, node {node['NodeID'][:8]})"


def first_line(exc: BaseException) -> str:
    """``exc`` as its type and first sentence: Ray's messages run on for lines (a worker's sys.path, advice)."""
    lines = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {lines[0].split('. ')[0] if lines else ''}"


def _answers(address: str) -> bool:
    """Whether ``address`` (host:port) accepts a connection within HEAD_CHECK_S."""
    host, _, port = address.rpartition(":")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=HEAD_CHECK_S).close()
    except OSError:
        return False
    return True


def _connection_lost(exc: OSError) -> ClusterError:
    return ClusterError(f"lost the connection to the Ray cluster ({first_line(exc)}): its head, or this machine's Ray node, stopped; "
                        f"the chunks mapped so far are kept, and a rerun resumes from them once the cluster is back")


def _object_store_full(exc: BaseException) -> ClusterError:
    return ClusterError(f"Ray's object store is full ({first_line(exc)}): the chunks mapped so far are kept; rerun with fewer --workers "
                        f"or a smaller --chunk-frames, or give the nodes more object store memory (ray start --object-store-memory)")


def check_ray_address(address: str, timeout_s: float) -> None:
    """Refuse (ConfigError, the line docs/troubleshooting.md lists) a --ray-address host:port (or ray://host:port)
    that does not accept a connection within ``timeout_s`` seconds, before ray.init, which retries such an
    address for many minutes. "auto" and addresses without a port are left to Ray."""
    target = address.removeprefix("ray://")
    host, _, port = target.rpartition(":")
    if address == "auto" or not host:
        return
    try:
        port_number = int(port)
    except ValueError:
        raise ConfigError(f"--ray-address {address}: the port {port!r} is not a number (auto, host:port or ray://host:port)") from None
    try:
        socket.create_connection((host.strip("[]"), port_number), timeout=timeout_s).close()
    except OSError as exc:
        reason = "timed out" if isinstance(exc, TimeoutError) else (exc.strerror or str(exc))
        raise ConfigError(f"--ray-address {address}: could not join the Ray instance (nothing accepted a connection at "
                          f"{host}:{port_number} within {timeout_s:g} s: {reason}; --ray-connect-timeout-s sets the wait)") from None
