"""Where the captures of a batch run: a local process pool or a Ray cluster — both call
:func:`polarshape.batch.worker.run_capture`, once per capture, and yield its outcomes as they finish.

* :func:`run_local` — ``concurrent.futures.ProcessPoolExecutor`` with the "spawn" start method
  (torch after ``fork`` is unsafe), sized by :func:`plan_local` so that workers × threads never
  exceeds the cores. Ctrl-C or SIGTERM stops the workers through their clean-up (a half-written
  result folder is removed); a worker whose batch process was killed outright (SIGKILL) notices
  within a second and stops the same way.
* :func:`run_ray` — one Ray task per capture (``num_cpus`` = the threads of a run, ``num_gpus=1``
  where the cluster has GPUs and the configuration's device is auto or cuda) on an existing
  cluster (``address``) or a local Ray instance. The workers read the captures and write the
  results themselves: every path must be on a filesystem all the nodes share.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import signal
import threading
import time
from collections.abc import Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from tqdm import tqdm

from polarshape.batch.worker import CaptureOutcome, CaptureTask, error_record, run_capture
from polarshape.errors import ConfigError, DeviceError, PipelineError

__all__ = ["ENGINES", "RAY_INSTALL_HINT", "available_cores", "import_ray", "plan_local", "ray_uses_gpus",
           "run_local", "run_ray"]

logger = logging.getLogger(__name__)

#: The engines ``polarshape batch --engine`` accepts.
ENGINES: tuple[str, ...] = ("local", "ray")

#: What to install for ``--engine ray``.
RAY_INSTALL_HINT = "pip install 'polarshape[cluster]' (in a checkout: .venv/bin/pip install -e '.[cluster]')"

#: Environment variables that size the thread pools of torch's and numpy's math libraries; a local
#: worker starts with each set to its thread count, so that no library starts one thread per core.
_THREAD_VARIABLES: tuple[str, ...] = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")

#: How long stopped workers get to remove their half-written folders before they are killed.
_STOP_GRACE_S = 15.0


def available_cores() -> int:
    """The CPU cores this process may run on (its affinity mask where the OS tells, else all)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def plan_local(n_captures: int, workers: int | None = None, threads: int | None = None,
               cores: int | None = None) -> tuple[int, int]:
    """(workers, threads per worker) of the local engine: by default one thread per worker and as
    many workers as cores (never more than captures); ``--workers N`` alone gives each worker
    cores // N threads.

    Raises:
        ConfigError: workers × threads exceeds the cores (``--workers``, ``--threads-per-worker``).
    """
    cores = available_cores() if cores is None else cores
    for value, option in ((workers, "--workers"), (threads, "--threads-per-worker")):
        if value is not None and value < 1:
            raise ConfigError(f"{option} must be at least 1; got {value}")
    if threads is None:
        threads = max(1, cores // workers) if workers is not None else 1
    if workers is None:
        workers = max(1, cores // threads)
    if workers * threads > cores:
        raise ConfigError(f"--workers {workers} x --threads-per-worker {threads} = {workers * threads} threads on "
                          f"{cores} cores would oversubscribe them; lower --workers or --threads-per-worker")
    return max(1, min(workers, n_captures)), threads


# --- local engine ------------------------------------------------------------------------------


def _stop_on_sigterm(signum: int, frame: object) -> None:
    raise SystemExit(128 + signum)  # through the finally blocks: the half-written folder is removed


def _watch_parent(parent_pid: int) -> None:
    """Stop this worker (SIGTERM to itself) once the batch process that started it is gone."""
    while os.getppid() == parent_pid:
        time.sleep(0.5)
    os.kill(os.getpid(), signal.SIGTERM)


def _init_local_worker(parent_pid: int) -> None:
    """Start of a local worker: Ctrl-C is the batch process's to handle (it stops the workers),
    SIGTERM unwinds the run, and the worker stops when the batch process dies."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _stop_on_sigterm)
    # tqdm's default lock is a multiprocessing one (a named semaphore), which a stopped worker would leak
    tqdm.set_lock(threading.RLock())
    threading.Thread(target=_watch_parent, args=(parent_pid,), daemon=True, name="watch-batch").start()


def _run_in_local_worker(task: CaptureTask) -> CaptureOutcome:
    """:func:`run_capture`, ending the worker process once an interruption has unwound it (the pool
    would otherwise hand it the next capture)."""
    try:
        return run_capture(task)
    except SystemExit as exc:
        os._exit(exc.code if isinstance(exc.code, int) else 1)


@contextlib.contextmanager
def _thread_environment(threads: int) -> Iterator[None]:
    """While inside, the thread-count variables say ``threads`` (spawned workers inherit them at start)."""
    saved = {name: os.environ.get(name) for name in _THREAD_VARIABLES}
    os.environ.update({name: str(threads) for name in _THREAD_VARIABLES})
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def _stop_workers(workers: Sequence[Any]) -> None:
    """SIGTERM each live worker, give it :data:`_STOP_GRACE_S` to clean up, then kill what is left."""
    for process in workers:
        if process.is_alive():
            process.terminate()
    deadline = time.monotonic() + _STOP_GRACE_S
    for process in workers:
        process.join(max(0.0, deadline - time.monotonic()))
        if process.is_alive():
            process.kill()
            process.join(1.0)


def _failed(task: CaptureTask, exc: BaseException, seconds: float = 0.0) -> CaptureOutcome:
    return CaptureOutcome(task.name, task.capture, ok=False, seconds=seconds, error=error_record(exc))


def run_local(tasks: Sequence[CaptureTask], workers: int) -> Iterator[CaptureOutcome]:
    """Run ``tasks`` on ``workers`` local processes (each with ``task.threads`` threads); yields each
    outcome as it finishes. A worker that dies (killed by the OS, e.g. out of memory) fails the
    captures it leaves unfinished; the others are still run.

    Closing the iterator early, Ctrl-C or SIGTERM stops the workers (their half-written result
    folders are removed) and cancels the captures not started.
    """
    if not tasks:
        return
    before = set(multiprocessing.active_children())
    context = multiprocessing.get_context("spawn")
    executor = ProcessPoolExecutor(max_workers=workers, mp_context=context, initializer=_init_local_worker,
                                   initargs=(os.getpid(),))
    try:
        with _thread_environment(tasks[0].threads):  # the workers start at the first submit
            futures = {executor.submit(_run_in_local_worker, task): task for task in tasks}
        pending = set(futures)
        while pending:
            finished, pending = wait(pending, return_when=FIRST_COMPLETED)
            for future in finished:
                try:
                    yield future.result()
                except BrokenProcessPool as exc:
                    reason = PipelineError(f"the worker process running it died ({exc}): killed by the OS, out of "
                                           "memory? Lower --workers; the next run of the batch retries it")
                    yield _failed(futures[future], reason)
        executor.shutdown(wait=True)
    except BaseException:
        executor.shutdown(wait=False, cancel_futures=True)
        _stop_workers([p for p in multiprocessing.active_children() if p not in before])
        executor.shutdown(wait=True)  # the workers are gone: this only releases the pool's queues
        raise


# --- Ray engine --------------------------------------------------------------------------------


def import_ray() -> Any:
    """The ``ray`` module.

    Raises:
        PipelineError: Ray is not installed (the message says what to install).
    """
    try:
        import ray
    except ImportError as exc:
        raise PipelineError(f"--engine ray needs Ray, which is not installed ({exc}); install it with "
                            f"{RAY_INSTALL_HINT}, or use --engine local") from None
    return ray


def ray_uses_gpus(device: str, cluster_gpus: float) -> bool:
    """Whether each Ray task asks for one GPU: the cluster has GPUs and ``device`` is auto or cuda.

    Raises:
        DeviceError: ``device`` is cuda and the cluster has no GPU.
    """
    if device == "cpu":
        return False
    if cluster_gpus <= 0:
        if device.startswith("cuda"):
            raise DeviceError("device: cuda, but the Ray cluster has no GPU; set device: cpu or auto (or --device "
                              "cpu), or add GPU nodes to the cluster")
        return False
    return True


def run_ray(tasks: Sequence[CaptureTask], *, address: str | None = None, device: str = "auto"
            ) -> Iterator[CaptureOutcome]:
    """Run ``tasks`` as Ray tasks (``num_cpus`` = ``task.threads``, one GPU each where
    :func:`ray_uses_gpus`); yields each outcome as it finishes.

    Connects to ``address`` (``ray://…`` or ``HOST:PORT`` of ``ray start --head``; None: the
    ``RAY_ADDRESS`` variable, a cluster started on this machine, else a new local instance) unless
    Ray is initialised already (then that cluster is used and left running).
    Closing the iterator early, Ctrl-C or SIGTERM cancels the tasks (a running one is interrupted
    and removes its half-written folder).

    Raises:
        PipelineError: Ray is not installed, or the cluster cannot be reached. DeviceError: see
            :func:`ray_uses_gpus`.
    """
    ray = import_ray()
    if not tasks:
        return
    started = not ray.is_initialized()
    if started:
        try:
            ray.init(address=address, include_dashboard=False, logging_level=logging.WARNING, log_to_driver=False)
        except ConnectionError as exc:
            raise PipelineError(
                f"--address {address}: cannot connect to the Ray cluster ({exc}); give the address `ray start --head` "
                "printed, and with Ray >= 2.59 (token authentication) export RAY_AUTH_MODE=token here too, with the "
                "cluster's ~/.ray/auth_token (or RAY_AUTH_TOKEN) — or run on the head node without --address"
            ) from None
    refs: dict[Any, CaptureTask] = {}
    try:
        gpus = 1 if ray_uses_gpus(device, float(ray.cluster_resources().get("GPU", 0))) else 0
        remote = ray.remote(run_capture)
        for task in tasks:
            ref = remote.options(num_cpus=task.threads, num_gpus=gpus, max_retries=0, name=f"polarshape:{task.name}")
            refs[ref.remote(task)] = task
        pending = list(refs)
        while pending:
            finished, pending = ray.wait(pending, num_returns=1)
            for ref in finished:
                try:
                    yield ray.get(ref)
                except Exception as exc:  # noqa: BLE001 - the worker died or Ray failed it: recorded, the rest goes on
                    yield _failed(refs[ref], exc)
    except BaseException:
        for ref in refs:
            with contextlib.suppress(Exception):
                ray.cancel(ref)
        raise
    finally:
        if started:
            ray.shutdown()
