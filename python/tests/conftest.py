"""Shared fixtures: the command line built from the same sources (the Rust reference the
bindings are compared with) and the real particle files."""

import os
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "tests" / "data"
DAM_BREAK = DATA / "double_dam_break_frame_26_4732_particles.vtk"
IN_REPOSITORY = (ROOT / "Cargo.toml").exists() and DAM_BREAK.exists()
"""Whether the tests run from a checkout (its data files, README, examples and command line), not
from an installed wheel alone."""


def pytest_configure(config):
    config.addinivalue_line(
        "markers",
        "repository: needs the repository's data files, README or command line (skipped when "
        "the tests run from an installed wheel alone)",
    )


def pytest_collection_modifyitems(config, items):
    if IN_REPOSITORY:
        return
    skip = pytest.mark.skip(
        reason="needs the fluid-surfels repository (tests/data, README.md, examples, the "
        "command line): run the tests from a checkout"
    )
    for item in items:
        if "repository" in item.keywords or "cli" in getattr(item, "fixturenames", ()):
            item.add_marker(skip)


def _binary() -> Path:
    given = os.environ.get("FLUID_SURFELS_BIN")
    if given:
        return Path(given)
    for profile in ("debug", "release"):
        path = ROOT / "target" / profile / "fluid-surfels"
        if path.exists():
            return path
    return ROOT / "target" / "debug" / "fluid-surfels"


@pytest.fixture(scope="session")
def cli():
    """Runs the fluid-surfels command line; fails (never skips) when it is not built."""
    binary = _binary()
    if not binary.exists():
        pytest.fail(
            f"{binary} is missing: build it first (cargo build), or set FLUID_SURFELS_BIN"
        )

    def run(*args: str) -> subprocess.CompletedProcess:
        done = subprocess.run(
            [str(binary), *map(str, args)], capture_output=True, text=True, check=False
        )
        assert done.returncode == 0, f"fluid-surfels {' '.join(map(str, args))}:\n{done.stderr}"
        return done

    return run


@pytest.fixture(scope="session")
def column():
    """The column scene's frames 0..=14 (the splash), as the main job simulates them."""
    import fluid_surfels as fs

    return fs.column_frames(14)


def extra(module: str, install: str):
    """Imports an optional test dependency (meshio, usd-core's pxr, distributed): skipped when
    it is missing, except where FLUID_SURFELS_REQUIRE_EXTRAS=1 (scripts/test.sh installs them,
    so there a missing one fails rather than skips)."""
    if os.environ.get("FLUID_SURFELS_REQUIRE_EXTRAS") == "1":
        import importlib

        return importlib.import_module(module)
    return pytest.importorskip(module, reason=f"an optional test dependency: pip install {install}")
