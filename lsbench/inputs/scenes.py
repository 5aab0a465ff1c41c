"""Scene loading: built-in procedural scenes and triangle files.

`load_scene(spec)` takes a built-in name (see `builtin_names()`) or a file path.

Triangle ids are the face order of the source, because the id a backend reports must be the id
Embree reports and the id a user finds in the file:
- nothing is welded, merged, reordered or dropped (degenerate and duplicate triangles stay);
- OBJ is read by a small reader of our own: trimesh's OBJ loader groups faces by material
  (`usemtl`), which renumbers triangles, and drops unreferenced vertices;
- everything else goes through trimesh (`process=False`, `maintain_order=True`); a file with
  several meshes (glTF nodes, primitives) is concatenated without welding, in file order (glTF:
  depth-first over the scene's nodes, children and primitives in the order the file lists them).

Bad input raises `SceneError` with a one-line message.
"""
from __future__ import annotations

import json
import math
import os
import struct
from collections.abc import Callable
from pathlib import Path

import numpy as np

from lsbench.inputs.scene import Camera, Scene, SceneError

# ----------------------------------------------------------------------------------------------
# public API


def builtin_names() -> list[str]:
    return list(_BUILTINS)


def load_scene(spec: str) -> Scene:
    """A built-in scene by name, or a triangle file (OBJ, PLY, glTF/GLB, STL, ... )."""
    builder = _BUILTINS.get(spec)
    if builder is not None:
        return builder()
    path = Path(spec)
    # a bare word that is no built-in is most likely a typo of one: say which names exist
    if not (path.exists() or path.suffix or os.sep in spec or "/" in spec):
        raise SceneError(
            f"unknown scene {spec!r}: not a built-in ({', '.join(builtin_names())}) "
            "and not a file path"
        )
    return _load_file(path)


def default_camera(scene: Scene) -> Camera:
    """scene.camera if set, else a view of the whole bounding box from outside, up = +Y."""
    if scene.camera is not None:
        return scene.camera
    lo, hi = (b.astype(np.float64) for b in scene.bounds)
    centre = (lo + hi) / 2
    radius = max(float(np.linalg.norm(hi - lo)) / 2, 1e-6)
    fov = 60.0
    # the bounding sphere fits a cone of half-angle fov/2 from this distance
    distance = radius / math.sin(math.radians(fov / 2))
    direction = np.array([0.4, 0.3, 1.0]) / np.linalg.norm([0.4, 0.3, 1.0])
    eye = centre + direction * distance
    return Camera(eye=_tuple(eye), target=_tuple(centre), up=(0.0, 1.0, 0.0), fov_deg=fov)


# ----------------------------------------------------------------------------------------------
# files


def _load_file(path: Path) -> Scene:
    if not path.exists():
        raise SceneError(f"scene file not found: {path}")
    if not path.is_file():
        raise SceneError(f"scene path is not a file: {path}")
    if path.suffix.lower() == ".obj":
        vertices, faces = _read_obj(path)
    else:
        vertices, faces = _read_with_trimesh(path)
    return _checked_scene(path.stem, vertices, faces, str(path))


def _checked_scene(name: str, vertices, faces, source: str, camera: Camera | None = None) -> Scene:
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


# ----------------------------------------------------------------------------------------------
# geometry building blocks (all vectorized; a part is a (vertices (n,3) float64, faces (m,3)))

Part = tuple[np.ndarray, np.ndarray]


def _tuple(v) -> tuple[float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]))


def _concat(parts: list[Part]) -> Part:
    offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    vertices = np.concatenate([v for v, _ in parts])
    faces = np.concatenate([f + o for (_, f), o in zip(parts, offsets)])
    return vertices, faces


def _grid_faces(cols: int, rows: int, wrap: bool) -> np.ndarray:
    """Two triangles per cell of a (rows+1) x cols vertex grid; `wrap` joins the last column
    to the first (closed surfaces share the seam vertices, so they have no crack)."""
    cells_u = cols if wrap else cols - 1
    i, j = np.meshgrid(np.arange(cells_u), np.arange(rows), indexing="xy")
    a = j * cols + i
    b = j * cols + (i + 1) % cols
    c, d = a + cols, b + cols
    return np.stack([np.stack([a, b, d], -1), np.stack([a, d, c], -1)], axis=2).reshape(-1, 3)


def _surface(fn: Callable[[np.ndarray, np.ndarray], np.ndarray], u: np.ndarray, v: np.ndarray,
             wrap_u: bool = False) -> Part:
    """Parametric surface fn(U, V) -> (..., 3) sampled at the grid u x v.
    With wrap_u, u is periodic: pass the samples without the closing one."""
    uu, vv = np.meshgrid(u, v, indexing="xy")
    vertices = fn(uu, vv).reshape(-1, 3)
    return vertices, _grid_faces(len(u), len(v) - 1, wrap_u)


def _periodic(n: int) -> np.ndarray:
    return np.arange(n) / n


def _revolve(radius: Callable[[np.ndarray, np.ndarray], np.ndarray], height: float,
             around: int, rings: int) -> Part:
    """Surface of revolution about +Y from y=0 to y=height; radius(theta, v) with v in [0, 1]."""
    def fn(u, v):
        theta = 2 * np.pi * u
        r = radius(theta, v)
        # z = -sin: triangles face outwards (as in _uv_sphere)
        return np.stack([r * np.cos(theta), v * height, -r * np.sin(theta)], -1)

    return _surface(fn, _periodic(around), np.linspace(0, 1, rings + 1), wrap_u=True)


def _uv_sphere(radius: float, around: int, rings: int) -> Part:
    """UV sphere with triangle-fan caps (a plain grid would make zero-area triangles at the
    poles): around * (2 * rings - 2) triangles."""
    def fn(u, v):
        theta, phi = 2 * np.pi * u, np.pi * v
        # z = -sin: with theta growing clockwise seen from +Y the triangles face outwards
        return radius * np.stack([np.sin(phi) * np.cos(theta), -np.cos(phi),
                                  -np.sin(phi) * np.sin(theta)], -1)

    # the band between the first and last latitude rings, then one fan per pole
    body_v, body_f = _surface(fn, _periodic(around), np.arange(1, rings) / rings, wrap_u=True)
    i = np.arange(around)
    south, north = len(body_v), len(body_v) + 1
    top = (rings - 2) * around  # first vertex of the last ring
    caps = np.concatenate([
        np.stack([np.full(around, south), (i + 1) % around, i], -1),
        np.stack([np.full(around, north), top + i, top + (i + 1) % around], -1),
    ])
    vertices = np.concatenate([body_v, [[0.0, -radius, 0.0], [0.0, radius, 0.0]]])
    return vertices, np.concatenate([body_f, caps])


def _icosphere() -> Part:
    """Unit icosphere, one subdivision: 42 vertices, 80 triangles."""
    import trimesh.creation

    mesh = trimesh.creation.icosphere(subdivisions=1, radius=1.0)
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


def _quad(p0, p1, p2, p3) -> Part:
    return np.array([p0, p1, p2, p3], dtype=np.float64), np.array([[0, 1, 2], [0, 2, 3]])


def _rect_y(x0, x1, z0, z1, y) -> Part:
    """Horizontal rectangle at height y."""
    return _quad((x0, y, z0), (x1, y, z0), (x1, y, z1), (x0, y, z1))


def _rect_z(x0, x1, y0, y1, z) -> Part:
    """Vertical rectangle in the plane z = const."""
    return _quad((x0, y0, z), (x1, y0, z), (x1, y1, z), (x0, y1, z))


def _rect_x(z0, z1, y0, y1, x) -> Part:
    """Vertical rectangle in the plane x = const."""
    return _quad((x, y0, z0), (x, y0, z1), (x, y1, z1), (x, y1, z0))


def _box(centre, size, angle_deg: float = 0.0) -> Part:
    """Axis-aligned box of `size`, rotated about +Y, 12 triangles."""
    corners = np.array([[x, y, z] for x in (-.5, .5) for y in (-.5, .5) for z in (-.5, .5)])
    corners = corners * np.asarray(size, dtype=np.float64)
    a = math.radians(angle_deg)
    rot = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    vertices = corners @ rot.T + np.asarray(centre, dtype=np.float64)
    # corner index = 4*ix + 2*iy + iz
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5],  # x- / x+
                      [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],  # y- / y+
                      [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])  # z- / z+
    return vertices, faces


def _instances(part: Part, offsets: np.ndarray, scales: np.ndarray | None = None) -> Part:
    """Copies of one part, scaled per axis then translated (vectorized, no per-copy loop)."""
    v, f = part
    offsets = np.asarray(offsets, dtype=np.float64).reshape(-1, 3)
    scales = np.ones_like(offsets) if scales is None else np.broadcast_to(scales, offsets.shape)
    vertices = v[None] * scales[:, None, :] + offsets[:, None, :]
    faces = f[None] + (np.arange(len(offsets)) * len(v))[:, None, None]
    return vertices.reshape(-1, 3), faces.reshape(-1, 3)


def _scene(name: str, parts: list[Part], camera: Camera) -> Scene:
    vertices, faces = _concat(parts)
    return _checked_scene(name, vertices, faces, f"builtin:{name}", camera)


# ----------------------------------------------------------------------------------------------
# atrium: a Sponza-like courtyard. Long axis X, up +Y, metres. The open courtyard is
# x in [-18, 18], z in [-5.7, 5.7]; two storeys of arcades at z = +-6 with galleries behind them
# (z up to +-9), a roof over the galleries only (open sky over the courtyard). Detail ranges from
# 2-triangle walls to fluted columns, dense curtains and vases: orders of magnitude apart.

_ATRIUM_BAY = 2.5  # column spacing
_ATRIUM_COLUMNS_X = -13.75 + _ATRIUM_BAY * np.arange(12)
_ATRIUM_WALL_Z = 6.0  # arcade wall centre plane (both sides)
_ATRIUM_WALL_T = 0.6  # arcade wall thickness
# per storey: floor level, column height, storey height
_ATRIUM_STOREYS = ((0.0, 4.0, 6.0), (6.0, 3.5, 6.0))


def _column() -> Part:
    """Unit-height fluted column: plinth, torus, tapered shaft with 16 flutes, flared capital."""
    def radius(theta, v):
        r = np.interp(v, [0.0, 0.04, 0.045, 0.09, 0.1, 0.88, 0.96, 1.0],
                      [0.36, 0.36, 0.31, 0.31, 0.27, 0.25, 0.34, 0.38])
        torus = 0.04 * np.sin(np.pi * np.clip((v - 0.045) / 0.045, 0, 1))
        shaft = (v > 0.1) & (v < 0.88)
        flutes = np.where(shaft, 0.012 * np.cos(16 * theta), 0.0)
        return r + torus + flutes

    return _revolve(radius, 1.0, around=32, rings=32)


def _arch_bay(rise: float) -> Part:
    """One arcade bay above the spring line: semicircular soffit plus the spandrel wall (front
    and back) between the arch and the bay's rectangle, centred at x=0, spring at y=0, wall
    centred at z=0. `rise` is the rectangle's height above the spring line."""
    half = _ATRIUM_BAY / 2
    ra = half - 0.35  # intrados radius: the arch springs from the column capital
    t_wall = _ATRIUM_WALL_T / 2
    corner = math.atan2(rise, half)
    # sample the rectangle's corners exactly, or the outer edge cuts them off
    t = np.union1d(np.linspace(0, np.pi, 49), [corner, np.pi - corner])

    def inner(tt):
        return np.stack([ra * np.cos(tt), ra * np.sin(tt)], -1)

    def outer(tt):
        c, s = np.cos(tt), np.sin(tt)
        with np.errstate(divide="ignore"):
            reach = np.minimum(half / np.abs(c), rise / s)
        return np.stack([reach * c, reach * s], -1)

    def soffit(u, v):
        xy = inner(u)
        return np.stack([xy[..., 0], xy[..., 1], v], -1)

    def spandrel(z):
        def fn(u, v):
            xy = inner(u) * (1 - v[..., None]) + outer(u) * v[..., None]
            return np.stack([xy[..., 0], xy[..., 1], np.full_like(u, z)], -1)
        return fn

    parts = [
        _surface(soffit, t, np.linspace(-t_wall, t_wall, 3)),
        _surface(spandrel(-t_wall), t, np.linspace(0, 1, 3)),
        _surface(spandrel(t_wall), t, np.linspace(0, 1, 3)),
        # impost: the strip of the spring line between the arch and the bay edge
        _rect_y(ra, half, -t_wall, t_wall, 0.0),
        _rect_y(-half, -ra, -t_wall, t_wall, 0.0),
    ]
    return _concat(parts)


def _curtain(width: float, height: float, phase: float) -> Part:
    """Hanging cloth centred at x=0, top edge at y=0, z=0; folds grow towards the hem."""
    def fn(u, v):
        x = (u - 0.5) * width
        y = -v * height
        folds = 0.12 * np.sin(2 * np.pi * 4 * u + phase) * (0.3 + 0.7 * v)
        ripple = 0.02 * np.sin(2 * np.pi * 11 * u + 3 * v + phase) * v
        billow = 0.25 * np.sin(np.pi * u) * np.sin(np.pi * v)
        return np.stack([x, y, folds + ripple + billow], -1)

    return _surface(fn, np.linspace(0, 1, 65), np.linspace(0, 1, 97))


def _vase() -> Part:
    """1.2 m vase with an eight-lobed body (surface of revolution, 48 x 48)."""
    def radius(theta, v):
        body = 0.18 + 0.16 * np.sin(np.pi * np.clip(v / 0.8, 0, 1))
        neck = np.where(v > 0.8, 0.18 + 0.5 * (v - 0.8) ** 2 * 10, body)
        lobes = 0.02 * np.cos(8 * theta) * np.sin(np.pi * np.clip(v / 0.8, 0, 1))
        return np.where(v > 0.8, neck, body + lobes)

    return _revolve(radius, 1.2, around=48, rings=48)


def _build_atrium() -> Scene:
    x0, x1, z_out, y_top = -18.0, 18.0, 9.0, 16.0
    zw, tw = _ATRIUM_WALL_Z, _ATRIUM_WALL_T / 2
    parts: list[Part] = [
        _rect_y(x0, x1, -z_out, z_out, 0.0),  # floor
        _rect_x(-z_out, z_out, 0.0, y_top, x0), _rect_x(-z_out, z_out, 0.0, y_top, x1),  # ends
        _rect_z(x0, x1, 0.0, y_top, -z_out), _rect_z(x0, x1, 0.0, y_top, z_out),  # long walls
    ]
    column = _column()
    for side in (-1.0, 1.0):
        z_face = side * (zw - tw)  # courtyard face of the arcade wall
        parts += [
            # gallery floor / ceiling slabs and the roof over the gallery (sky stays open)
            _rect_y(x0, x1, side * (zw - tw), side * z_out, 6.0),
            _rect_y(x0, x1, side * (zw - tw), side * z_out, 12.0),
            _rect_y(x0, x1, side * (zw - tw), side * z_out, y_top),
            _rect_z(x0, x1, 12.0, y_top, z_face),  # attic wall above the upper arcade
            # solid piers closing the arcades at both ends
            _rect_z(x0, _ATRIUM_COLUMNS_X[0], 0.0, 12.0, side * zw),
            _rect_z(_ATRIUM_COLUMNS_X[-1], x1, 0.0, 12.0, side * zw),
        ]
    bay_centres = (_ATRIUM_COLUMNS_X[:-1] + _ATRIUM_COLUMNS_X[1:]) / 2
    for floor, col_h, storey_h in _ATRIUM_STOREYS:
        spring = floor + col_h
        for side in (-1.0, 1.0):
            n = len(_ATRIUM_COLUMNS_X)
            cols = np.stack([_ATRIUM_COLUMNS_X, np.full(n, floor), np.full(n, side * zw)], -1)
            parts.append(_instances(column, cols, np.array([1.0, col_h, 1.0])))
            m = len(bay_centres)
            bays = np.stack([bay_centres, np.full(m, spring), np.full(m, side * zw)], -1)
            parts.append(_instances(_arch_bay(floor + storey_h - spring), bays))
    # banners hanging from the upper arcade into the courtyard, like Sponza's
    for i, (cx, side) in enumerate([(-7.5, -1), (7.5, -1), (-7.5, 1), (7.5, 1)]):
        cv, cf = _curtain(2.0, 5.0, phase=0.7 * i)
        cv = cv * np.array([1.0, 1.0, -side]) + np.array([cx, 11.8, side * (zw - tw - 0.45)])
        parts.append((cv, cf))
    vase_spots = np.array([[x, 0.0, z] for x, z in
                           [(-10, 3.5), (-6, -3.5), (-2, 3.5), (2, -3.5), (6, 3.5), (10, -3.5)]])
    parts.append(_instances(_vase(), vase_spots))
    sphere_spots = np.array([[-14.0, 0.5, 4.0], [14.0, 0.5, -4.0], [14.0, 0.5, 4.0]])
    parts.append(_instances(_uv_sphere(0.5, 32, 24), sphere_spots))
    camera = Camera(eye=(-16.0, 2.5, 0.0), target=(10.0, 5.0, 0.0), fov_deg=60.0)
    return _scene("atrium", parts, camera)


# ----------------------------------------------------------------------------------------------
# cornell: x in [-1, 1], y in [0, 2], z in [-1, 1], open towards +z; 36 triangles


def _build_cornell() -> Scene:
    parts = [
        _rect_y(-1, 1, -1, 1, 0.0),  # floor
        _rect_y(-1, 1, -1, 1, 2.0),  # ceiling
        _rect_z(-1, 1, 0, 2, -1.0),  # back wall
        _rect_x(-1, 1, 0, 2, -1.0),  # left wall
        _rect_x(-1, 1, 0, 2, 1.0),  # right wall
        _box((0.33, 0.3, 0.3), (0.6, 0.6, 0.6), angle_deg=-17.0),  # short box
        _box((-0.33, 0.6, -0.28), (0.6, 1.2, 0.6), angle_deg=17.0),  # tall box
        _rect_y(-0.25, 0.25, -0.2, 0.2, 1.98),  # light, just below the ceiling
    ]
    camera = Camera(eye=(0.0, 1.0, 3.8), target=(0.0, 1.0, 0.0), fov_deg=40.0)
    return _scene("cornell", parts, camera)


# ----------------------------------------------------------------------------------------------
# spheres: 10 x 10 x 10 jittered lattice of small spheres over a floor


def _build_spheres() -> Scene:
    rng = np.random.default_rng(20240611)  # fixed seed: the scene is the same in every run
    n = 10
    idx = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    centres = (idx - (n - 1) / 2) + rng.uniform(-0.15, 0.15, size=idx.shape)
    radii = rng.uniform(0.12, 0.34, size=len(idx))
    # two kinds of small object: coarse icospheres (80 tris) and UV spheres (168 tris)
    big = radii > 0.23
    floor_y = -(n / 2) - 0.5
    parts = [
        _instances(_icosphere(), centres[~big], radii[~big, None]),
        _instances(_uv_sphere(1.0, 12, 8), centres[big], radii[big, None]),
        _rect_y(-12, 12, -12, 12, floor_y),
    ]
    camera = Camera(eye=(10.0, 7.0, 16.0), target=(0.0, -0.5, 0.0), fov_deg=50.0)
    return _scene("spheres", parts, camera)


# ----------------------------------------------------------------------------------------------
# tiny scenes for unit tests

_TINY_CAMERA = Camera(eye=(0.0, 0.0, 3.0), target=(0.0, 0.0, 0.0), fov_deg=60.0)


def _build_single_triangle() -> Scene:
    part = (np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.0, 0.0]]), np.array([[0, 1, 2]]))
    return _scene("single-triangle", [part], _TINY_CAMERA)


def _build_quad() -> Scene:
    return _scene("quad", [_rect_z(-1, 1, -1, 1, 0.0)], _TINY_CAMERA)


def _build_two_planes() -> Scene:
    # the back plane is larger, so rays that miss the front plane hit it
    parts = [_rect_z(-1, 1, -1, 1, 0.0), _rect_z(-2, 2, -2, 2, -1.0)]
    return _scene("two-planes", parts, _TINY_CAMERA)


_BUILTINS: dict[str, Callable[[], Scene]] = {
    "atrium": _build_atrium,
    "cornell": _build_cornell,
    "spheres": _build_spheres,
    "single-triangle": _build_single_triangle,
    "quad": _build_quad,
    "two-planes": _build_two_planes,
}
