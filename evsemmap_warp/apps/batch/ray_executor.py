"""The Ray executor: a batch's tasks on a local Ray instance it starts and stops, or on a running instance or
cluster it joins by address."""

from __future__ import annotations

import contextlib
import os
import socket
import time

from ...config import ConfigError
from .executors import MATH_THREAD_VARIABLES, stuck_error
from .planning import CHUNK_TIMEOUT_S, RAY_CONNECT_TIMEOUT_S
from .worker import Context, handoff_recorder, init_worker, reset_tasks_started


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


_RAY_CONTEXTS: dict = {}  # object id -> context, per Ray worker process


def _ray_task(fn, threads: int, context_box: list, submitted: float, *args):
    """A Ray task. The context (put once by the driver) comes boxed in a list, so Ray does not fetch
    and unpickle it for every task: each worker process fetches it once (unboxed, unpickling the
    sources for every task made short tasks several times slower, docs/performance.md). ``submitted``:
    when the driver submitted it (time.time()), for the hand-off costs (handoff_recorder)."""
    import ray

    key = context_box[0].hex()
    if key not in _RAY_CONTEXTS:
        reset_tasks_started()  # a cluster's worker that served an earlier run: this run's first task in it
    handoff = handoff_recorder(submitted)  # before fetching the context: a worker's start includes it
    if key not in _RAY_CONTEXTS:
        _RAY_CONTEXTS.clear()
        _RAY_CONTEXTS[key] = ray.get(context_box[0])
        init_worker(_RAY_CONTEXTS[key], threads)
    return handoff(fn(*args, context=_RAY_CONTEXTS[key]))


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
                with _environment(env):
                    ray.init(num_cpus=workers or os.cpu_count(), **options)
        self.workers = workers or int(ray.cluster_resources().get("CPU", 1))
        self._task = ray.remote(num_cpus=1, max_retries=3)(_ray_task)
        self.context_ref = None

    def attach(self, context: Context) -> "RayExecutor":
        """Put the run's context in Ray's object store, once for all tasks."""
        self.context_ref = self.ray.put(context)
        return self

    def run(self, fn, items: list, on_done) -> None:
        """``fn(*item)`` for every item as Ray tasks; ``on_done(item, result)``. A local instance has as many
        CPUs as workers, so two tasks per worker are in flight (the next one waits in Ray, not in this loop);
        on a running instance or a cluster, which may have more CPUs, one per worker, so that ``workers``
        bounds what the run takes of it (two per worker ran a 1-worker run on both CPUs of a 2-CPU instance).
        A finished task's successor is submitted before ``on_done`` folds its result, so that no worker waits for
        the driver's fold (with one task per worker in flight a worker idled through every fold; docs/performance.md)."""
        queue = list(items)
        flight = {}
        threads = max(1, (os.cpu_count() or 1) // self.workers)
        most_in_flight = (2 if self.own_instance else 1) * self.workers

        def submit():
            while queue and len(flight) < most_in_flight:
                item = queue.pop(0)
                flight[self._task.remote(fn, threads, [self.context_ref], time.time(), *item)] = item

        submit()
        while flight:
            finished, _ = self.ray.wait(list(flight), num_returns=1, timeout=self.chunk_timeout_s)
            if not finished:
                for ref in flight:
                    self.ray.cancel(ref, force=True)
                raise stuck_error(self.chunk_timeout_s)
            results = [(flight.pop(ref), self.ray.get(ref)) for ref in finished]
            submit()
            for item, result in results:
                on_done(item, result)

    def close(self) -> None:
        """Shut down the Ray instance this executor started (a cluster given by address is left running); once.
        Here, not on a thread while the tiles are written: shutting Ray down while the driver may still release
        object references ends the process (tried: stopping it as the last result came in)."""
        if self.started:
            self.started = False
            self.ray.shutdown()


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
