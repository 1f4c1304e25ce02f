"""The executors that run a batch's tasks on this machine: InlineExecutor (in this process, one after
another) and LocalExecutor (a process pool). The Ray executor is ray_executor.RayExecutor. Each has
``name``, ``workers``, ``run(fn, items, on_done)`` and ``close()``."""

from __future__ import annotations

import os
import pickle
import tempfile
import threading
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

from ... import files
from ...limits import CHUNK_TIMEOUT_S
from .worker import Context, as_task, init_worker


class InlineExecutor:
    """The tasks one after another in this process (tests and debugging: the same task functions,
    without the process boundary)."""

    name = "inline"
    workers = 1

    def __init__(self, context: Context):
        self.context = context

    def run(self, fn, items: list, on_done) -> None:
        """``fn(*item)`` for every item in order; ``on_done(item, result)`` after each."""
        for item in items:
            on_done(item, fn(*item, context=self.context))

    def close(self) -> None:
        """Nothing to release."""


MATH_THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
# How long close() lets the pool's workers end by themselves (an idle one exits at once), and then how long an
# interrupted worker gets to stop its task (cleaning up its temporary files) before it is terminated.
CLOSE_GRACE_S = 5.0
INTERRUPT_GRACE_S = 3.0


def stuck_error(timeout_s: float, what: str = "chunk") -> TimeoutError:
    """The run's end when no ``what`` (a chunk, or a fold of the tiles) finished for ``timeout_s`` (a worker or a node
    stuck): the chunks mapped so far stay."""
    return TimeoutError(f"no {what} finished in {timeout_s:g} s (--chunk-timeout-s): a worker or a node is stuck; "
                        "the chunks mapped so far are kept, and a rerun resumes from them")


class WorkersDied(OSError):
    """A chunk whose worker died every time it ran (out of memory, killed), or workers that died as they started: one
    line (an OSError, as the command line reports it)."""

    def __init__(self, times: int, task, any_finished: bool):
        why = "" if any_finished else (" (no task finished: a worker that dies as it starts prints why above; a script that starts "
                                       'a batch does so under if __name__ == "__main__":)')
        super().__init__(f"batch: a worker died {times} times running {task}; giving up{why}")


class LocalExecutor:
    """A process pool, one worker per core by default; a pool whose worker died is replaced and the
    unfinished tasks are run again (each at most ``retries`` more times)."""

    name = "local"

    def __init__(self, workers: int, context: Context, retries: int = 3, log=None, chunk_timeout_s: float = CHUNK_TIMEOUT_S):
        import multiprocessing

        self.workers, self.context, self.retries, self.log = workers, context, retries, log or (lambda m: None)
        self.chunk_timeout_s = chunk_timeout_s
        self._mp = multiprocessing.get_context("spawn")  # no fork of a process with Warp and threads loaded
        self._threads = max(1, (os.cpu_count() or 1) // workers)
        self._pool = None
        self._context_path: str | None = None

    def _submit(self, fn, item):
        """Submit a task; a worker process started by it starts with Ctrl-C ignored (the setting passes
        through exec) until init_worker installs its handler, so an interrupt while workers start up
        leaves no traceback of theirs, only the driver's "interrupted". It also starts with its math
        libraries' thread pools (OpenBLAS, OpenMP, MKL) at its share of the cores, which they read once
        on loading: at their default every worker's BLAS takes every core (the point transforms), and
        workers sharing the cores then map slower than with their share each. A user's own setting of
        those variables is kept."""
        import signal

        previous = signal.signal(signal.SIGINT, signal.SIG_IGN) if threading.current_thread() is threading.main_thread() else None
        saved = {name: os.environ.get(name) for name in MATH_THREAD_VARIABLES}
        for name in MATH_THREAD_VARIABLES:
            os.environ.setdefault(name, str(self._threads))
        try:
            return self._pool.submit(as_task, fn, time.time(), *item)
        finally:
            for name, value in saved.items():
                if value is None:
                    os.environ.pop(name, None)
            if previous is not None:
                signal.signal(signal.SIGINT, previous)

    def _new_pool(self):
        """A pool whose workers read the context from a file (_start_worker)."""
        if self._context_path is None:
            self._context_path = self._write_context()
        return ProcessPoolExecutor(self.workers, mp_context=self._mp, initializer=_start_worker, initargs=(self._context_path, self._threads))

    def _write_context(self) -> str:
        """The context, pickled into a file of the temporary folder (its path). Not the initializer's argument: that
        goes into each worker's start-up pipe, whose write blocks until the worker reads it, and a worker that dies as it
        starts (a script that starts a pool with no ``if __name__ == "__main__":`` runs itself again there) never reads
        more than a pipe holds, 64 KiB; the sources of a drive of 300 frames or more are more."""
        what = "writing the run's context for the pool's workers; TMPDIR sets the folder"
        try:
            descriptor, path = tempfile.mkstemp(prefix="evsemmap-batch-context-", suffix=".pickle")
        except OSError as exc:
            raise files.error_naming(exc, tempfile.gettempdir(), what) from None
        try:
            with os.fdopen(descriptor, "wb") as file:
                pickle.dump(self.context, file, protocol=pickle.HIGHEST_PROTOCOL)
        except BaseException as exc:
            Path(path).unlink(missing_ok=True)
            if isinstance(exc, OSError):
                raise files.error_naming(exc, tempfile.gettempdir(), what) from None
            raise
        return path

    def run(self, fn, items: list, on_done) -> None:
        """``fn(*item)`` for every item, at most two per worker in flight; ``on_done(item, result)``."""
        pending = list(items)
        attempts = {i: 0 for i in range(len(items))}
        order = {id(item): i for i, item in enumerate(items)}
        while pending:
            self._pool = self._pool or self._new_pool()
            flight = {}
            broken = False
            queue = list(pending)
            try:
                while queue or flight:
                    while queue and len(flight) < 2 * self.workers:
                        item = queue.pop(0)
                        flight[self._submit(fn, item)] = item
                    finished, _ = wait(flight, timeout=self.chunk_timeout_s, return_when=FIRST_COMPLETED)
                    if not finished:
                        self._interrupt_workers()
                        raise stuck_error(self.chunk_timeout_s)
                    for future in finished:
                        item = flight.pop(future)
                        on_done(item, future.result())
                        pending.remove(item)
            except BrokenProcessPool:
                broken = True
            except KeyboardInterrupt:  # Ctrl-C: stop the workers' tasks too (a worker that was still starting missed it)
                self._interrupt_workers()
                raise
            if broken:
                self._pool.shutdown(wait=False, cancel_futures=True)
                self._pool = None
                for item in pending:
                    attempts[order[id(item)]] += 1
                    if attempts[order[id(item)]] > self.retries:
                        raise WorkersDied(self.retries + 1, item[0], any_finished=len(pending) < len(items))
                self.log(f"a worker died; a new pool runs the {len(pending)} unfinished task(s) again")

    def _interrupt_workers(self) -> None:
        """Cancel what has not started and interrupt every worker (_interrupt)."""
        if self._pool is None:
            return
        processes = self._processes()
        self._pool.shutdown(wait=False, cancel_futures=True)
        self._pool = None
        _interrupt(processes)

    def _processes(self) -> list:
        return list((getattr(self._pool, "_processes", None) or {}).values())

    def close(self) -> None:
        """Stop the pool's workers (tasks not started are cancelled). After a run that finished they are idle and
        exit at once; after a failure a worker may still be in a task, or stuck in one: it gets CLOSE_GRACE_S to
        end, then is interrupted as on Ctrl-C (the pool's own shutdown(wait=True) waits for its tasks without bound).
        The context's file goes with them."""
        try:
            if self._pool is not None:
                processes = self._processes()
                self._pool.shutdown(wait=False, cancel_futures=True)
                self._pool = None
                deadline = time.monotonic() + CLOSE_GRACE_S
                for process in processes:
                    process.join(max(0.0, deadline - time.monotonic()))
                _interrupt([process for process in processes if process.is_alive()])
        finally:
            if self._context_path is not None:
                Path(self._context_path).unlink(missing_ok=True)  # a cleaner of the temporary folder may have been first
                self._context_path = None


def _start_worker(context_path: str, threads: int) -> None:
    """A pool worker's initializer: the context from its file (LocalExecutor._write_context says why a file), then
    init_worker."""
    with open(context_path, "rb") as file:
        context = pickle.load(file)
    init_worker(context, threads)


def _interrupt(processes: list) -> None:
    """Interrupt ``processes`` (pool workers): one in a task stops it, cleaning up its temporary files, an idle one
    exits (_worker_interrupt). One that was still starting up (Ctrl-C ignored until init_worker) would run a whole
    chunk: after INTERRUPT_GRACE_S in all, those still running are terminated (what they leave is cleared by the
    next run, remove_unfinished_chunks)."""
    import signal

    for process in processes:
        try:
            os.kill(process.pid, signal.SIGINT)
        except (ProcessLookupError, TypeError):
            pass
    deadline = time.monotonic() + INTERRUPT_GRACE_S
    for process in processes:
        process.join(max(0.0, deadline - time.monotonic()))
        if process.is_alive():
            process.terminate()
