"""Type stubs of the extension module fluid_surfels._native (re-exported by fluid_surfels)."""

from os import PathLike
from typing import Any, Literal, Optional, Sequence, Union

import numpy as np
import numpy.typing as npt

__version__: str
FORMATS: list[str]
"""The file formats `read` and `write` take: ply, vtk, vtu, bgeo, xyz, xyz-raw, csv, json."""

_Path = Union[str, "PathLike[str]"]
_Points = npt.NDArray[Union[np.float32, np.float64]]
_Ids = npt.NDArray[np.integer[Any]]
_Through = Literal["surface", "refine", "surfels", "mesh", "splats", "frame"]

class Error(Exception):
    """An error of the library (a file it cannot read, a particle set it cannot use, work over
    a limit); the message is the library's. Wrong dtypes and shapes raise ValueError instead."""

class Refined:
    """The upsampled surface of one frame (Solenthaler et al. 2007, §3.2-3.4)."""

    positions: npt.NDArray[np.float32]
    """(K, 3): the surface points first (in the order of Frame.surface_indices), then each
    step's new points."""
    normals: npt.NDArray[np.float32]
    """(K, 3) unit normals."""
    steps: npt.NDArray[np.uint8]
    """(K,) the step that made each point (0 for the surface particles)."""
    weights: npt.NDArray[np.float32]
    """(K,) interpolation weights (eq. 17-19)."""
    radii: npt.NDArray[np.float32]
    """(K,) splat radius of each point."""
    kernel_radii: npt.NDArray[np.float32]
    """(K,) density kernel radius of each point (the chain's density grid)."""
    final_radius: float
    """The radius after the last step."""
    def __len__(self) -> int: ...

class Surfels:
    """Oriented disks on the water's surface."""

    positions: npt.NDArray[np.float32]
    """(M, 3) centres."""
    normals: npt.NDArray[np.float32]
    """(M, 3) unit normals, out of the water."""
    radii: npt.NDArray[np.float32]
    """(M,) disk radii."""
    iso: float
    """The iso-value of the density grid they lie on (nan for the 'refined' source)."""
    def __len__(self) -> int: ...

class Mesh:
    """A triangle mesh of the iso-surface the surfels lie on (`frame(..., mesh=True)`): closed,
    indexed, counter-clockwise seen from outside; its vertices are the surfels."""

    vertices: npt.NDArray[np.float32]
    """(V, 3) vertex positions."""
    normals: npt.NDArray[np.float32]
    """(V, 3) unit vertex normals, out of the water."""
    faces: npt.NDArray[np.uint32]
    """(F, 3) vertex indices of each triangle."""
    closed: bool
    """Whether every edge is shared by two triangles, once each way."""
    euler_characteristic: int
    """V - E + F: 2 per separate body, less 2 per handle."""
    velocities: Optional[npt.NDArray[np.float32]]
    """(V, 3) vertex velocities interpolated from the particles' (SPH cubic spline,
    normalised), or None when the particles had none."""
    def __len__(self) -> int: ...

class Frame:
    """One frame through the pipeline: every intermediate that was computed."""

    radius: float
    """The support radius used."""
    mean_neighbours: float
    """Mean neighbour count at the support radius (usual: 30-60)."""
    classes: npt.NDArray[np.uint8]
    """(N,) class of every particle: 0 interior, 1 surface, 2 isolated (fluid_surfels.INTERIOR,
    SURFACE, ISOLATED)."""
    offsets: npt.NDArray[np.float32]
    """(N,) centre-of-mass offset d/r of every particle (eq. 2)."""
    normals: npt.NDArray[np.float32]
    """(N, 3) outward normals of the surface particles (zero for the others)."""
    flips: int
    """Particles (matched by id) whose surface state changed since the previous frame."""
    surface_indices: npt.NDArray[np.uint32]
    """(S,) indices of the particles that were refined (surface and isolated ones)."""
    refined: Optional[Refined]
    """The refined surface, from through="refine" on (None for the 'particles' source)."""
    surfels: Optional[Surfels]
    """The surfels that are rendered, from through="surfels" on; through "splats" or "frame"
    with detail "auto" only those facing the camera (or the light) that the picture can show,
    unless mesh=True."""
    image: Optional[npt.NDArray[np.uint8]]
    """(H, W, 4) RGBA: the shaded splats (through="splats") or the finished frame
    (through="frame"); None before."""
    timings: dict[str, Union[float, int, str]]
    """Milliseconds per stage: neighbours_ms, detect_ms, refine_ms, calibration_ms, density_ms,
    surfels_ms, splats_ms, caustics_ms, image_ms, total_ms; and what the level of detail made:
    detail ("auto" or "fixed" as applied), steps (run), refined_points, cell (the density
    grid's, world units), surfels, hidden_surfels (left out as facing away from the picture's
    views)."""
    warnings: list[str]
    """What a user should know (a support radius far off, a grid coarsened to fit its memory
    budget)."""
    mesh: Optional[Mesh]
    """The triangle mesh of the surfels' iso-surface, with frame(..., mesh=True); None
    otherwise and for the renderers that draw spheres."""

class Pipeline:
    """The chain from particles to pixels, on the CPU: surface detection (with hysteresis across
    the frames of a sequence), upsampling, density grid, surfels, EWA splats and optics.

    Keyword arguments are the keys of a pipeline file (see examples/scenes/every_key.toml),
    tables as dicts: Pipeline(support_radius=0.1, refine={"steps": 2},
    optics={"image_size": [640, 480]}). Unset keys keep their defaults; unknown keys and values
    out of range raise ValueError.
    """

    def __init__(self, **params: Any) -> None: ...
    @staticmethod
    def from_toml(path: _Path) -> Pipeline:
        """A pipeline from a TOML file (the format of `render --config`)."""
    @property
    def params(self) -> dict[str, Any]:
        """Every parameter in the layout of a pipeline file; Pipeline(**p.params) is the same
        pipeline."""
    @property
    def support_radius(self) -> Optional[float]:
        """The support radius in use (None before the first frame when it is estimated)."""
    def frame(
        self,
        positions: _Points,
        ids: Optional[_Ids] = None,
        velocities: Optional[_Points] = None,
        *,
        masses: Optional[npt.NDArray[Union[np.float32, np.float64]]] = None,
        through: _Through = "surfels",
        mesh: bool = False,
    ) -> Frame:
        """Runs one frame. mesh: also the triangle mesh of the surfels' iso-surface
        (Frame.mesh). positions: (N, 3) float32 or float64, any layout. ids: (N,) integers
        that keep the hysteresis of surface detection with each particle when the order
        changes. velocities: (N, 3), interpolated at the mesh's vertices (Frame.mesh.velocities),
        read by no other stage. masses: (N,) weights of the
        centre of mass (all equal when absent). through: how far the chain runs ("mesh":
        the surfels and their mesh, as mesh=True).

        C-contiguous float32 positions and masses and uint32 ids are read in place, without a
        copy, while the GIL is released: do not write to them from another thread meanwhile;
        other layouts and dtypes are converted once."""
    def render(
        self,
        positions: _Points,
        ids: Optional[_Ids] = None,
        velocities: Optional[_Points] = None,
        *,
        masses: Optional[npt.NDArray[Union[np.float32, np.float64]]] = None,
        image: Literal["frame", "splats"] = "frame",
    ) -> npt.NDArray[np.uint8]:
        """The whole chain on one frame; its image as an (H, W, 4) uint8 RGBA array: the
        finished frame (caustics, refraction, reflection) or the shaded splats."""
    def fit_to(self, lo: Sequence[float], hi: Sequence[float]) -> None:
        """Fits the sequence's camera, pool and scene box to the box [lo, hi] as well as to the
        first rendered frame's water (give the union of every frame's bounds)."""
    def reset(self) -> None:
        """Forgets what the sequence kept (hysteresis, estimated radius, camera and pool)."""
    def plan(self) -> Optional[dict[str, Any]]:
        """The sequence's plan (support radius, camera, pool, scene box, the light's
        resolutions) once a frame was rendered; None before."""
    def set_plan(self, plan: Union[dict[str, Any], str]) -> None:
        """Takes a sequence's plan (a dict or its JSON text): the next frames render with its
        radius and views."""
    def warm_up(
        self,
        positions: _Points,
        ids: Optional[_Ids] = None,
        *,
        masses: Optional[npt.NDArray[Union[np.float32, np.float64]]] = None,
        through: _Through = "frame",
    ) -> None:
        """Surface detection (and the levels of detail) alone on a frame before the ones to
        draw: a chunk of a sequence then starts with the serial run's hysteresis."""

def read(
    path: _Path, format: Optional[str] = None, *, memory_budget: Optional[int] = None
) -> dict[str, Any]:
    """Reads a particle file into a dict of arrays: positions (N, 3) float32 and, where the file
    has them, ids (N,) uint32, masses (N,) float32, velocities and normals (N, 3) float32,
    colours (N, 3) uint8; attributes: a dict of the file's other per-particle attributes by
    name, (N,) or (N, C), in the type the file stores."""

def write(
    path: _Path,
    positions: _Points,
    *,
    ids: Optional[_Ids] = None,
    masses: Optional[npt.NDArray[Union[np.float32, np.float64]]] = None,
    velocities: Optional[_Points] = None,
    normals: Optional[_Points] = None,
    colours: Optional[npt.NDArray[np.uint8]] = None,
    attributes: Optional[dict[str, npt.NDArray[Any]]] = None,
    format: Optional[str] = None,
    overwrite: bool = False,
) -> None:
    """Writes a particle file (format by extension unless given). An existing file is replaced
    only with overwrite=True (FileExistsError otherwise); the file is written whole or not at
    all."""

def column_frames(last: int) -> list[dict[str, npt.NDArray[Any]]]:
    """The built-in column scene (2,880 particles of a collapsing water column, simulated),
    frames 0 to last: dicts with positions, ids, masses and velocities."""

def column_params() -> dict[str, Any]:
    """The parameters of the main job on the column scene, for Pipeline(**column_params())."""

def plan_of(pattern: str, first: int, params: Optional[dict[str, Any]] = None) -> dict[str, Any]:
    """The plan of a sequence of files: frame `first` of `pattern` (holding {} for the frame
    number) drawn as a finished frame by a pipeline of `params`."""

def render_chunk(
    pattern: str,
    frames: Sequence[int],
    out: _Path,
    *,
    warmup: Sequence[int] = (),
    plan: Optional[Union[dict[str, Any], str]] = None,
    params: Optional[dict[str, Any]] = None,
    skip_existing: bool = True,
) -> dict[str, Any]:
    """One chunk of a sequence of files: a pipeline of `params` takes `plan`, warms up on the
    frames `warmup`, then writes the finished frame of each of `frames` to
    out/frame_NNNN.png atomically. A frame that fails is reported and the others written.
    Returns written, skipped, failed ([frame, error] pairs), warmup_failed and seconds."""

def write_mesh(
    path: _Path,
    vertices: _Points,
    faces: npt.NDArray[Any],
    *,
    velocities: Optional[_Points] = None,
    time: Optional[float] = None,
    overwrite: bool = False,
) -> None:
    """Writes a triangle mesh as binary PLY, OBJ, legacy VTK POLYDATA, VTK XML (an
    unstructured grid of triangles, which meshio reads) or USD text (by the extension of path:
    .ply, .obj, .vtk, .vtu, .usda), atomically: vertices (V, 3), faces (F, 3)
    vertex indices, velocities (V, 3) when given (not in OBJ); normals from the triangles.
    time: a .usda frame of a sequence, its values time samples at that time code (see
    write_usd_stage). An existing file is replaced only with overwrite=True (FileExistsError
    otherwise)."""

def read_mesh(path: _Path) -> Mesh:
    """Reads a mesh from a .ply or .vtk file: vertices, normals (the file's, or the
    triangles'), velocities when the file has them, faces (polygons split into triangles)."""

def write_usd_stage(
    path: _Path,
    frames: list[tuple[float, _Path]],
    *,
    fps: float = 24.0,
    overwrite: bool = False,
) -> None:
    """Writes a USD stage (.usda) that plays the .usda frames ((time code, path) pairs, each
    written by write_mesh(..., time=t)) as an animation through value clips, with its
    manifest <stem>.manifest.usda beside it. An existing stage is replaced only with
    overwrite=True (FileExistsError otherwise)."""
