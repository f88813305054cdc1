"""The type stubs describe the module as built: every name and member the stubs declare exists,
every public name of the module is declared, and the functions' parameters match."""

import ast
import inspect
from pathlib import Path

import fluid_surfels as fs
from fluid_surfels import _native

# the stubs the package installs (the wheel holds them), so this runs from an installed wheel too
STUBS = Path(fs.__file__).resolve().parent / "_native.pyi"


def declared():
    tree = ast.parse(STUBS.read_text())
    names, members, params = set(), {}, {}
    for node in tree.body:
        if isinstance(node, ast.ClassDef):
            names.add(node.name)
            members[node.name] = set()
            for item in node.body:
                if isinstance(item, ast.FunctionDef):
                    members[node.name].add(item.name)
                    params[f"{node.name}.{item.name}"] = item.args
                elif isinstance(item, ast.AnnAssign):
                    members[node.name].add(item.target.id)
        elif isinstance(node, ast.FunctionDef):
            names.add(node.name)
            params[node.name] = node.args
        elif isinstance(node, ast.AnnAssign) and not node.target.id.startswith("_"):
            names.add(node.target.id)
    names.add("__version__")
    return names, members, params


def test_stubs_match_the_module():
    names, members, params = declared()
    public = {n for n in dir(_native) if not n.startswith("_")} | {"__version__"}
    assert names == public, (names ^ public)
    assert set(fs.__all__) - {"INTERIOR", "SURFACE", "ISOLATED"} == public
    for cls, attrs in members.items():
        for attr in attrs - {"__init__"}:
            assert hasattr(getattr(_native, cls), attr), f"{cls}.{attr}"
    # the keyword names of every function (what editors complete) are the module's
    for name, args in params.items():
        obj = _native
        for part in name.split("."):
            obj = getattr(obj, part)
        if name.endswith(("__init__", "__len__")) or not callable(obj):
            continue  # properties and getters
        stub = [a.arg for a in args.posonlyargs + args.args + args.kwonlyargs if a.arg != "self"]
        runtime = [p for p in inspect.signature(obj).parameters if p != "self"]
        assert stub == runtime, (name, stub, runtime)
    assert fs.Pipeline.__doc__ and fs.read.__doc__ and fs.Frame.classes.__doc__
