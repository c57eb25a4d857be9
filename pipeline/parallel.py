"""Process policy: how many worker threads the pipeline uses, and how OpenMP's threads wait.

Importing the pipeline's modules sets nothing process-wide, with one exception: the orchestration
entry point, :mod:`pipeline.run`, sets this policy (:func:`set_process_policy`) and loads the
compiled kernels from their cache (:func:`load_cached_kernels`) when it is imported, so that no
inspection of the process loads them. Functions that run work beside their main line take a
``workers`` count whose default comes from :func:`default_workers`; the entry points
(``plate-inspect``'s :func:`pipeline.cli.main`, the service's job consumer) call
:func:`configure_process` once at start, before any compiled kernel runs. The policy also drops a
compiled-kernel cache older than the modules it was compiled from (:func:`drop_stale_kernels`).
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import functools
import json
import os
import sys
import threading
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Executor, Future
from pathlib import Path
from typing import Any, Generic, TypeVar

#: Environment variable that overrides the number of worker threads (an integer >= 1).
WORKERS_ENV = "PLATE_INSPECT_WORKERS"

#: glibc malloc: blocks up to this many bytes come from the heap, where a freed block is reused,
#: instead of a fresh mapping that the kernel zeroes page by page on first touch (glibc's
#: largest allowed value, 32 MiB on 64-bit: an image of 1224x1024 float64 is 10 MB). The policy
#: also allows no mapping at all (``M_MMAP_MAX`` 0), so that larger blocks (a capture's stack of
#: twelve 1224x1024 float32 images is 60 MB) come from the heap too.
MALLOC_MMAP_THRESHOLD_BYTES = 32 * 2**20
#: glibc malloc: free memory at the top of the heap is given back to the system only beyond this.
MALLOC_TRIM_THRESHOLD_BYTES = 2**30
#: glibc malloc: every thread allocates from the one main heap, so that the memory an inspection's
#: worker threads free is reused by the next inspection's (new) workers and by the main thread,
#: and memory paged in once serves them all (a thread arena's heap is paged in on its own).
MALLOC_ARENAS = 1
#: Heap paged in at start-up (:func:`prefault_heap`), beside the imports: an inspection's working set
#: (~380 MB at 1224x1024, ~500 MB for a 2448x2048 capture measured on its 1224x1024 working grid).
PREFAULT_HEAP_BYTES = 512 * 2**20
#: The paging-in thread's nice value: it takes only time the process's other threads leave.
PREFAULT_NICE = 19
#: mallopt parameters (glibc's malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_MMAP_MAX, _M_ARENA_MAX = -1, -3, -4, -8


def default_workers() -> int:
    """The number of worker threads for work that runs beside the pipeline's main line.

    Returns
    -------
    int
        ``$PLATE_INSPECT_WORKERS`` when set, else the number of CPUs this process may run on.

    Raises
    ------
    ValueError
        ``PLATE_INSPECT_WORKERS`` is set but not an integer >= 1.
    """
    text = os.environ.get(WORKERS_ENV, "").strip()
    if text:
        try:
            workers = int(text)
        except ValueError:
            workers = 0
        if workers < 1:
            raise ValueError(f"{WORKERS_ENV}: expected an integer >= 1, got {text!r}")
        return workers
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


@contextlib.contextmanager
def kernel_threads_spared(spare: int) -> Iterator[None]:
    """Within the block, the parallel numba kernels started on this thread run on ``spare`` threads fewer
    than numba's count (at least one): the threads left are the work's beside them.

    numba's thread count is the calling thread's own; the results of the pipeline's parallel kernels do
    not depend on it (their loops' iterations are independent).
    """
    import numba  # the policy module imports no kernel machinery at import

    n = numba.get_num_threads()
    numba.set_num_threads(max(1, n - max(0, int(spare))))
    try:
        yield
    finally:
        numba.set_num_threads(n)


@functools.cache
def _blas_controller() -> Any:
    """The process's thread-pool libraries (threadpoolctl's ``ThreadpoolController``), found once, at the
    first call (after :mod:`pipeline.run`'s imports have loaded numpy's and scipy's BLAS): a controller
    scans every library the process has loaded, which ``threadpool_limits`` does on each call."""
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


def single_threaded_blas() -> Any:
    """A context manager (threadpoolctl's limiter) within which BLAS runs on its caller's thread only.

    The pipeline's BLAS calls are small (3x3 systems, N x 3 products, a few fits' normal equations):
    OpenBLAS's threads would only spin after each one and take a core from the work beside it. Leaving
    the block restores the limits found on entering it; ``restore_original_limits()`` does the same for
    a limiter kept open.
    """
    return _blas_controller().limit(limits=1, user_api="blas")


T = TypeVar("T")


class Deferred(Generic[T]):
    """Work submitted to a pool that the caller does itself when it asks for the result before a worker
    has started it (:meth:`result`).

    A caller that would otherwise wait for its pool's queue to drain (the artifact writes at the end of
    an inspection, two workers and a queue of files) takes the work still queued instead of idling: the
    same calls, on the caller's thread.
    """

    def __init__(self, pool: Executor, fn: Callable[..., T], *args: Any, **kwargs: Any) -> None:
        self._call = functools.partial(fn, *args, **kwargs)
        self.future: Future[T] = pool.submit(self._call)

    def run_if_queued(self) -> None:
        """Make the call here, on the caller's thread, when no worker has started it (its result, or its
        exception, then comes from here)."""
        if self.future.cancel():
            done: Future[T] = Future()
            try:
                done.set_result(self._call())
            except Exception as err:  # kept, as a worker's future keeps it, for result() to raise
                done.set_exception(err)
            self.future = done

    def result(self) -> T:
        """The call's result: made here when no worker has started it (:meth:`run_if_queued`), else the
        worker's (its exception raised as :meth:`concurrent.futures.Future.result` raises it)."""
        self.run_if_queued()
        return self.future.result()


def finish(work: Iterable[Deferred[Any]]) -> None:
    """Wait for every piece of ``work``, first making here each one that no worker has started (the most
    recently submitted first), then waiting for those under way; the first exception, in the order of
    ``work``, is raised."""
    work = list(work)
    for item in reversed(work):
        item.run_if_queued()
    for item in work:
        item.result()


_policy_lock = threading.Lock()
_policy_set = False
#: Whether the policy's malloc settings took (:func:`keep_freed_memory`), and whether
#: :func:`configure_process` has started paging the heap in.
_heap_kept = False
_prefaulted = False


def configure_process() -> None:
    """Set the process-wide thread policy of a process that runs inspections; call it once at start.

    The parallel numba kernels (OpenMP layer) leave their worker threads spinning after each
    parallel region unless told otherwise; on the cell's 2-core computer that spinning takes the
    second core from the work beside it (stereo, artifact writing; measured in docs/figures.md,
    *Speed, end to end*). ``OMP_WAIT_POLICY=PASSIVE`` is read by libgomp when it starts, so this
    must run before the first kernel; a value already set in the environment wins.

    An inspection allocates and frees images of several MB many times over: with glibc's default
    policy most of them are fresh mappings, and zeroing their pages took ~0.3 of the ~1.4
    core-seconds of an inspection at 1224x1024 (measured with ``perf``). :func:`keep_freed_memory`
    keeps freed blocks for reuse. The first inspection of a process would still page in its whole
    working set (~45 000 pages at 1224x1024, 0.1-0.7 s of system time on the cell's virtual machine):
    :func:`prefault_heap` pages the heap in on a thread of its own while the process imports its
    modules on the other core.
    """
    global _prefaulted
    set_process_policy()
    with _policy_lock:
        if not _heap_kept or _prefaulted:
            return
        _prefaulted = True
    prefault_heap()


def set_process_policy() -> bool:
    """The thread and memory policy of :func:`configure_process` without its paging-in, once per process.

    :mod:`pipeline.run` calls it when imported, so that a program that calls the inspection without the
    entry points' start-up (a script, a notebook, another service) runs it as fast as the command line
    does (``benchmarks/bench_pipeline.py --bare``: docs/figures.md). Its effects are a process's
    performance only, never a result; it also drops a compiled-kernel cache older than its sources
    (:func:`drop_stale_kernels`), so that no kernel runs code the tree no longer holds.
    The second and later calls do nothing.

    Returns
    -------
    bool
        Whether this call set the malloc policy (see :func:`keep_freed_memory`); False on every call
        after the first.
    """
    global _policy_set, _heap_kept
    with _policy_lock:
        if _policy_set:
            return False
        _policy_set = True
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    drop_stale_kernels()  # before the first kernel loads from it
    _heap_kept = keep_freed_memory()
    return _heap_kept


def keep_freed_memory() -> bool:
    """Have glibc's malloc keep freed memory for reuse (see :data:`MALLOC_MMAP_THRESHOLD_BYTES`).

    Every block comes from the heap (no mapping of its own, ``M_MMAP_MAX`` 0). The process then holds
    its peak of heap memory (up to :data:`MALLOC_TRIM_THRESHOLD_BYTES` of it free) instead of giving
    it back after each inspection. Nothing is changed when any of these settings is already given in
    the environment (``MALLOC_MMAP_THRESHOLD_``, ``MALLOC_MMAP_MAX_``, ``MALLOC_TRIM_THRESHOLD_``),
    or off glibc.

    Returns
    -------
    bool
        Whether the policy was set.
    """
    if not sys.platform.startswith("linux") or any(
        name in os.environ
        for name in ("MALLOC_MMAP_THRESHOLD_", "MALLOC_MMAP_MAX_", "MALLOC_TRIM_THRESHOLD_")
    ):
        return False
    libc = _glibc()
    if libc is None:
        return False
    mallopt = libc.mallopt
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    if "MALLOC_ARENA_MAX" not in os.environ:
        mallopt(_M_ARENA_MAX, MALLOC_ARENAS)
    return bool(
        mallopt(_M_MMAP_THRESHOLD, MALLOC_MMAP_THRESHOLD_BYTES)
        and mallopt(_M_MMAP_MAX, 0)
        and mallopt(_M_TRIM_THRESHOLD, MALLOC_TRIM_THRESHOLD_BYTES)
    )


def prefault_heap(total_bytes: int = PREFAULT_HEAP_BYTES) -> threading.Thread | None:
    """Page in ``total_bytes`` of the heap on a daemon thread, then free it for reuse.

    Call after :func:`keep_freed_memory` succeeded: the block then comes from the heap and stays there
    when freed, paged in, so that the first inspection's images land on memory the kernel has
    already zeroed. One block, so that the paged-in memory is one free stretch of the heap: taken in
    blocks of 16 MB, the small blocks that other threads took meanwhile (the kernels loaded at
    :mod:`pipeline.run`'s import) could lie between them, and an inspection's largest arrays then
    found no room there and paged fresh memory in. The work is
    done by libc (``malloc``, ``memset``, ``free`` through ctypes, which releases the GIL) on a thread
    of nice :data:`PREFAULT_NICE`: it runs on a core the process's imports leave idle, and yields to
    the warm-up and the inspection. Returns the thread (None off glibc).
    """
    libc = _glibc()
    if libc is None:
        return None
    malloc, memset, free = libc.malloc, libc.memset, libc.free
    malloc.argtypes, malloc.restype = [ctypes.c_size_t], ctypes.c_void_p
    memset.argtypes, memset.restype = (
        [ctypes.c_void_p, ctypes.c_int, ctypes.c_size_t],
        ctypes.c_void_p,
    )
    free.argtypes, free.restype = [ctypes.c_void_p], None

    def page_in() -> None:
        with contextlib.suppress(OSError, AttributeError):  # the idle core's time only
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), PREFAULT_NICE)
        block = malloc(total_bytes)
        if block:
            memset(block, 0, total_bytes)
            free(block)

    thread = threading.Thread(target=page_in, name="plate-inspect-prefault", daemon=True)
    thread.start()
    return thread


@functools.cache
def _glibc() -> ctypes.CDLL | None:
    """The C library when it is glibc (it has ``mallopt``), else None."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.mallopt  # noqa: B018  # glibc's own: the test that this is glibc
    except (OSError, AttributeError):
        return None
    return libc


#: The package whose compiled kernels are cached (:func:`drop_stale_kernels`).
PACKAGE_ROOT = Path(__file__).resolve().parent
#: The fingerprint's file, in the package's own ``__pycache__``.
KERNEL_STAMP_NAME = "kernels.stamp"
#: The cache's files (numba's index and code).
KERNEL_CACHE_PATTERNS = ("*.nbi", "*.nbc")


def drop_stale_kernels(root: Path = PACKAGE_ROOT) -> bool:
    """Drop the kernels' cache under ``root`` when a module with kernels changed since it was kept.

    numba caches a compiled kernel (``cache=True``) beside its module, in ``__pycache__`` (``*.nbi``, the
    index, and ``*.nbc``, the code), and checks the cache against that module's file alone. A kernel
    compiles the kernels it calls into its own code: when a called kernel's module changes (a pull, a
    checkout) and the caller's does not, the caller goes on running the old callee. This happened in
    this tree: the near-field light vectors (``lights/model.py``) were rewritten, and the robust
    normals' kernel (``surface/normals/robust.py``, unchanged) ran the old ones until its cache was
    removed by hand. The kernels compile again on their first call after a drop (``scripts/setup.sh``
    compiles them at install).

    The stamp lists the modules that use numba with their size and modification time; only those are
    looked at on a process's start (a change elsewhere cannot change a compiled kernel). A module that
    starts to call a kernel of a new module changes itself, and so drops the cache too.

    Returns
    -------
    bool
        True when the cache was dropped (no stamp yet, or a listed module changed), False when it
        stands. A package that cannot be written (an installed, read-only one) is left as it is.
    """
    stamp = root / "__pycache__" / KERNEL_STAMP_NAME
    try:
        kept = json.loads(stamp.read_text())
        if kept == _kernel_fingerprint(root, kept):
            return False
    except (OSError, ValueError, TypeError, AttributeError):
        pass
    try:
        for pattern in KERNEL_CACHE_PATTERNS:
            for cached in root.rglob(pattern):
                cached.unlink(missing_ok=True)
        stamp.parent.mkdir(exist_ok=True)
        partial = stamp.with_name(f"{KERNEL_STAMP_NAME}.{os.getpid()}")
        partial.write_text(json.dumps(_kernel_fingerprint(root, _kernel_modules(root))))
        os.replace(partial, stamp)  # whole, even with other processes starting beside this one
    except OSError:
        return False
    return True


def load_cached_kernels(package: str = __package__ or "pipeline") -> int:
    """Load every compiled kernel of ``package``'s imported modules that the on-disk cache holds.

    numba loads a cached kernel on its first call (and sets itself up in the first one), which made a
    process's first inspection markedly longer than its second (``benchmarks/bench_pipeline.py
    --bare``: docs/figures.md). Loading them here moves that to the process's start. Only kernels
    whose cache entry is fresh for this machine and this source are loaded: a missing or stale one (a
    changed module, another CPU) is left to compile on its first call, never here. Loading a parallel
    kernel starts OpenMP's threads: set the process policy first (:func:`set_process_policy`).

    Returns
    -------
    int
        The number of kernels (signatures) loaded; 0 when this numba keeps its cache otherwise.
    """
    from numba.core.registry import CPUDispatcher

    loaded = 0
    prefix = package + "."
    for name, module in list(sys.modules.items()):
        if module is None or not (name == package or name.startswith(prefix)):
            continue
        for value in list(vars(module).values()):
            if isinstance(value, CPUDispatcher) and value.__module__ == name:
                loaded += _load_cached(value)
    return loaded


def _load_cached(kernel: Any) -> int:
    """Load ``kernel``'s (a numba dispatcher's) signatures that its cache holds for this machine and source
    (numba's index keys: signature, codegen, code hash); 0 when its cache is not numba's usual one."""
    try:
        cache = kernel._cache
        codegen = kernel.targetctx.codegen()
        keys = [
            key
            for key in cache._cache_file._load_index()
            if cache._index_key(key[0], codegen) == key
        ]
    except (AttributeError, TypeError, OSError, ValueError):  # another numba, or no readable cache
        return 0
    for key in keys:
        kernel.compile(key[0])  # found in the cache: loaded, not compiled
    return len(keys)


def _kernel_modules(root: Path) -> dict[str, list[int]]:
    """The modules under ``root`` whose source mentions numba (relative paths; values filled by
    :func:`_kernel_fingerprint`)."""
    modules: dict[str, list[int]] = {}
    for directory, subdirs, files in os.walk(root):
        subdirs[:] = [d for d in subdirs if d != "__pycache__"]
        for name in files:
            path = Path(directory, name)
            if name.endswith(".py") and b"numba" in path.read_bytes():
                modules[str(path.relative_to(root))] = []
    return modules


def _kernel_fingerprint(root: Path, modules: dict[str, list[int]]) -> dict[str, list[int]]:
    """Each of ``modules`` (relative paths) with its size and modification time (ns)."""
    out: dict[str, list[int]] = {}
    for relative in sorted(modules):
        st = (root / relative).stat()
        out[relative] = [st.st_size, st.st_mtime_ns]
    return out
