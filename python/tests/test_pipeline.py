"""The Python pipeline against the Rust pipeline (through the command line built from the same
sources), across frames, and on bad input."""

import threading
import time

import numpy as np
import pytest

import fluid_surfels as fs
from conftest import DAM_BREAK, DATA
from png import read_png


def surface_ids(frame, ids):
    return set(ids[frame.classes == fs.SURFACE].tolist())


def run_column(pipeline, frames, last_through="surfels", order=None):
    """Every frame through surface detection (the hysteresis of a real run), the last one
    through `last_through`; `order(k, n)` permutes frame k's particles."""
    result = []
    for k, d in enumerate(frames):
        pos, ids = d["positions"], d["ids"]
        if order is not None:
            perm = order(k, len(ids))
            pos, ids = pos[perm], ids[perm]
        through = last_through if k == len(frames) - 1 else "surface"
        result.append((pipeline.frame(pos, ids, through=through), ids))
    return result


def test_column_matches_the_main_job(cli, column, tmp_path):
    """Classes, refined points and surfels of the splash frame equal the main job's files (the
    Rust Pipeline on the same simulation), exactly."""
    cli("run", "--out-dir", tmp_path)
    frame, ids = run_column(fs.Pipeline(**fs.column_params()), column)[-1]
    surface = fs.read(tmp_path / "surface.ply")
    assert surface_ids(frame, ids) == set(surface["ids"].tolist())
    refined = fs.read(tmp_path / "refined.ply")
    assert frame.refined is not None and len(frame.refined) == len(refined["positions"])
    np.testing.assert_array_equal(frame.refined.positions, refined["positions"])
    np.testing.assert_array_equal(frame.refined.normals, refined["normals"])
    np.testing.assert_array_equal(frame.refined.steps, refined["attributes"]["step"])
    surfels = fs.read(tmp_path / "surfels.ply")
    assert frame.surfels is not None and len(frame.surfels) > 1000
    np.testing.assert_array_equal(frame.surfels.positions, surfels["positions"])
    np.testing.assert_array_equal(frame.surfels.normals, surfels["normals"])
    np.testing.assert_array_equal(frame.surfels.radii, surfels["attributes"]["radius"])
    # the timings and the report
    assert frame.timings["total_ms"] > 0 and frame.timings["refine_ms"] > 0
    # what the level of detail made (through the surfels: no camera, so fixed)
    assert frame.timings["detail"] == "fixed" and frame.timings["steps"] == 3
    assert frame.timings["refined_points"] == len(frame.refined)
    assert frame.timings["points_per_level"] == [0, 0, 0, len(frame.refined)]
    assert frame.timings["surfels"] == len(frame.surfels) and frame.timings["cell"] > 0
    # a frame without a picture keeps every surfel
    assert frame.timings["hidden_surfels"] == 0
    assert frame.image is None and frame.radius == fs.column_params()["support_radius"]


@pytest.mark.repository
def test_real_file_matches_the_command_line(cli, tmp_path):
    """On a SPlisHSPlasH file read with fluid_surfels.read: the same surface particles, refined
    points and rendered surfels as detect, refine and render --save-surfels."""
    cli("detect", "--input", DAM_BREAK, "--out", tmp_path / "surface.ply")
    cli("refine", "--input", DAM_BREAK, "--out", tmp_path / "refined.ply")
    cli("render", "--input", DAM_BREAK, "--cpu", "--size", "64x48",
        "--save-surfels", tmp_path / "surfels.ply", "--out", tmp_path / "splats.png")
    d = fs.read(DAM_BREAK)
    assert d["positions"].shape == (4732, 3) and d["positions"].dtype == np.float32
    frame = fs.Pipeline().frame(d["positions"], d["ids"], d["velocities"])
    assert surface_ids(frame, d["ids"]) == set(fs.read(tmp_path / "surface.ply")["ids"].tolist())
    refined = fs.read(tmp_path / "refined.ply")
    np.testing.assert_array_equal(frame.refined.positions, refined["positions"])
    surfels = fs.read(tmp_path / "surfels.ply")
    assert len(frame.surfels) == len(surfels["positions"]) > 1000
    np.testing.assert_array_equal(frame.surfels.positions, surfels["positions"])
    np.testing.assert_array_equal(frame.surfels.radii, surfels["attributes"]["radius"])


@pytest.mark.repository
def test_render_equals_the_command_lines_png(cli, column, tmp_path):
    """The finished frame as an array equals render's PNG of the same frame, byte for byte: the
    column splash frame (its pool and camera) and the real file (a fitted pool)."""
    cli("render", "--scene", "column", "--frame", "14", "--optics", "--cpu",
        "--size", "96x72", "--out", tmp_path / "column.png")
    params = fs.column_params()
    params["optics"]["image_size"] = [96, 72]
    pipeline = fs.Pipeline(**params)
    run_column(pipeline, column[:-1], last_through="surface")
    last = column[-1]
    image = pipeline.render(last["positions"], last["ids"])
    assert image.shape == (72, 96, 4) and image.dtype == np.uint8
    np.testing.assert_array_equal(image, read_png(tmp_path / "column.png"))

    cli("render", "--input", DAM_BREAK, "--optics", "--cpu", "--size", "80x60",
        "--out", tmp_path / "ddb.png")
    d = fs.read(DAM_BREAK)
    image = fs.Pipeline(optics={"image_size": (80, 60)}).render(d["positions"], d["ids"])
    np.testing.assert_array_equal(image, read_png(tmp_path / "ddb.png"))
    # the shaded splats: through the frame object as well
    cli("render", "--input", DAM_BREAK, "--cpu", "--size", "64x48",
        "--out", tmp_path / "splats.png")
    frame = fs.Pipeline(optics={"image_size": [64, 48]}).frame(d["positions"], through="splats")
    np.testing.assert_array_equal(frame.image, read_png(tmp_path / "splats.png"))


def test_hysteresis_follows_the_ids_when_the_order_changes(column):
    """Shuffling every frame's particles changes no class (matched by id) and no flip count;
    without ids the same shuffles do change classes, so the ids are what carries the state."""
    rng = np.random.default_rng(7)
    perms = {}

    def shuffled(k, n):
        return perms.setdefault(k, rng.permutation(n))

    plain = run_column(fs.Pipeline(**fs.column_params()), column, "refine")
    mixed = run_column(fs.Pipeline(**fs.column_params()), column, "refine", order=shuffled)
    flips = 0
    for (a, ids_a), (b, ids_b) in zip(plain, mixed):
        by_id = dict(zip(ids_b.tolist(), b.classes.tolist()))
        assert [by_id[i] for i in ids_a.tolist()] == a.classes.tolist()
        assert a.flips == b.flips
        flips += a.flips
    assert flips > 0, "the column's frames flip some particles: the hysteresis is exercised"
    # (the refined points are not compared: the upsampling's collision handling keeps the
    # first of two colliding candidates, so its output depends on the order of the input)

    # without ids the state sticks to positions in the array, which the shuffles move
    blind = fs.Pipeline(**fs.column_params())
    differs = 0
    for k, d in enumerate(column):
        perm = shuffled(k, len(d["ids"]))
        f = blind.frame(d["positions"][perm], through="surface")
        by_id = dict(zip(d["ids"][perm].tolist(), f.classes.tolist()))
        ref = plain[k][0].classes.tolist()
        differs += sum(by_id[i] != c for i, c in zip(column[k]["ids"].tolist(), ref))
    assert differs > 0


def test_a_sequence_in_a_loop_equals_the_command_lines(cli, column, tmp_path):
    """The README's loop: frames rendered one after the other by one pipeline (hysteresis,
    camera and pool kept) equal render --frames, frame by frame."""
    cli("render", "--scene", "column", "--frames", "12..=14", "--cpu", "--size", "48x36",
        "--out", tmp_path)
    params = fs.column_params()
    params["optics"]["image_size"] = [48, 36]
    pipeline = fs.Pipeline(**params)
    run_column(pipeline, column[:12], last_through="surface")
    images = [pipeline.render(d["positions"], d["ids"]) for d in column[12:15]]
    assert not np.array_equal(images[0], images[2]), "the water moves"
    for k, image in zip(range(12, 15), images):
        np.testing.assert_array_equal(image, read_png(tmp_path / f"frame_{k:04}.png"), err_msg=k)


@pytest.mark.repository
def test_non_contiguous_and_float64_arrays_give_the_same_result():
    d = fs.read(DAM_BREAK)
    pos = d["positions"]
    ref = fs.Pipeline(support_radius=0.1).frame(pos, d["ids"], through="refine")
    wide = np.zeros((len(pos), 7), dtype=np.float32)
    wide[:, 2:5] = pos
    fortran = np.asfortranarray(pos)
    # unaligned: float32 values at an odd byte offset of a buffer
    raw = bytearray(pos.nbytes + 1)
    unaligned = np.frombuffer(raw, dtype=np.float32, offset=1).reshape(-1, 3)
    assert not unaligned.flags.aligned
    np.copyto(unaligned, pos)
    ids_raw = bytearray(d["ids"].nbytes + 1)
    unaligned_ids = np.frombuffer(ids_raw, dtype=np.uint32, offset=1)
    np.copyto(unaligned_ids, d["ids"])
    variants = [(wide[:, 2:5], d["ids"]), (fortran, d["ids"].astype(np.int64)),
                (pos.astype(np.float64), d["ids"][::-1].copy()[::-1]),
                (pos[::-1][::-1], d["ids"].astype(np.int16 if len(pos) < 32768 else np.int32)),
                (unaligned, unaligned_ids)]
    for positions, ids in variants:
        f = fs.Pipeline(support_radius=0.1).frame(positions, ids, through="refine")
        np.testing.assert_array_equal(f.classes, ref.classes)
        np.testing.assert_array_equal(f.refined.positions, ref.refined.positions)


@pytest.mark.repository
def test_masses_weigh_the_centre_of_mass():
    d = fs.read(DAM_BREAK)
    pos = d["positions"]
    ref = fs.Pipeline(support_radius=0.1).frame(pos, through="surface")
    ones = fs.Pipeline(support_radius=0.1).frame(pos, masses=np.ones(len(pos)), through="surface")
    np.testing.assert_array_equal(ones.classes, ref.classes)
    heavy_top = np.where(pos[:, 1] > np.median(pos[:, 1]), 10.0, 1.0).astype(np.float32)
    weighed = fs.Pipeline(support_radius=0.1).frame(pos, masses=heavy_top, through="surface")
    assert (weighed.classes != ref.classes).sum() > 10
    with pytest.raises(ValueError, match="`masses` has 3 rows"):
        fs.Pipeline().frame(pos, masses=np.ones(3))
    with pytest.raises(ValueError, match="`masses` must have dtype float32 or float64, got float16"):
        fs.Pipeline().frame(pos, masses=np.ones(len(pos), np.float16))


@pytest.mark.repository
def test_bad_input_raises_clear_exceptions():
    p = fs.Pipeline(support_radius=0.1)
    good = np.zeros((10, 3), dtype=np.float32)
    cases = [
        (lambda: p.frame(np.zeros((10, 2), np.float32)), ValueError, r"shape \(N, 3\), got shape \(10, 2\)"),
        (lambda: p.frame(np.zeros(3, np.float32)), ValueError, r"got shape \(3,\)"),
        (lambda: p.frame(np.zeros((4, 3, 1), np.float32)), ValueError, r"got shape \(4, 3, 1\)"),
        (lambda: p.frame(np.zeros((10, 3), np.float16)), ValueError, "float32 or float64, got float16"),
        (lambda: p.frame(np.zeros((10, 3), np.int64)), ValueError, "got int64"),
        (lambda: p.frame([[0.0, 0.0, 0.0]]), ValueError, "must be a NumPy array.*got a list"),
        (lambda: p.frame(good, ids=np.arange(9)), ValueError, "`ids` has 9 rows but there are 10"),
        (lambda: p.frame(good, ids=np.arange(10) - 1), ValueError, r"`ids`\[0\] is -1"),
        (lambda: p.frame(good, ids=np.zeros(10, np.float32)), ValueError, "integer dtype"),
        (lambda: p.frame(np.random.default_rng(0).random((10, 3)), ids=np.zeros(10, np.uint32)),
         fs.Error, "(?i)id 0"),
        (lambda: p.frame(good, velocities=np.zeros((10, 4))), ValueError, "`velocities` must have shape"),
        (lambda: p.frame(good, through="everything"), ValueError, "`through` must be one of"),
        (lambda: p.render(good, image="depth"), ValueError, "`image` must be"),
        (lambda: fs.Pipeline(support_radius=-1.0), ValueError, "support_radius.*-1"),
        (lambda: fs.Pipeline(refine={"stpes": 2}), ValueError, "stpes"),
        (lambda: fs.Pipeline(lihgt={}), ValueError, "lihgt"),
        (lambda: fs.Pipeline(source="voxels"), ValueError, "voxels"),
        (lambda: fs.Pipeline(grid={"calibration": "volume"}), ValueError, 'source = "particles"'),
        (lambda: fs.Pipeline(optics={"image_size": [1, None]}), ValueError, r"image_size\[1\]"),
        (lambda: fs.Pipeline(optics=object()), ValueError, "`optics`: a object cannot be"),
        (lambda: fs.read("/nonexistent/particles.ply"), fs.Error, "particles.ply"),
        (lambda: fs.read(DAM_BREAK, format="stl"), ValueError, "`format` must be one of ply"),
        (lambda: fs.column_frames(10**9), fs.Error, "frame"),
    ]
    for i, (call, kind, pattern) in enumerate(cases):
        with pytest.raises(kind, match=pattern) as raised:
            call()
        assert len(str(raised.value)) < 300, (i, str(raised.value))
    nan = good.copy()
    nan[3, 1] = np.nan
    with pytest.raises(fs.Error, match="(?i)nan|finite"):
        p.frame(nan)
    with pytest.raises(fs.Error, match="(?i)finite"):
        p.frame(np.full((10, 3), 1e300))  # float64 beyond float32
    # an empty frame: no radius to estimate is an error; with a radius an empty result
    with pytest.raises(fs.Error):
        fs.Pipeline().frame(np.zeros((0, 3), np.float32))
    empty = p.frame(np.zeros((0, 3), np.float32), through="frame")
    assert empty.classes.shape == (0,) and empty.normals.shape == (0, 3)
    # the pipeline is still usable after every refusal
    assert len(p.frame(np.random.default_rng(1).random((200, 3), np.float32) * 0.3).classes) == 200


@pytest.mark.repository
def test_params_round_trip_and_files(tmp_path):
    p = fs.Pipeline(support_radius=0.05, refine={"steps": 2}, grid={"cells_per_radius": 2.5},
                    light={"direction": np.array([0.0, 1.0, 0.0])}, optics={"image_size": (64, 48)})
    params = p.params
    assert params["support_radius"] == 0.05 and params["refine"]["steps"] == 2
    assert params["optics"]["image_size"] == [64, 48] and params["light"]["direction"] == [0.0, 1.0, 0.0]
    assert fs.Pipeline(**params).params == params
    assert p.support_radius == 0.05
    defaults = fs.Pipeline()
    assert defaults.support_radius is None
    scene = tmp_path / "scene.toml"
    scene.write_text('support_radius = 0.1\nsource = "particles"\n[optics]\nimage_size = [32, 24]\n')
    q = fs.Pipeline.from_toml(scene)
    assert q.params["source"] == "particles" and q.params["optics"]["image_size"] == [32, 24]
    every = fs.Pipeline.from_toml(DAM_BREAK.parents[2] / "examples" / "scenes" / "every_key.toml")
    assert every.params == defaults.params
    with pytest.raises(ValueError, match="unknown"):
        scene.write_text("[grid]\ncells = 3\n")
        fs.Pipeline.from_toml(scene)


@pytest.mark.repository
def test_read_and_write_every_format(tmp_path):
    d = fs.read(DAM_BREAK)
    n = len(d["positions"])
    assert d["ids"].dtype == np.uint32 and d["velocities"].shape == (n, 3)
    for name in fs.FORMATS:
        path = tmp_path / f"out.{name}"
        fs.write(path, d["positions"], ids=d["ids"], velocities=d["velocities"], format=name)
        back = fs.read(path, format=name)
        np.testing.assert_allclose(back["positions"], d["positions"], rtol=1e-6, err_msg=name)
    # every array kind through PLY, attributes in their own type
    rng = np.random.default_rng(3)
    attrs = {"density": rng.random(n), "phase": np.arange(n, dtype=np.int16) % 3,
             "vorticity": rng.random((n, 3)).astype(np.float32)}
    colours = rng.integers(0, 256, (n, 3), dtype=np.uint8)
    fs.write(tmp_path / "all.ply", d["positions"], ids=d["ids"], masses=np.ones(n),
             velocities=d["velocities"], normals=d["velocities"], colours=colours, attributes=attrs)
    back = fs.read(tmp_path / "all.ply")
    np.testing.assert_array_equal(back["colours"], colours)
    np.testing.assert_array_equal(back["ids"], d["ids"])
    np.testing.assert_array_equal(back["masses"], np.ones(n, np.float32))
    for key, values in attrs.items():
        # PLY stores a vector as one property per component (key_x, key_y, key_z)
        columns = {key: values} if values.ndim == 1 else {
            f"{key}_{axis}": values[:, i] for i, axis in enumerate("xyz")}
        for name, column in columns.items():
            assert back["attributes"][name].dtype == values.dtype, name
            np.testing.assert_array_equal(back["attributes"][name], column)
    # a vector attribute stays one (N, 3) array through VTK
    fs.write(tmp_path / "all.vtk", d["positions"], attributes={"vorticity": attrs["vorticity"]})
    np.testing.assert_array_equal(fs.read(tmp_path / "all.vtk")["attributes"]["vorticity"],
                                  attrs["vorticity"])
    # nothing is overwritten silently
    before = (tmp_path / "all.ply").read_bytes()
    with pytest.raises(FileExistsError, match="overwrite=True"):
        fs.write(tmp_path / "all.ply", d["positions"])
    assert (tmp_path / "all.ply").read_bytes() == before
    fs.write(tmp_path / "all.ply", d["positions"], overwrite=True)
    assert len(fs.read(tmp_path / "all.ply")["attributes"]) == 0
    with pytest.raises(ValueError, match=r"`attributes\[\"x\"\]` must have shape \(4732,\)"):
        fs.write(tmp_path / "x.ply", d["positions"], attributes={"x": np.zeros(3)})
    with pytest.raises(ValueError, match="`colours` must have dtype uint8"):
        fs.write(tmp_path / "x.ply", d["positions"], colours=np.zeros((n, 3)))
    with pytest.raises(fs.Error, match="(?i)extension|format"):
        fs.write(tmp_path / "x.unknown", d["positions"])


@pytest.mark.repository
def test_the_gil_is_released_during_a_frame():
    """While one thread runs a frame, another thread runs Python code: with the GIL held for
    the whole frame it could not run at all between the frame's start and end."""
    d = fs.read(DAM_BREAK)
    pipeline = fs.Pipeline(support_radius=0.1)
    span = {}

    def work():
        span["start"] = time.perf_counter()
        pipeline.frame(d["positions"], through="surfels")
        span["end"] = time.perf_counter()

    ticks = []
    worker = threading.Thread(target=work)
    worker.start()
    while worker.is_alive():
        ticks.append(time.perf_counter())
    worker.join()
    inside = [t for t in ticks if span["start"] < t < span["end"]]
    # the frame takes tens of milliseconds; a released GIL lets this loop tick thousands of times
    assert len(inside) > 100, (len(inside), span["end"] - span["start"])


@pytest.mark.repository
def test_warnings_reach_pythons_warnings_module():
    """A support radius far off warns through `warnings` (UserWarning) and in Frame.warnings;
    a good one does not."""
    d = fs.read(DAM_BREAK)
    with pytest.warns(UserWarning, match="too large"):
        frame = fs.Pipeline(support_radius=0.5).frame(d["positions"], through="surface")
    assert any("too large" in w for w in frame.warnings)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert fs.Pipeline().frame(d["positions"], through="surface").warnings == []


@pytest.mark.repository
def test_the_lnm_detection_method_equals_detect_method_lnm(cli, tmp_path):
    """surface={"method": "lnm"} gives the narrow band that `detect --method lnm` writes: the
    same surface particles in the same order (the dam break BGEO, a bulk body whose band is
    not all of it), a superset of the centre-of-mass surface."""
    bgeo = DATA / "dam_break_frame_23_24389_particles.bgeo"
    cli("detect", "--input", bgeo, "--method", "lnm", "--out", tmp_path / "band.ply")
    pos = fs.read(bgeo)["positions"]
    band = fs.Pipeline(surface={"method": "lnm"}).frame(pos, through="surface")
    com = fs.Pipeline().frame(pos, through="surface")
    written = fs.read(tmp_path / "band.ply")["positions"]
    np.testing.assert_array_equal(pos[band.classes == fs.SURFACE], written)
    in_band = band.classes != fs.INTERIOR
    assert in_band[com.classes == fs.SURFACE].all() and 0 < len(written) < len(pos)


# a single layer has a third of a bulk's neighbours, which the pipeline rightly warns of
@pytest.mark.filterwarnings("ignore:support radius")
def test_the_boundary_calibration_keeps_a_sheets_thickness_at_every_level():
    """A single layer of particles (spacing 0.05) is one spacing thick at every refinement level
    with grid={"calibration": "boundary"}; with the paper's sums it is 2.5 spacings thick or more
    (issue 35)."""
    s = 0.05
    i, k = np.meshgrid(np.arange(20), np.arange(20))
    sheet = np.stack([i.ravel() * s, np.zeros(i.size), k.ravel() * s], axis=1).astype(np.float32)

    def thickness(steps, calibration):
        p = fs.Pipeline(support_radius=2 * s, refine={"steps": steps}, grid={"calibration": calibration})
        q = p.frame(sheet, through="surfels").surfels.positions
        middle = (np.abs(q[:, 0] - 0.475) < 0.2) & (np.abs(q[:, 2] - 0.475) < 0.2)
        y = q[middle, 1]
        return (np.median(y[y > 0]) - np.median(y[y < 0])) / s

    for steps in range(4):
        assert abs(thickness(steps, "boundary") - 1.0) <= 0.2, steps
    assert thickness(3, "paper") > 2.0


def test_the_mesh_of_a_frame_is_closed_and_written_back(tmp_path):
    """frame(..., mesh=True) gives the chain's mesh (issue 40): closed, its vertices the
    surfels; write_mesh writes PLY (read back by fs.read) and OBJ; bad input raises."""
    d = fs.column_frames(0)[0]
    p = fs.Pipeline(**fs.column_params())
    frame = p.frame(d["positions"], ids=d["ids"], mesh=True)
    m = frame.mesh
    assert m is not None and m.closed and len(m) == m.faces.shape[0] > 0
    assert m.euler_characteristic == 2
    assert m.faces.dtype == np.uint32 and m.faces.max() < m.vertices.shape[0]
    np.testing.assert_array_equal(m.vertices, frame.surfels.positions)
    assert p.frame(d["positions"], ids=d["ids"]).mesh is None
    through = p.frame(d["positions"], ids=d["ids"], through="mesh")
    np.testing.assert_array_equal(through.mesh.faces, m.faces)
    assert through.timings["mesh_ms"] > 0.0
    # splashsurf's field (the raw particles weighted by their SPH volumes): closed too
    v = fs.Pipeline(support_radius=p.support_radius, source="particles", grid={"calibration": "volume"})
    vm = v.frame(d["positions"], through="mesh").mesh
    assert vm.closed and len(vm) > 0
    fs.write_mesh(tmp_path / "m.ply", m.vertices, m.faces)
    back = fs.read(tmp_path / "m.ply")
    np.testing.assert_array_equal(back["positions"], m.vertices)
    fs.write_mesh(tmp_path / "m.obj", m.vertices, m.faces)
    text = (tmp_path / "m.obj").read_text()
    assert sum(line.startswith("f ") for line in text.splitlines()) == len(m)
    with pytest.raises(FileExistsError):
        fs.write_mesh(tmp_path / "m.ply", m.vertices, m.faces)
    with pytest.raises(ValueError, match="ply"):
        fs.write_mesh(tmp_path / "m.stl", m.vertices, m.faces)
    with pytest.raises(ValueError, match="past the"):
        fs.write_mesh(tmp_path / "bad.ply", m.vertices, m.faces + m.vertices.shape[0])
