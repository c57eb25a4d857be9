"""Process policy (pipeline/parallel.py): worker counts and the OpenMP wait policy are set by entry points
and by an inspection whose caller did not."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from pipeline.parallel import WORKERS_ENV, default_workers


def test_default_workers_is_the_cpus_of_the_process(monkeypatch):
    monkeypatch.delenv(WORKERS_ENV, raising=False)
    expected = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    assert default_workers() == expected >= 1


def test_default_workers_env_override(monkeypatch):
    monkeypatch.setenv(WORKERS_ENV, " 3 ")
    assert default_workers() == 3


@pytest.mark.parametrize("value", ["0", "-1", "two", "1.5"])
def test_default_workers_refuses_a_bad_override(monkeypatch, value):
    monkeypatch.setenv(WORKERS_ENV, value)
    with pytest.raises(ValueError, match=WORKERS_ENV):
        default_workers()


def test_kernel_threads_spared_for_the_block_and_on_this_thread_only():
    import threading

    import numba

    from pipeline.parallel import kernel_threads_spared

    n = numba.get_num_threads()
    seen = {}
    with kernel_threads_spared(1):
        seen["inside"] = numba.get_num_threads()
        other = threading.Thread(target=lambda: seen.setdefault("other", numba.get_num_threads()))
        other.start()
        other.join()
        with kernel_threads_spared(n + 5):
            seen["at least one"] = numba.get_num_threads()
    assert seen == {"inside": max(1, n - 1), "other": n, "at least one": 1}
    assert numba.get_num_threads() == n
    with pytest.raises(RuntimeError), kernel_threads_spared(1):
        raise RuntimeError("left the block")
    assert numba.get_num_threads() == n


def test_importing_the_command_line_and_the_stages_sets_no_process_policy():
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    code = "import os, pipeline.cli, pipeline.stages; print(os.environ.get('OMP_WAIT_POLICY'))"
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == "None"


IMPORT_RUN = """
import importlib, os
import pipeline.run
kernels = [
    importlib.import_module("pipeline.surface.normals.robust").robust_kernel,
    importlib.import_module("pipeline.solvers.pcg")._cg_step,
]
print(os.environ.get("OMP_WAIT_POLICY"), *(len(k.overloads) for k in kernels), *(k.stats.cache_hits.total() for k in kernels))
"""


def test_importing_the_entry_point_sets_the_policy_and_loads_the_cached_kernels():
    # the kernels the suite has run (and cached) are loaded from the cache at import, so that no
    # inspection of the process loads one (a bare script's first inspection at 1224x1024: 0.4 s)
    from pipeline.run import warm_up

    warm_up()  # this tree's kernels of the usual path compiled and cached, as scripts/setup.sh does
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    out = subprocess.run(
        [sys.executable, "-c", IMPORT_RUN], env=env, capture_output=True, text=True, check=True
    )
    policy, *counts = out.stdout.split()
    assert policy == "PASSIVE"
    assert all(int(c) >= 1 for c in counts), out.stdout  # loaded, and from the cache


POLICY = """
import os, sys
from pipeline.parallel import configure_process, set_process_policy
configure_process()
first = os.environ.get("OMP_WAIT_POLICY")
os.environ["OMP_WAIT_POLICY"] = "ACTIVE"
print(first, set_process_policy(), os.environ["OMP_WAIT_POLICY"])
"""


@pytest.mark.parametrize(("given", "expected"), [(None, "PASSIVE"), ("ACTIVE", "ACTIVE")])
def test_configure_process_sets_passive_waiting_once_unless_the_user_chose(given, expected):
    # in a process of its own: this one's policy was set by conftest
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if given is not None:
        env["OMP_WAIT_POLICY"] = given
    out = subprocess.run(
        [sys.executable, "-c", POLICY], env=env, capture_output=True, text=True, check=True
    )
    # the second call changes nothing
    assert out.stdout.split() == [expected, "False", "ACTIVE"]


BARE_CALLER = """
import os, sys, tempfile
from pathlib import Path
import pipeline.run as run
from pipeline.simulate import CaptureSpec, PlateSpec, simulate_capture
before = os.environ.get("OMP_WAIT_POLICY")
with tempfile.TemporaryDirectory() as tmp:
    bundle = simulate_capture(Path(tmp) / "c", plate=PlateSpec(), capture=CaptureSpec(width=160, height=128), seed=0)
    run.inspect(bundle, bundle / "target.json", out_dir=Path(tmp) / "out")
print(before, os.environ.get("OMP_WAIT_POLICY"))
"""


def test_a_bare_caller_inspects_under_the_policy():
    # a script that calls the inspection without the command line's start-up (OpenMP's threads would
    # spin and take the second core; measured 0.70 s against 0.60 s at 1224x1024)
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    out = subprocess.run(
        [sys.executable, "-c", BARE_CALLER], env=env, capture_output=True, text=True, check=True
    )
    assert out.stdout.split() == ["PASSIVE", "PASSIVE"]  # set by the import already


def test_freed_memory_is_kept_for_reuse_unless_the_user_chose(monkeypatch):
    from pipeline.parallel import keep_freed_memory

    for name in ("MALLOC_MMAP_THRESHOLD_", "MALLOC_MMAP_MAX_", "MALLOC_TRIM_THRESHOLD_"):
        monkeypatch.delenv(name, raising=False)
    if sys.platform.startswith("linux"):  # glibc accepts the settings
        assert keep_freed_memory()
    for name, value in (("MALLOC_TRIM_THRESHOLD_", "131072"), ("MALLOC_MMAP_MAX_", "65536")):
        with monkeypatch.context() as env:
            env.setenv(name, value)
            assert not keep_freed_memory()


PAGED_IN = """
import resource, sys
from pipeline.parallel import keep_freed_memory, prefault_heap
import numpy as np
prefault = sys.argv[1] == "1"
assert keep_freed_memory()
if prefault:
    prefault_heap(256 * 2**20).join()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
blocks = [np.ones(8 * 2**20 // 8) for _ in range(24)]  # 192 MB in blocks of 8 MB, written
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc")
def test_the_prefaulted_heap_serves_the_first_images_without_page_faults():
    # 192 MB of images on a fresh heap: ~12 000 page faults here (each page zeroed by the kernel; numpy
    # asks for huge pages where it can, hence not 49 000); after
    # prefault_heap they land on pages the heap already holds
    def faults(prefault: bool) -> int:
        out = subprocess.run(
            [sys.executable, "-c", PAGED_IN, "1" if prefault else "0"],
            env={k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")},
            capture_output=True,
            text=True,
            check=True,
        )
        return int(out.stdout.strip())

    fresh, prefaulted = faults(False), faults(True)
    assert fresh > 1_000
    assert prefaulted < 0.05 * fresh


def test_deferred_work_is_done_by_the_caller_when_no_worker_has_started_it():
    """``finish`` runs on the caller's thread each piece of work still queued (the last submitted
    first) and waits for the rest; every result and exception is the call's own."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    from pipeline.parallel import Deferred, finish

    release, started = threading.Event(), threading.Event()
    ran_on: dict[str, str] = {}

    def work(name: str) -> str:
        if name == "busy":
            started.set()
            release.wait(5)
        ran_on[name] = threading.current_thread().name
        return name

    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="worker") as pool:
        busy = Deferred(pool, work, "busy")
        queued = [Deferred(pool, work, f"queued {k}") for k in range(3)]
        assert started.wait(5)
        threading.Timer(0.2, release.set).start()
        finish([busy, *queued])
    assert ran_on["busy"].startswith("worker")
    assert all(ran_on[f"queued {k}"] == threading.current_thread().name for k in range(3))
    assert [d.result() for d in (busy, *queued)] == ["busy", "queued 0", "queued 1", "queued 2"]

    calls = []

    def fail() -> None:
        calls.append(1)
        raise OSError("disk full")

    with ThreadPoolExecutor(max_workers=1) as pool:
        blocker = Deferred(pool, release.wait, 5)
        failing = Deferred(pool, fail)
        with pytest.raises(OSError, match="disk full"):
            finish([blocker, failing])
        with pytest.raises(OSError, match="disk full"):  # kept, not made again
            failing.result()
    assert len(calls) == 1


def test_blas_runs_on_its_callers_thread_within_the_block_and_as_before_after_it():
    from threadpoolctl import threadpool_info

    from pipeline.parallel import single_threaded_blas

    def blas_threads() -> list[int]:
        return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]

    before = blas_threads()
    with single_threaded_blas():
        assert blas_threads() and all(n == 1 for n in blas_threads())
    assert blas_threads() == before
