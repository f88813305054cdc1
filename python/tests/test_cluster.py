"""A sequence over a Dask cluster (issue 39): chunks with the plan and a warm-up draw the serial
run's PNGs byte for byte, a corrupt frame is reported while the others are written, and a worker
killed in the middle of the run costs no frame and leaves no partial one."""

import os
import signal
import threading
import time
from pathlib import Path

import pytest

import fluid_surfels as fs
from conftest import extra

distributed = extra("distributed", "'fluid_surfels[dask]'")
from fluid_surfels import cluster  # noqa: E402

PARAMS = dict(fs.column_params())
PARAMS["optics"] = {**PARAMS.get("optics", {}), "image_size": [64, 48]}


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """24 frames of the column scene as VTK files, and the serial run's PNGs (one chunk)."""
    d = tmp_path_factory.mktemp("column")
    for f, s in enumerate(fs.column_frames(23)):
        fs.write(d / f"c_{f}.vtk", s["positions"], ids=s["ids"])
    pattern = str(d / "c_{}.vtk")
    serial = d / "serial"
    r = fs.render_chunk(pattern, list(range(24)), serial, params=PARAMS)
    assert r["written"] == list(range(24)) and not r["failed"], r
    return pattern, serial


@pytest.fixture(scope="module")
def client():
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as c, distributed.Client(c) as cl:
        yield cl


def pngs(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.glob("frame_*.png"))}


def test_chunks_draw_the_serial_frames(frames, client, tmp_path):
    pattern, serial = frames
    r = cluster.render_sequence(pattern, range(24), tmp_path, client, chunk=8, progress=False, **PARAMS)
    assert r["written"] == list(range(24)) and r["chunks"] == 3 and not r["failed"], r
    assert pngs(tmp_path) == pngs(serial)
    # a rerun keeps every frame
    again = cluster.render_sequence(pattern, range(24), tmp_path, client, chunk=8, progress=False, **PARAMS)
    assert again["skipped"] == list(range(24)) and not again["written"]


def test_a_corrupt_frame_is_reported_and_the_others_written(frames, client, tmp_path):
    pattern, serial = frames
    src = Path(pattern.replace("{}", "0")).parent
    bad = tmp_path / "in"
    bad.mkdir()
    for f in range(24):
        (bad / f"c_{f}.vtk").write_bytes((src / f"c_{f}.vtk").read_bytes())
    (bad / "c_10.vtk").write_bytes(b"# vtk DataFile Version 3.0\nnot a particle file\n")
    out = tmp_path / "out"
    r = cluster.render_sequence(str(bad / "c_{}.vtk"), range(24), out, client, chunk=8, progress=False, **PARAMS)
    assert [f for f, _ in r["failed"]] == [10], r
    assert "c_10.vtk" in r["failed"][0][1]
    assert r["written"] == [f for f in range(24) if f != 10]
    # the frames before the bad one are the serial run's
    written = pngs(out)
    assert "frame_0010.png" not in written
    assert all(written[n] == b for n, b in pngs(serial).items() if n < "frame_0010.png")


def test_a_killed_worker_costs_no_frame(frames, tmp_path):
    pattern, serial = frames
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as c, distributed.Client(c) as cl:
        result = {}

        def run():
            result["r"] = cluster.render_sequence(pattern, range(24), tmp_path, cl, chunk=12, progress=False, **PARAMS)

        t = threading.Thread(target=run)
        t.start()
        # once the first frames are written, kill every worker process (the nannies restart
        # them; Dask runs their tasks again)
        deadline = time.time() + 120
        while not list(tmp_path.glob("frame_*.png")) and time.time() < deadline:
            time.sleep(0.05)
        killed = 0
        for pid in cl.run(os.getpid).values():
            os.kill(pid, signal.SIGKILL)
            killed += 1
        t.join(300)
        assert not t.is_alive()
    r = result["r"]
    assert killed == 2
    assert not r["failed"], r
    assert sorted(r["written"] + r["skipped"]) == list(range(24))
    # the killed tasks ran again: the frames they had written were kept (and warmed up on)
    assert r["skipped"], r
    # every frame whole and the serial run's; no temporary file under a frame's name
    assert pngs(tmp_path) == pngs(serial)
