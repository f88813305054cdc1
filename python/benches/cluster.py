"""The cluster's speed-up (issue 39): a 48-frame column sequence written to files, rendered by
`fluid_surfels.cluster.render_sequence` on a LocalCluster of 1 worker of one thread, 2 workers
of one thread each, and 1 worker of two threads (the pipeline's `threads` = 2), in one run; the
ratio of the first to the second, and the overhead per task (the run's wall time against the
tasks' own).

    python python/benches/cluster.py [--size 320x240] [--frames 48] [--chunks-per-worker 3] [--json]
"""

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import distributed

import fluid_surfels as fs
from fluid_surfels import cluster


def run(pattern, frames, out, workers, threads, params, per_worker):
    with distributed.LocalCluster(
        n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None
    ) as c, distributed.Client(c) as client:
        t = time.perf_counter()
        r = cluster.render_sequence(
            pattern, range(frames), out, client, chunk=max(1, frames // (workers * per_worker)), progress=False,
            **{**params, "threads": threads},
        )
        wall = time.perf_counter() - t
    assert len(r["written"]) == frames and not r["failed"], r
    tasks = sum(x["seconds"] for x in r["tasks"])
    return {
        "workers": workers,
        "threads_per_frame": threads,
        "seconds": wall,
        "task_seconds": tasks,
        "overhead_per_task_s": (wall * workers - tasks) / len(r["tasks"]),
    }


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--frames", type=int, default=48)
    ap.add_argument("--chunks-per-worker", type=int, default=3)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    w, h = (int(x) for x in a.size.split("x"))
    params = dict(fs.column_params())
    params["optics"] = {**params.get("optics", {}), "image_size": [w, h]}
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        for f, s in enumerate(fs.column_frames(a.frames - 1)):
            fs.write(d / f"c_{f}.vtk", s["positions"], ids=s["ids"])
        pattern = str(d / "c_{}.vtk")
        rows = [
            run(pattern, a.frames, d / f"out{k}", workers, threads, params, a.chunks_per_worker)
            for k, (workers, threads) in enumerate([(1, 1), (2, 1), (1, 2)])
        ]
    report = {
        "machine": f"{platform.machine()}, {os.cpu_count()} cores",
        "frames": a.frames,
        "size": a.size,
        "runs": rows,
        "speedup_2_workers": rows[0]["seconds"] / rows[1]["seconds"],
        "speedup_1_worker_2_threads": rows[0]["seconds"] / rows[2]["seconds"],
    }
    if a.json:
        print(json.dumps(report, indent=2))
        return
    for r in rows:
        print(
            f"{r['workers']} worker(s) x {r['threads_per_frame']} thread(s): {r['seconds']:.1f} s "
            f"(overhead per task {r['overhead_per_task_s']:.2f} s)"
        )
    print(
        f"2 workers of 1 thread: {report['speedup_2_workers']:.2f}x faster than 1; "
        f"1 worker of 2 threads: {report['speedup_1_worker_2_threads']:.2f}x"
    )


if __name__ == "__main__":
    main()
