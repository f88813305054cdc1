"""fluid-surfels from Python: the particles of a fluid simulation to a rendered water surface.

    import fluid_surfels as fs
    pipeline = fs.Pipeline(support_radius=0.1, optics={"image_size": [640, 480]})
    frame = pipeline.frame(positions, ids=ids)          # classes, refined points, surfels
    image = pipeline.render(positions, ids=ids)         # (H, W, 4) uint8, the finished frame

Everything runs in the Rust library (`fluid_surfels._native`) with the GIL released; see the
type stubs (`_native.pyi`) for every function and field.
"""

from ._native import (
    FORMATS,
    Error,
    Frame,
    Mesh,
    Pipeline,
    Refined,
    Surfels,
    __version__,
    column_frames,
    column_params,
    plan_of,
    read,
    read_mesh,
    render_chunk,
    write,
    write_mesh,
    write_usd_stage,
)

INTERIOR, SURFACE, ISOLATED = 0, 1, 2
"""The values of `Frame.classes`."""

__all__ = [
    "FORMATS",
    "INTERIOR",
    "ISOLATED",
    "SURFACE",
    "Error",
    "Frame",
    "Mesh",
    "Pipeline",
    "Refined",
    "Surfels",
    "__version__",
    "column_frames",
    "column_params",
    "plan_of",
    "read",
    "read_mesh",
    "render_chunk",
    "write",
    "write_mesh",
    "write_usd_stage",
]
