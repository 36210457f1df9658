"""Fits as Ray tasks, on a local Ray instance or a cluster, behind ``concurrent.futures.Executor``.

The evaluation submits its fits through an Executor and keeps its own bounded queue
(``run_fits``); ``RayExecutor.submit`` turns each submission into a Ray task and hands back
a concurrent future, so the queue works unchanged. The data set goes into the object store
once (``ray.put``) and every task gets its reference; a worker process reads it from the
store at its first task and keeps it for the next ones (like ``fit_executor``'s workers,
see ``executors.worker_data``). Its scenes are featurised once, at loading: the store
holds the graph tensors, so no fit featurises anything.

Each task asks Ray for ``cpus_per_fit`` CPUs and ``gpus_per_fit`` of a GPU (a fraction: a
small GNN fit uses a sliver of a large GPU, so one GPU runs many fits at once; Ray gives
the task its GPU as the only one visible, ``cuda``) and runs torch on ``threads`` threads
(one by default: more collapse when other work shares the cores, docs/performance.md).
A task whose worker dies (killed, out of memory) runs again up to ``max_retries`` times; an
exception raised by a fit is not retried, since a seeded fit would raise it again.

Ray is an optional dependency (requirements-ray.txt): only this module imports it, and only
``--executor ray`` imports this module.
"""
from __future__ import annotations

import concurrent.futures as futures
import math
import threading
from collections.abc import Iterable, Mapping

from stars_ros.errors import StarsError
from stars_ros.evaluation.executors import hold_worker_data

try:
    import ray
except ImportError as missing:
    raise StarsError('the Ray executor needs Ray, which is not installed: '
                     'pip install -r requirements-ray.txt') from missing

#: Object id of the data set this worker process holds (set in Ray workers only).
_held_data: str | None = None


def _run_task(fn, data_box: list, threads: int, args: tuple, kwargs: dict):
    """``fn(*args, **kwargs)`` in a Ray worker holding the data set of ``data_box``. The
    reference comes boxed in a list, so that Ray hands over the reference, not the data
    set: a worker reads it from the object store once, not at every task."""
    import torch
    global _held_data
    (data,) = data_box
    if _held_data != data.hex():
        hold_worker_data(ray.get(data))
        _held_data = data.hex()
    torch.set_num_threads(threads)
    return fn(*args, **kwargs)


def fit_slots(nodes: Iterable[Mapping[str, float]], cpus_per_fit: float, gpus_per_fit: float) -> int:
    """How many fits nodes with these resources ('CPU', 'GPU' per node) run at once: a fit
    runs on one node, so each node is counted alone."""
    def fits(available: float, per_fit: float) -> int:
        return math.floor(round(available / per_fit, 6))  # 0.3 / 0.1 is 2.9999999999999996
    slots = 0
    for resources in nodes:
        counts = [fits(resources.get('CPU', 0.0), cpus_per_fit)] if cpus_per_fit else []
        counts += [fits(resources.get('GPU', 0.0), gpus_per_fit)] if gpus_per_fit else []
        slots += min(counts) if counts else 0
    return slots


class RayExecutor(futures.Executor):
    """Runs each submitted ``fn(*args, **kwargs)`` as a Ray task in a worker that holds
    ``data`` (read there with ``executors.worker_data``).

    Connects as ``ray.init(address)`` does: the given address, else ``RAY_ADDRESS``, else a
    cluster started on this machine with ``ray start``, else a new local instance; in a
    process already connected to Ray, that connection is used (and left open at shutdown).

    Args:
        data (RatingData): the data set every fit reads; put into the object store once.
        address (str, optional): Ray cluster address, e.g. ``10.0.0.5:6379``.
        cpus_per_fit (float): CPUs Ray reserves per task (default: 1).
        gpus_per_fit (float): GPUs Ray reserves per task, a fraction to share one (default: 0).
        threads (int): torch threads in each task (default: 1).
        max_retries (int): runs again of a task whose worker died (default: 3).
    """

    def __init__(self, data, address: str | None = None, cpus_per_fit: float = 1.0, gpus_per_fit: float = 0.0,
                 threads: int = 1, max_retries: int = 3):
        if cpus_per_fit < 0 or gpus_per_fit < 0 or not cpus_per_fit + gpus_per_fit:
            raise ValueError(f'a fit must ask for some CPU or GPU, got cpus_per_fit {cpus_per_fit}, '
                             f'gpus_per_fit {gpus_per_fit}')
        if threads < 1 or max_retries < 0:
            raise ValueError(f'need threads >= 1 and max_retries >= 0, got {threads} and {max_retries}')
        self.cpus_per_fit, self.gpus_per_fit, self.threads = cpus_per_fit, gpus_per_fit, threads
        self._connected_here = not ray.is_initialized()
        if self._connected_here:
            ray.init(address=address, include_dashboard=False)
        self._data = ray.put(data)
        self._task = ray.remote(_run_task).options(num_cpus=cpus_per_fit, num_gpus=gpus_per_fit,
                                                   max_retries=max_retries, retry_exceptions=False)
        self._running: dict[futures.Future, ray.ObjectRef] = {}  # settled from Ray's threads, hence the lock
        self._lock = threading.Lock()

    @property
    def address(self) -> str:
        """The cluster's address (of the local instance, when one was started)."""
        return ray.get_runtime_context().gcs_address

    def capacity(self) -> int:
        """How many fits the cluster runs at once with this executor's per-fit resources."""
        return fit_slots((node['Resources'] for node in ray.nodes() if node['Alive']), self.cpus_per_fit,
                         self.gpus_per_fit)

    def submit(self, fn, /, *args, **kwargs) -> futures.Future:
        if self._data is None:
            raise RuntimeError('cannot submit to a RayExecutor after shutdown')
        reference = self._task.remote(fn, [self._data], self.threads, args, kwargs)
        future = futures.Future()
        with self._lock:
            self._running[future] = reference
        reference.future().add_done_callback(lambda done: self._settle(future, done))
        return future

    def _settle(self, future: futures.Future, done: futures.Future) -> None:
        """Hand ``done``'s outcome to ``future``: a fit's exception as itself, with the
        worker's traceback as a note, rather than Ray's wrapper of it."""
        with self._lock:
            self._running.pop(future, None)
        if not future.set_running_or_notify_cancel():  # cancelled by whoever holds it
            return
        error = done.exception()
        if error is None:
            future.set_result(done.result())
            return
        if isinstance(error, ray.exceptions.RayTaskError) and isinstance(error.cause, Exception):
            error.cause.add_note(f'raised in a Ray worker:\n{error}')
            error = error.cause
        future.set_exception(error)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """Cancel the tasks not finished (with ``cancel_futures``: their workers are killed,
        not retried) or wait for them, free the data set and, when this executor connected
        to Ray, disconnect (which ends a local instance it started)."""
        if self._data is None:
            return
        with self._lock:
            running = list(self._running.values())
        if cancel_futures:
            for reference in running:
                ray.cancel(reference, force=True)
        elif wait and running:
            ray.wait(running, num_returns=len(running))
        self._data = None
        if self._connected_here:
            ray.shutdown()
