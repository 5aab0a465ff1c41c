"""Triangle files -> Scene, with triangle ids in the file's face order.

The id a backend reports must be the id Embree reports and the id a user finds in the file:
- nothing is welded, merged, reordered or dropped (degenerate and duplicate triangles stay);
- OBJ is read by a small reader of our own: trimesh's OBJ loader groups faces by material
  (`usemtl`), which renumbers triangles, and drops unreferenced vertices;
- everything else goes through trimesh (`process=False`, `maintain_order=True`); a file with
  several meshes (glTF nodes, primitives) is concatenated without welding, in file order (glTF:
  depth-first over the scene's nodes, children and primitives in the order the file lists them).

`checked_scene` is the one gate into the Scene contract (float32 vertices, uint32 faces, every
index in range, no NaN/Inf), for files and built-in scenes alike. Bad input raises `SceneError`
with a one-line message.
"""
from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np

from lsbench.inputs.scene import Camera, Scene, SceneError


def load_mesh_file(path: Path) -> Scene:
    """A triangle file (OBJ, PLY, glTF/GLB, STL, ...) as a Scene named after the file."""
    if not path.exists():
        raise SceneError(f"scene file not found: {path}")
    if not path.is_file():
        raise SceneError(f"scene path is not a file: {path}")
    if path.suffix.lower() == ".obj":
        vertices, faces = _read_obj(path)
    else:
        vertices, faces = _read_with_trimesh(path)
    return checked_scene(path.stem, vertices, faces, str(path))


def checked_scene(name: str, vertices, faces, source: str, camera: Camera | None = None) -> Scene:
    """Validate and convert to the Scene contract (float32 (V,3), uint32 (F,3))."""
    with np.errstate(over="ignore"):  # beyond float32 range -> Inf, reported below in one line
        vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3).astype(np.float32)
    faces = np.asarray(faces).reshape(-1, 3)
    if faces.shape[0] == 0:
        raise SceneError(f"{source}: scene has no triangles")
    # checked after the float32 cast: a float64 value beyond float32 range becomes Inf there
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise SceneError(
            f"{source}: {int(bad.sum())} vertices have NaN/Inf coordinates "
            f"(first: vertex {int(np.argmax(bad))})"
        )
    faces = faces.astype(np.int64)
    out = (faces < 0) | (faces >= vertices.shape[0])
    if out.any():
        face = int(np.argmax(out.any(axis=1)))
        raise SceneError(
            f"{source}: face {face} refers to vertex {int(faces[face][out[face]][0])} "
            f"(0-based), out of range for {vertices.shape[0]} vertices"
        )
    return Scene(name=name, vertices=np.ascontiguousarray(vertices),
                 faces=np.ascontiguousarray(faces.astype(np.uint32)), source=source, camera=camera)


def _one_line(err: BaseException) -> str:
    text = " ".join(str(err).split()) or type(err).__name__
    return text if len(text) <= 200 else text[:197] + "..."


def _read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """`v` and `f` records in file order; polygons fan-triangulated; other records ignored."""
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as err:
        raise SceneError(f"cannot read {path}: {_one_line(err)}") from None
    vertices: list[list[float]] = []
    faces: list[tuple[int, int, int]] = []
    for lineno, line in enumerate(text.splitlines(), 1):
        tokens = line.split()
        if not tokens or tokens[0] not in ("v", "f"):
            continue
        try:
            if tokens[0] == "v":
                vertices.append([float(t) for t in tokens[1:4]])
                if len(vertices[-1]) != 3:
                    raise ValueError
                continue
            # "f 1/2/3 ..." -> the position index; negative indices count back from the
            # vertices read so far
            ids = [int(t.split("/", 1)[0]) for t in tokens[1:]]
        except ValueError:
            raise SceneError(f"{path}:{lineno}: cannot parse {tokens[0]!r} record") from None
        if len(ids) < 3:
            raise SceneError(f"{path}:{lineno}: face with fewer than 3 vertices")
        if 0 in ids:
            raise SceneError(f"{path}:{lineno}: face index 0 (OBJ indices start at 1)")
        ids = [i - 1 if i > 0 else len(vertices) + i for i in ids]
        faces.extend((ids[0], ids[k], ids[k + 1]) for k in range(1, len(ids) - 1))
    return np.array(vertices, dtype=np.float64), np.array(faces, dtype=np.int64)


def _read_with_trimesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import trimesh  # slow import (~0.5 s); only file scenes need it

    try:
        loaded = trimesh.load_scene(str(path), process=False, maintain_order=True)
    except Exception as err:  # trimesh raises anything from ValueError to KeyError on bad input
        raise SceneError(f"cannot read {path}: {_one_line(err)}") from None
    nodes = loaded.graph.nodes_geometry
    if path.suffix.lower() in (".gltf", ".glb"):
        nodes = _gltf_file_order(path, loaded, nodes)
    vertices, faces, offset = [], [], 0
    for node in nodes:
        transform, geometry_name = loaded.graph[node]
        mesh = loaded.geometry[geometry_name]
        if not isinstance(mesh, trimesh.Trimesh):  # point clouds, paths: no triangles
            continue
        # bake the instance transform; faces keep their index order (no winding flip, no weld)
        v = np.asarray(mesh.vertices, dtype=np.float64)
        vertices.append(v @ transform[:3, :3].T + transform[:3, 3])
        faces.append(np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3) + offset)
        offset += len(v)
    if not faces:
        raise SceneError(f"{path}: scene has no triangles")
    return np.concatenate(vertices), np.concatenate(faces)


def _gltf_file_order(path: Path, loaded, nodes: list[str]) -> list[str]:
    """Geometry nodes sorted into the glTF file's order.

    trimesh walks the node tree with a stack, so it lists sibling nodes in reverse file order.
    Node names are rebuilt the way trimesh's loader names them; a primitive of a multi-primitive
    mesh is a child frame of its node, listed in primitive order (the sort is stable). Anything
    unexpected keeps trimesh's order, which is deterministic too.
    """
    from trimesh.util import unique_name

    try:
        header = _gltf_header(path)
        gltf_nodes = header.get("nodes", [])
        name_index: dict[str, int] = {}
        counts: dict[str, int] = {}
        for i, node in enumerate(gltf_nodes):
            name_index[unique_name(node.get("name", str(i)), name_index, counts=counts)] = i
        # depth-first pre-order from the scene's roots, children in file order
        position: dict[int, int] = {}
        scene = header.get("scenes", [{}])[header.get("scene", 0)]
        stack = list(reversed(scene.get("nodes", [])))
        while stack:
            index = stack.pop()
            if index in position:
                continue
            position[index] = len(position)
            stack.extend(reversed(gltf_nodes[index].get("children", [])))
        parents = loaded.graph.transforms.parents

        def key(frame: str) -> int:
            if frame not in name_index:
                frame = parents[frame]  # a primitive's frame hangs under its node's frame
            return position[name_index[frame]]

        return sorted(nodes, key=key)
    except Exception:
        return list(nodes)


def _gltf_header(path: Path) -> dict:
    data = path.read_bytes()
    if data[:4] == b"glTF":
        # GLB: 12-byte header, then the JSON chunk (length, type, payload)
        (length,) = struct.unpack_from("<I", data, 12)
        return json.loads(data[20:20 + length])
    return json.loads(data)
