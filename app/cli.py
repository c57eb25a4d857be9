"""``plate-inspect serve``: the web server plus its job consumer (a child process), and
``plate-inspect worker``: a job consumer alone (a worker machine of a yard).

Registered in the CLI through the entry-point group ``plate_inspect.commands``
(``serve = "app.cli:register"``, which adds both); the pipeline's CLI never imports ``app``.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

from app.settings import Settings

log = logging.getLogger("app.serve")

#: Seconds the consumer gets to stop after SIGTERM before it is killed.
CONSUMER_STOP_TIMEOUT_S = 10.0


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add the ``serve`` and ``worker`` subcommands to the CLI's subparsers."""
    p = subparsers.add_parser(
        "serve",
        help="run the inspection service (REST API, dashboard, job consumer)",
        description="Run the cell's server: the REST API under /api/v1 (OpenAPI at /docs), the dashboard, and a "
        "job consumer process that runs the pipeline. Settings come from PLATE_INSPECT_* variables.",
    )
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8000, help="port (default 8000)")
    p.add_argument(
        "--data-dir",
        type=Path,
        default=None,
        help="data directory (default: PLATE_INSPECT_DATA_DIR or ./var)",
    )
    p.add_argument(
        "--demo",
        action="store_true",
        help="demo cell: generate and print an API token if none is set",
    )
    p.add_argument(
        "--no-worker",
        action="store_true",
        help="no local job consumer: the jobs run on `plate-inspect worker` machines (shared queue)",
    )
    p.set_defaults(handler=serve_command)
    w = subparsers.add_parser(
        "worker",
        help="run a job consumer only (a worker machine of a yard)",
        description="Run a job consumer: it takes inspection jobs from the queue and runs the pipeline. "
        "Same PLATE_INSPECT_* settings as serve; on a shared queue (PLATE_INSPECT_QUEUE_URL) any number "
        "of workers run at once. The database is brought to the current schema on start.",
    )
    w.add_argument(
        "--cell",
        default=None,
        metavar="ID",
        help="also run the acquisition jobs of cell ID (its cameras must be reachable from here: "
        "PLATE_INSPECT_CELL_CONFIG names that cell)",
    )
    w.add_argument(
        "--data-dir",
        type=Path,
        default=None,
        help="data directory, shared by every machine (default: PLATE_INSPECT_DATA_DIR or ./var)",
    )
    w.set_defaults(handler=worker_command)


def worker_command(args: argparse.Namespace) -> int:
    """Handler of ``plate-inspect worker``: :func:`app.worker.main` in this process."""
    from app import worker

    if args.data_dir is not None:
        os.environ["PLATE_INSPECT_DATA_DIR"] = str(args.data_dir.resolve())
    return worker.main([] if args.cell is None else ["--cell", args.cell])


class ConsumerProcess:
    """The job consumer (``python -m app.worker --parent-pid <this pid>``) as a supervised child process.

    It is restarted if it exits while the server runs (a job it was running is reclaimed by the
    new consumer: a worker death, see :mod:`app.jobs`), except when it exits with
    :data:`app.worker.EXIT_CONFIG` (a setting it cannot run with: logged, not retried).
    :meth:`stop` ends it with SIGTERM, then SIGKILL after a timeout. It stops by itself when this
    process dies, even by SIGKILL (:func:`app.jobs.guards.exit_with_parent`).
    """

    def __init__(self, settings: Settings):
        self.env = {**os.environ, **settings.to_env()}
        self.args = consumer_cell_args(settings)
        self.proc: subprocess.Popen[bytes] | None = None
        self._stopping = threading.Event()
        self._watchdog: threading.Thread | None = None

    def start(self) -> None:
        self._spawn()
        self._watchdog = threading.Thread(target=self._watch, name="consumer-watchdog", daemon=True)
        self._watchdog.start()

    def _spawn(self) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "app.worker", "--parent-pid", str(os.getpid()), *self.args],
            env=self.env,
        )
        log.info("job consumer started (pid %s)", self.proc.pid)

    def _watch(self) -> None:
        # imported here: the whole service behind app.worker would otherwise load with every
        # `plate-inspect` command (the pipeline's CLI loads this module to register `serve`)
        from app.worker import EXIT_CONFIG

        while not self._stopping.wait(1.0):
            code = None if self.proc is None else self.proc.poll()
            if code is None or self._stopping.is_set():
                continue
            if code == EXIT_CONFIG:
                log.error(
                    "job consumer refused its settings (exit %s, see its log above); not restarted: jobs stay "
                    "queued until the settings are fixed and the service restarted",
                    code,
                )
                return
            log.warning("job consumer exited with %s; restarting it", code)
            self._spawn()

    def stop(self) -> None:
        self._stopping.set()
        if self._watchdog is not None:
            self._watchdog.join()
        if self.proc is None or self.proc.poll() is not None:
            return
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(CONSUMER_STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            log.warning("job consumer did not stop in %.0f s; killing it", CONSUMER_STOP_TIMEOUT_S)
            self.proc.kill()
            self.proc.wait()
        log.info("job consumer stopped")


def consumer_cell_args(settings: Settings) -> list[str]:
    """``["--cell", id]`` for the consumer of a server with a cell on a shared queue (it runs that
    cell's acquisitions), else nothing (the embedded queue's one consumer runs every job)."""
    if settings.queue_url is None:
        return []
    from app.services.cell import CellUnavailable, load_cell

    try:
        return ["--cell", load_cell(settings).cell_id]
    except CellUnavailable:
        return []


def serve_command(args: argparse.Namespace) -> int:
    """Handler of ``plate-inspect serve``: start the consumer, run uvicorn, stop the consumer."""
    import uvicorn

    from app.main import create_app

    if not 0 < args.port < 65536:
        raise ValueError(f"--port: expected 1..65535, got {args.port}")
    overrides = {}
    if args.data_dir is not None:
        overrides["data_dir"] = args.data_dir
    if args.demo:
        overrides["demo"] = True
    settings = Settings(**overrides)
    generated_token = settings.api_token is None
    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s", force=True
    )
    try:
        app = create_app(settings)
    except ValueError as err:
        print(f"plate-inspect serve: {err}", file=sys.stderr)
        return 2
    settings = app.state.settings
    if generated_token:
        print(f"plate-inspect serve: demo mode, API token: {app.state.api_token}", flush=True)
    print(
        f"plate-inspect serve: http://{args.host}:{args.port}/ (API docs at /docs), data in {settings.data_dir.resolve()}",
        flush=True,
    )
    consumer = None if args.no_worker else ConsumerProcess(settings)
    if consumer is None:
        print("plate-inspect serve: no local job consumer (--no-worker)", flush=True)
    # uvicorn shuts down gracefully on SIGTERM, then raises the signal again with the handler
    # that was installed before it started: the default one would end this process before the
    # consumer is stopped (leaving it orphaned). Ours just notes it, so the consumer stops first.
    stopped_by: list[int] = []
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: stopped_by.append(signum))
    if consumer is not None:
        consumer.start()
    try:
        uvicorn.run(app, host=args.host, port=args.port, log_level="info")
    finally:
        if consumer is not None:
            consumer.stop()
        signal.signal(signal.SIGTERM, previous)
    return 128 + signal.SIGTERM if stopped_by else 0
