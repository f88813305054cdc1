"""A long sequence over a cluster, with Dask (`pip install "fluid_surfels[dask]"`).

    from fluid_surfels.cluster import render_sequence
    report = render_sequence("sim/f_{}.vtk", range(0, 10_000), "out/", chunk=50,
                             support_radius=0.1, optics={"image_size": [1280, 720]})

Frames are nearly independent, but a sequence carries state: the support radius and the views
fitted on its first frame (camera, pool, scene box, the light's resolutions), and surface
detection's hysteresis. So the sequence's plan is made once, from the range's first frame
(`plan_of`, one task), and handed to every chunk; each chunk is one Dask task that runs a
pipeline over its contiguous frames after a warm-up on the frames just before them
(`render_chunk`: detection alone, `DEFAULT_WARMUP` frames), and writes each finished frame to
`out/frame_NNNN.png` atomically (shared storage). On the column scene a chunk then draws the
serial run's PNGs byte for byte (docs/python.md).

Any Dask cluster works: a `LocalCluster` (made here when no client is given: one worker process
per core, one thread each), SSH, Kubernetes (dask-kubernetes) or Slurm (dask-jobqueue); give its
`distributed.Client`. A task whose worker dies is run again by Dask (`retries` for errors); a
frame whose file is bad is reported with its error and the other frames are written; a rerun
with `skip_existing` (the default) draws only the frames whose PNG is missing.
"""

from __future__ import annotations

import math
import os
import sys
import time
import uuid
from pathlib import Path
from typing import Any, Iterable, Optional

from . import _native

DEFAULT_WARMUP = 8
"""Frames a chunk warms up on (`pipeline::DEFAULT_WARMUP`): on the column scene every chunk's
classes agree with the serial run's after at most 7."""


def _distributed() -> Any:
    try:
        import distributed
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError(
            "fluid_surfels.cluster needs Dask's distributed scheduler: "
            'pip install "fluid_surfels[dask]" (or: pip install "dask[distributed]")'
        ) from e
    return distributed


def _plan(pattern: str, first: int, params: dict[str, Any]) -> dict[str, Any]:
    return _native.plan_of(pattern, first, params)


def _chunk(
    pattern: str,
    frames: list[int],
    out: str,
    warmup: list[int],
    plan: dict[str, Any],
    params: dict[str, Any],
    skip_existing: bool,
) -> dict[str, Any]:
    report = _native.render_chunk(
        pattern,
        frames,
        out,
        warmup=warmup,
        plan=plan,
        params=params,
        skip_existing=skip_existing,
    )
    report["frames"] = list(frames)
    report["worker_pid"] = os.getpid()
    return report


def chunks(frames: list[int], chunk: int, warmup: int) -> list[tuple[list[int], list[int]]]:
    """The contiguous chunks of `chunk` frames, each with the (at most `warmup`) frames of the
    sequence just before it to warm up on."""
    if chunk < 1:
        raise ValueError(f"chunk must be at least 1, got {chunk}")
    if warmup < 0:
        raise ValueError(f"warmup must be at least 0, got {warmup}")
    return [
        (frames[max(0, i - warmup) : i], frames[i : i + chunk])
        for i in range(0, len(frames), chunk)
    ]


def render_sequence(
    pattern: str,
    frames: Iterable[int],
    out: "str | os.PathLike[str]",
    client: Optional[Any] = None,
    chunk: Optional[int] = None,
    warmup: Optional[int] = None,
    *,
    skip_existing: bool = True,
    retries: int = 2,
    progress: bool = True,
    **params: Any,
) -> dict[str, Any]:
    """Renders the finished frames of `frames` of the files `pattern` (holding `{}` for the
    frame number) into `out/frame_NNNN.png`, one Dask task per chunk of `chunk` frames (default:
    three chunks per thread of the cluster), each warmed up on the `warmup` frames before
    it (default `DEFAULT_WARMUP`) with the plan of the first frame. `params` are the
    `Pipeline`'s. Returns a report: `written`, `skipped`, `failed` ([frame, error] pairs; a
    chunk whose task failed for good lists each of its frames), `chunks`, `seconds`, and per
    task its frames, seconds and worker."""
    distributed = _distributed()
    frames = [int(f) for f in frames]
    if not frames:
        raise ValueError("no frame to render")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    warmup = DEFAULT_WARMUP if warmup is None else int(warmup)
    own = None
    if client is None:
        own = distributed.LocalCluster(
            n_workers=os.cpu_count() or 1, threads_per_worker=1, processes=True
        )
        client = distributed.Client(own)
    try:
        if chunk is None:
            # three chunks per worker thread: chunks of uneven cost even out (measured with
            # python/benches/cluster.py, 48 column frames at 320x240, 2 workers of one thread
            # against 1: one chunk each 1.67-1.74x, three each 1.83x)
            threads = sum(client.nthreads().values()) or 1
            chunk = math.ceil(len(frames) / (3 * threads))
        parts = chunks(frames, chunk, warmup)
        start = time.perf_counter()
        run = uuid.uuid4().hex[:8]
        plan = client.submit(
            _plan, pattern, frames[0], params, key=f"fluid-surfels-plan-{run}", retries=retries
        )
        tasks = {
            client.submit(
                _chunk,
                pattern,
                part,
                str(out),
                warm,
                plan,
                params,
                skip_existing,
                key=f"fluid-surfels-chunk-{run}-{k}",
                retries=retries,
            ): part
            for k, (warm, part) in enumerate(parts)
        }
        report: dict[str, Any] = {
            "written": [],
            "skipped": [],
            "failed": [],
            "warmup_failed": [],
            "chunks": len(parts),
            "tasks": [],
        }
        done = 0
        for future in distributed.as_completed(list(tasks)):
            part = tasks[future]
            try:
                r = future.result()
            except Exception as e:  # the task failed for good: each of its frames is reported
                report["failed"].extend([f, f"{type(e).__name__}: {e}"] for f in part)
            else:
                for key in ("written", "skipped", "failed", "warmup_failed"):
                    report[key].extend(r[key])
                report["tasks"].append(
                    {"frames": [part[0], part[-1]], "seconds": r["seconds"], "worker_pid": r["worker_pid"]}
                )
            done += len(part)
            if progress:
                print(f"fluid-surfels: {done}/{len(frames)} frames", file=sys.stderr, flush=True)
        for key in ("written", "skipped"):
            report[key].sort()
        report["failed"].sort()
        report["seconds"] = time.perf_counter() - start
        return report
    finally:
        if own is not None:
            client.close()
            own.close()
