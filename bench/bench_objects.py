"""Which object a bench case synthesises: a shared mesh by name, any mesh file, or a procedural one.

spot, avocado, bob     the textured meshes of ../shared/data/meshes (bob: a duck)
toycar, figurine,      `recon.procedural` objects (the mug: a handle on one side; the
mug, chair             chair: thin legs and slats)
path/to/mesh.obj       any mesh `sine synth --mesh` reads (OBJ/GLB/GLTF/PLY); the case is
                       named after the file's stem (its folder in the bench's --out)
"""

from __future__ import annotations

from pathlib import Path

SHARED_MESHES = Path(__file__).resolve().parents[2] / "shared/data/meshes"
MESHES = {
    "spot": SHARED_MESHES / "spot/spot_triangulated.obj",
    "avocado": SHARED_MESHES / "avocado/avocado.obj",
    "bob": SHARED_MESHES / "bob/bob_tri.obj",
}
# the editing benchmarks' objects: toys, shared textured meshes, an asymmetric object and one
# with thin parts
GRID_OBJECTS = ("toycar", "figurine", "spot", "avocado", "bob", "mug", "chair")
MESH_SUFFIXES = (".obj", ".glb", ".gltf", ".ply", ".off", ".stl")


def is_mesh_path(name: str) -> bool:
    """Whether a case name is a mesh file rather than a built-in object."""
    return Path(name).suffix.lower() in MESH_SUFFIXES


def case_name(name: str) -> str:
    """The case's name in tables and folders: a mesh file's stem, else the name itself."""
    return Path(name).stem if is_mesh_path(name) else name


def synth_source(name: str) -> dict:
    """The `SynthConfig` source of a case: {"mesh": path} or {"procedural": name}."""
    if is_mesh_path(name):
        path = Path(name).expanduser().resolve()
        if not path.is_file():
            raise SystemExit(f"mesh {name} does not exist")
        return {"mesh": path}
    if name in MESHES:
        return {"mesh": MESHES[name]}
    return {"procedural": name}


def gt_edit_capture(source: str, work: Path, kind: str, size: int, views: int, **edit) -> Path:
    """work/gt_KIND: the case's object rendered again with a GT edit (`edit`: SynthConfig
    options, e.g. edit=["geometric"], edit_plane=[...]) and the cameras of the base capture
    work/synth, so one template serves every edit kind; reused when its edit.json exists."""
    from recon.synth import SynthConfig, synthesize

    syn = work / f"gt_{kind}"
    done = [syn / "edits" / name / "edit.json" for name in edit.get("edit", [])]
    if not done or not all(path.is_file() for path in done):
        synthesize(
            SynthConfig(
                out=syn,
                views=views,
                width=size,
                height=size,
                cameras_from=work / "synth",
                **edit,
                **synth_source(source),
            ),
            progress=False,
        )
    return syn
