"""A yard on this machine: inspections per minute with 1 and 2 workers (PostgreSQL + Redis, the
real pipeline), and the API's latency for history reads with 10 000 inspections in PostgreSQL
against SQLite. Prints a table.

    .venv/bin/python benchmarks/bench_yard.py [--jobs 8] [--size 320x256] [--rows 10000]

PostgreSQL and Redis are Debian's packages, started in temporary directories on free ports
(``tests/yard/servers.py``; PostgreSQL with its durable defaults here). Each worker count gets a
fresh database and queue; the workers are started (and ready) before the jobs are posted, and the
clock runs from the first post to the last job done.
"""

from __future__ import annotations

import argparse
import random
import statistics
import sys
import tempfile
import time
from datetime import timedelta
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fastapi.testclient import TestClient
from sqlalchemy import insert

from app.main import create_app
from app.models import Inspection, Plate, utcnow
from app.settings import Settings
from tests.yard import servers
from tests.yard.cluster import Yard


def throughput(pg, redis, *, workers: int, jobs: int, size: tuple[int, int], lights: int) -> float:
    """Inspections per minute with ``workers`` worker processes."""
    name = pg.create_database()
    redis.flush()
    with tempfile.TemporaryDirectory(prefix="bench-yard-") as tmp:
        yard = Yard(Path(tmp) / "data", database_url=pg.url(name), queue_url=redis.url(0))
        try:
            yard.start_server()
            for _ in range(workers):
                yard.start_worker()
            sim = {"n_lights": lights, "width": size[0], "height": size[1]}
            t0 = time.monotonic()
            ids = [yard.submit(f"B-{i}", sim) for i in range(jobs)]
            bodies = yard.wait_all(ids, timeout_s=3600)
            elapsed = time.monotonic() - t0
        finally:
            yard.stop()
    failed = [b["error"] for b in bodies if b["status"] != "done"]
    if failed:
        raise SystemExit(f"jobs failed: {failed}")
    pg.drop_database(name)
    return jobs / elapsed * 60.0


def fill(session_factory, rows: int, plates: int) -> None:
    """``rows`` done inspections over ``plates`` plates, in one transaction."""
    now = utcnow()
    doc = {"format": "plate-result/1", "verdict": "pass", "radius_mm": 5001.0, "warnings": []}
    with session_factory() as s:
        s.execute(insert(Plate), [{"id": f"H-{p}", "created_at": now} for p in range(plates)])
        s.execute(
            insert(Inspection),
            [
                {
                    "plate_id": f"H-{i % plates}",
                    "source": "simulated",
                    "status": "done",
                    "progress": 1.0,
                    "attempts": 1,
                    "deaths": 0,
                    "verdict": "pass",
                    "result": doc,
                    "radius_mm": 5000.0 + i % 7,
                    "created_at": now - timedelta(seconds=rows - i),
                    "queued_at": now - timedelta(seconds=rows - i),
                }
                for i in range(rows)
            ],
        )
        s.commit()


def history_latency(database_url: str | None, *, rows: int, plates: int, reads: int) -> dict:
    """p50 / p95 of GET /plates/{id}/inspections and GET /inspections (20 per page), ms."""
    with tempfile.TemporaryDirectory(prefix="bench-yard-") as tmp:
        settings = Settings(data_dir=Path(tmp), database_url=database_url, api_token="x" * 20)
        app = create_app(settings)
        fill(app.state.session_factory, rows, plates)
        rng = random.Random(0)
        out = {}
        with TestClient(app) as client:
            for label, url in (
                (
                    "plate history",
                    lambda: f"/api/v1/plates/H-{rng.randrange(plates)}/inspections?limit=20",
                ),
                (
                    "all, paged",
                    lambda: f"/api/v1/inspections?limit=20&offset={rng.randrange(rows - 20)}",
                ),
            ):
                client.get(url())  # warm the pool and the caches
                times = []
                for _ in range(reads):
                    t0 = time.perf_counter()
                    r = client.get(url())
                    times.append((time.perf_counter() - t0) * 1000.0)
                    assert r.status_code == 200, r.text
                times.sort()
                out[label] = (statistics.median(times), times[int(0.95 * (len(times) - 1))])
        app.state.engine.dispose()
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, default=8)
    parser.add_argument("--size", default="320x256")
    parser.add_argument("--lights", type=int, default=6)
    parser.add_argument("--rows", type=int, default=10_000)
    parser.add_argument("--plates", type=int, default=500)
    parser.add_argument("--reads", type=int, default=300)
    args = parser.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))
    with servers.running_postgres(durable=True) as pg, servers.running_redis() as redis:
        print(
            f"| workers | inspections/min ({args.jobs} jobs, {args.size}, {args.lights} lights) |"
        )
        print("|---|---|")
        for workers in (1, 2):
            rate = throughput(
                pg, redis, workers=workers, jobs=args.jobs, size=size, lights=args.lights
            )
            print(f"| {workers} | {rate:.1f} |", flush=True)
        name = pg.create_database()
        results = {
            "SQLite": history_latency(None, rows=args.rows, plates=args.plates, reads=args.reads),
            "PostgreSQL": history_latency(
                pg.url(name), rows=args.rows, plates=args.plates, reads=args.reads
            ),
        }
    print()
    print(f"| database ({args.rows} inspections, {args.plates} plates) | read | p50 ms | p95 ms |")
    print("|---|---|---|---|")
    for db, reads in results.items():
        for label, (p50, p95) in reads.items():
            print(f"| {db} | {label} | {p50:.1f} | {p95:.1f} |")


if __name__ == "__main__":
    main()
