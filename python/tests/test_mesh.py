"""Meshes out to other tools (issue 40): the frame's mesh with velocities, written as PLY,
OBJ, legacy VTK, VTK XML and USD, and read back by meshio (PLY, OBJ, VTK XML), usd-core (the
USD stage and its value clips) and fluid_surfels' own reader (PLY, VTK: meshio 5.3 reads legacy
VTK only as UNSTRUCTURED_GRID, and this writer writes the POLYDATA that ParaView, VTK and
Houdini take for polygon meshes; the .vtu unstructured grid is the VTK file meshio reads)."""

import numpy as np
import pytest

import fluid_surfels as fs
from conftest import extra


@pytest.fixture(scope="module")
def meshes():
    """The column's frames 0, 6 and 12 through the chain, meshed with velocities."""
    frames = fs.column_frames(12)
    p = fs.Pipeline(**fs.column_params())
    out = []
    for f in (0, 6, 12):
        d = frames[f]
        m = p.frame(d["positions"], ids=d["ids"], velocities=d["velocities"], mesh=True).mesh
        out.append((f, d, m))
    return out


def test_the_mesh_carries_the_particles_velocities(meshes):
    """Interpolated with the normalised SPH kernel: finite, one per vertex, and within the
    particles' range of speeds (a normalised mean never leaves it)."""
    for f, d, m in meshes:
        assert m.velocities is not None and m.velocities.shape == m.vertices.shape
        assert np.isfinite(m.velocities).all()
        top = np.linalg.norm(d["velocities"], axis=1).max()
        assert np.linalg.norm(m.velocities, axis=1).max() <= top * (1 + 1e-4) + 1e-6, f
    # the splash's surface moves up on average, as its particles do
    _, d, m = meshes[2]
    assert m.velocities[:, 1].mean() > 0 and d["velocities"][:, 1].mean() > 0
    # a uniform flow comes out exactly (the kernel sum is normalised); without velocities, none
    d = meshes[0][1]
    p = fs.Pipeline(**fs.column_params())
    flow = np.tile(np.float32([0.3, -0.2, 1.0]), (d["positions"].shape[0], 1))
    m = p.frame(d["positions"], ids=d["ids"], velocities=flow, mesh=True).mesh
    np.testing.assert_allclose(m.velocities, np.broadcast_to(flow[0], m.velocities.shape), atol=1e-5)
    assert p.frame(d["positions"], ids=d["ids"], mesh=True).mesh.velocities is None


def test_ply_and_obj_read_back_by_meshio(meshes, tmp_path):
    meshio = extra("meshio", "meshio")
    _, _, m = meshes[1]
    fs.write_mesh(tmp_path / "m.ply", m.vertices, m.faces, velocities=m.velocities)
    back = meshio.read(tmp_path / "m.ply")
    np.testing.assert_array_equal(back.points, m.vertices)
    np.testing.assert_array_equal(back.cells_dict["triangle"], m.faces)
    got = np.stack([back.point_data[k] for k in ("vx", "vy", "vz")], axis=1)
    np.testing.assert_array_equal(got, m.velocities)
    fs.write_mesh(tmp_path / "m.obj", m.vertices, m.faces)
    back = meshio.read(tmp_path / "m.obj")
    np.testing.assert_allclose(back.points, m.vertices, rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(back.cells_dict["triangle"], m.faces)


def test_vtu_read_back_by_meshio(meshes, tmp_path):
    """The VTK XML unstructured grid of triangles: points, triangles, normals and velocities."""
    meshio = extra("meshio", "meshio")
    _, _, m = meshes[1]
    fs.write_mesh(tmp_path / "m.vtu", m.vertices, m.faces, velocities=m.velocities)
    back = meshio.read(tmp_path / "m.vtu")
    np.testing.assert_array_equal(back.points, m.vertices)
    np.testing.assert_array_equal(back.cells_dict["triangle"], m.faces)
    np.testing.assert_array_equal(back.point_data["velocity"], m.velocities)
    normals = back.point_data["Normals"]
    assert normals.shape == m.vertices.shape
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)


def test_ply_and_vtk_read_back_by_our_reader(meshes, tmp_path):
    _, _, m = meshes[1]
    for ext in ("ply", "vtk"):
        path = tmp_path / f"m.{ext}"
        fs.write_mesh(path, m.vertices, m.faces, velocities=m.velocities)
        back = fs.read_mesh(path)
        np.testing.assert_array_equal(back.vertices, m.vertices)
        np.testing.assert_array_equal(back.faces, m.faces)
        np.testing.assert_array_equal(back.velocities, m.velocities)
        assert back.closed and back.euler_characteristic == m.euler_characteristic
    with pytest.raises(ValueError, match=".ply or .vtk"):
        fs.read_mesh(tmp_path / "m.obj")
    with pytest.raises(ValueError, match="time"):
        fs.write_mesh(tmp_path / "t.ply", m.vertices, m.faces, time=1.0)


def test_a_usd_stage_plays_the_frames(meshes, tmp_path):
    """One .usda a frame (time samples at its frame) and a stage of value clips: usd-core
    opens it, the clips resolve, and at each frame's time the mesh has that frame's points,
    faces, normals and velocities."""
    extra("pxr", "usd-core")
    from pxr import Usd, UsdGeom

    frames = []
    for f, _, m in meshes:
        path = tmp_path / f"water_{f:04}.usda"
        fs.write_mesh(path, m.vertices, m.faces, velocities=m.velocities, time=float(f))
        frames.append((float(f), path))
    stage_path = tmp_path / "water.usda"
    fs.write_usd_stage(stage_path, frames, fps=30.0)
    with pytest.raises(FileExistsError):
        fs.write_usd_stage(stage_path, frames)
    stage = Usd.Stage.Open(str(stage_path))
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0.0, 12.0)
    assert stage.GetTimeCodesPerSecond() == 30.0
    clips = Usd.ClipsAPI(stage.GetPrimAtPath("/fluid"))
    resolved = [a.resolvedPath for a in clips.GetClipAssetPaths()]
    assert resolved == [str(p) for _, p in frames]
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/fluid/surface"))
    assert mesh.GetNormalsInterpolation() == "vertex"
    for f, _, m in meshes:
        points = np.array(mesh.GetPointsAttr().Get(f))
        np.testing.assert_allclose(points, m.vertices, rtol=1e-6, atol=1e-6)
        indices = np.array(mesh.GetFaceVertexIndicesAttr().Get(f)).reshape(-1, 3)
        np.testing.assert_array_equal(indices, m.faces)
        assert set(mesh.GetFaceVertexCountsAttr().Get(f)) == {3}
        assert len(mesh.GetNormalsAttr().Get(f)) == len(points)
        np.testing.assert_allclose(
            np.array(mesh.GetVelocitiesAttr().Get(f)), m.velocities, rtol=1e-6, atol=1e-6
        )
    # between two frames the earlier one holds
    assert len(mesh.GetPointsAttr().Get(3.0)) == meshes[0][2].vertices.shape[0]
    # a lone .usda without time: default values, as Blender imports a single file
    _, _, m = meshes[0]
    fs.write_mesh(tmp_path / "still.usda", m.vertices, m.faces)
    lone = Usd.Stage.Open(str(tmp_path / "still.usda"))
    still = UsdGeom.Mesh(lone.GetPrimAtPath("/fluid/surface"))
    assert len(still.GetPointsAttr().Get()) == m.vertices.shape[0]
    assert len(still.GetVelocitiesAttr().Get() or []) == 0
