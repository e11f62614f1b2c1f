"""Where a grid's cells run: `local` (threads of this process, each driving one cell's child processes, `jobs` at a
time) or `ray` (one Ray task per cell on an existing cluster, each asking for its CPUs and GPUs). Both call
`run_cell` and report every finished cell to `on_done`; both stop their cells on Ctrl-C or SIGTERM, which then
write a checkpoint, so that the next `uw-bench` resumes them.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait

from uw3dgs.bench.cell import Outcome, run_cell, stop_children
from uw3dgs.bench.grid import Cell

POLL_SECONDS = 1.0
"""How often the driver looks at its cells (progress view, finished cells)."""


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity, which a container or `taskset` may narrow)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def local_threads(jobs: int, threads_per_job: int | None, cores: int) -> int:
    """The threads of each job: the cores divided among the jobs, or as asked; ValueError where the jobs would
    oversubscribe the cores (more threads than cores make every job slower, not the grid faster)."""
    if jobs < 1:
        raise ValueError(f"--jobs must be at least 1, got {jobs}")
    if jobs > cores:
        raise ValueError(f"--jobs {jobs} on {cores} core(s) would oversubscribe them; use --jobs {cores} or fewer")
    threads = threads_per_job if threads_per_job is not None else cores // jobs
    if threads < 1 or jobs * threads > cores:
        raise ValueError(f"--jobs {jobs} x --threads-per-job {threads} = {jobs * threads} threads on {cores} core(s); "
                         f"the most that fits is --threads-per-job {cores // jobs}")
    return threads


def run_local(cells: Sequence[Cell], jobs: int, threads: int, on_done: Callable[[Outcome], None],
              on_poll: Callable[[], None] = lambda: None) -> list[Outcome]:
    """Run the cells `jobs` at a time, each with `threads` threads, in grid order."""
    outcomes = []
    pool = ThreadPoolExecutor(max_workers=jobs, thread_name_prefix="uw-bench")
    futures: set[Future] = {pool.submit(run_cell, cell, threads) for cell in cells}
    try:
        while futures:
            done, futures = wait(futures, timeout=POLL_SECONDS, return_when=FIRST_COMPLETED)
            for future in done:
                outcomes.append(future.result())
                on_done(outcomes[-1])
            on_poll()
    except BaseException:  # Ctrl-C, SIGTERM: no new cells; the running ones checkpoint and stop
        for future in futures:
            future.cancel()
        stop_children()
        pool.shutdown(wait=True)
        raise
    pool.shutdown()
    return outcomes


def run_ray(cells: Sequence[Cell], address: str | None, cpus: int, gpus: float, on_done: Callable[[Outcome], None],
            on_poll: Callable[[], None] = lambda: None) -> list[Outcome]:
    """Run every cell as a Ray task asking for `cpus` CPUs (its thread count) and `gpus` GPUs. `address`: a
    cluster's ('auto', 'ray://head:10001', ...); None: Ray's default (RAY_ADDRESS, else a new local instance);
    'local': a new local instance with this machine's cores. The run folders must be on a file system every node
    and this process share (the cells resume from, and the table reads, what they wrote)."""
    try:
        import ray
    except ImportError:
        raise RuntimeError("--executor ray needs Ray: pip install -c constraints.txt 'uw3dgs[ray]' (or pip install "
                           "ray)") from None
    started = not ray.is_initialized()
    if started:
        if address == "local":
            ray.init(num_cpus=available_cores(), include_dashboard=False, log_to_driver=False)
        else:
            ray.init(address=address, log_to_driver=False)
    task = ray.remote(num_cpus=cpus, num_gpus=gpus, max_retries=0)(run_cell)
    pending = {task.remote(cell, cpus): cell for cell in cells}
    outcomes = []
    try:
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1, timeout=POLL_SECONDS)
            for ref in done:
                pending.pop(ref)
                outcomes.append(ray.get(ref))
                on_done(outcomes[-1])
            on_poll()
    except BaseException:  # cancelling a running task interrupts run_cell, which stops its child like SIGTERM
        for ref in pending:
            ray.cancel(ref)
        for ref in pending:  # the cancelled tasks' own errors (TaskCancelledError) say nothing new
            with contextlib.suppress(Exception):
                ray.get(ref)
        raise
    finally:
        if started:
            ray.shutdown()
    return outcomes
