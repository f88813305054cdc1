"""What the binding costs per frame: the wall time of `Pipeline.frame` seen from Python against
the time the Rust pipeline measures inside the same call (`Frame.timings["total_ms"]`), on the
column scene's splash frame (2,880 particles) and on a larger block of particles.

    python python/benches/overhead.py [--repeat 15] [--json]

The difference is the binding: checking and copying the arrays in, releasing and taking back the
GIL, and handing the results to NumPy.
"""

import argparse
import json
import platform
import statistics
import time

import numpy as np

import fluid_surfels as fs


def measure(pipeline, positions, ids, through, repeat):
    walls, inner = [], []
    for _ in range(repeat):
        t = time.perf_counter()
        frame = pipeline.frame(positions, ids, through=through)
        walls.append((time.perf_counter() - t) * 1e3)
        inner.append(frame.timings["total_ms"])
    over = [w - i for w, i in zip(walls, inner)]
    return {
        "particles": len(positions),
        "through": through,
        "wall_ms_median": statistics.median(walls),
        "rust_ms_median": statistics.median(inner),
        "overhead_ms_median": statistics.median(over),
        "overhead_fraction": statistics.median(over) / statistics.median(walls),
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=15)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()

    rows = []
    frames = fs.column_frames(14)
    pipeline = fs.Pipeline(**fs.column_params())
    for d in frames[:-1]:
        pipeline.frame(d["positions"], d["ids"], through="surface")
    last = frames[-1]
    for through in ("surface", "surfels"):
        rows.append(measure(pipeline, last["positions"], last["ids"], through, args.repeat))

    # a jittered block of 100,000 particles (spacing 0.05): the copy in grows with N
    rng = np.random.default_rng(1)
    grid = np.stack(np.meshgrid(*[np.arange(n) for n in (50, 40, 50)], indexing="ij"), -1)
    block = (grid.reshape(-1, 3) + rng.uniform(-0.05, 0.05, (100_000, 3))) * 0.05
    block = block.astype(np.float32)
    ids = np.arange(len(block), dtype=np.uint32)
    pipeline = fs.Pipeline(support_radius=0.1)
    rows.append(measure(pipeline, block, ids, "surface", max(3, args.repeat // 3)))

    report = {"machine": f"{platform.machine()}, {platform.python_implementation()} "
                         f"{platform.python_version()}", "rows": rows}
    if args.json:
        print(json.dumps(report, indent=2))
        return
    print(f"binding overhead per frame ({report['machine']}), medians of {args.repeat} runs")
    for r in rows:
        print(f"  {r['particles']:>7} particles through {r['through']:<8} wall {r['wall_ms_median']:8.2f} ms, "
              f"Rust {r['rust_ms_median']:8.2f} ms, overhead {r['overhead_ms_median']:6.3f} ms "
              f"({100 * r['overhead_fraction']:.2f} %)")


if __name__ == "__main__":
    main()
