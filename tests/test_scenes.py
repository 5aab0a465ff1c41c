"""Scene loading: built-in procedural scenes, real files, and bad input."""
from __future__ import annotations

import base64
import json
import time
from pathlib import Path

import numpy as np
import pytest

from lsbench.inputs.scene import Camera, Scene, SceneError
from lsbench.inputs.scenes import builtin_names, default_camera, load_scene

# name -> (min, max) triangle count
BUILTIN_COUNTS = {
    "atrium": (150_000, 300_000),
    "cornell": (30, 40),
    "spheres": (50_000, 200_000),
    "single-triangle": (1, 1),
    "quad": (2, 2),
    "two-planes": (4, 4),
    "adversarial": (2520, 2520),
    "mixed-scale": (3002, 3002),
}


def test_builtin_names_are_the_documented_ones():
    assert builtin_names() == list(BUILTIN_COUNTS)


@pytest.mark.parametrize("name", list(BUILTIN_COUNTS))
def test_builtin_loads_with_contract_types_and_counts(name):
    scene = load_scene(name)
    lo, hi = BUILTIN_COUNTS[name]
    assert lo <= scene.triangle_count <= hi
    assert scene.name == name and scene.source == f"builtin:{name}"
    assert scene.vertices.dtype == np.float32 and scene.vertices.shape[1] == 3
    assert scene.faces.dtype == np.uint32 and scene.faces.shape[1] == 3
    assert np.isfinite(scene.vertices).all()
    assert int(scene.faces.max()) < len(scene.vertices)
    assert isinstance(scene.camera, Camera)


@pytest.mark.parametrize("name", list(BUILTIN_COUNTS))
def test_builtin_is_deterministic(name):
    assert load_scene(name).content_hash == load_scene(name).content_hash


@pytest.mark.parametrize("name", list(BUILTIN_COUNTS))
def test_builtin_camera_looks_at_geometry(name):
    scene = load_scene(name)
    cam = scene.camera
    lo, hi = scene.bounds
    # the target lies inside the (slightly grown) bounds: the view is not of empty space
    grow = 0.01 * float(np.linalg.norm(hi - lo))
    target = np.asarray(cam.target)
    assert np.all(target >= lo - grow) and np.all(target <= hi + grow)
    assert np.linalg.norm(np.subtract(cam.target, cam.eye)) > 0


def test_atrium_is_fast_and_has_an_empty_middle():
    start = time.perf_counter()
    scene = load_scene("atrium")
    assert time.perf_counter() - start < 5.0
    # no triangle in the air above the courtyard's middle (floor excluded)
    centroids = scene.triangles.mean(axis=1)
    middle = ((np.abs(centroids[:, 0]) < 12) & (np.abs(centroids[:, 2]) < 2.5)
              & (centroids[:, 1] > 1.5))
    assert not middle.any()
    # detail varies by orders of magnitude: big flat walls next to tiny triangles
    tri = scene.triangles.astype(np.float64)
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1) / 2
    assert area.max() / np.median(area) > 1e4


def test_cornell_camera_is_in_front_of_the_open_side():
    scene = load_scene("cornell")
    assert scene.camera.eye[2] > scene.bounds[1][2]


def test_default_camera_sees_the_whole_bounding_box():
    verts = np.array([[0, 0, 0], [4, 0, 0], [0, 2, 0], [0, 0, 8]], dtype=np.float32)
    scene = Scene("t", verts, np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32), "test")
    cam = default_camera(scene)
    assert cam.up == (0.0, 1.0, 0.0) and cam.fov_deg == 60.0
    np.testing.assert_allclose(cam.target, [2, 1, 4], atol=1e-6)
    eye, forward = np.array(cam.eye), np.subtract(cam.target, cam.eye)
    forward /= np.linalg.norm(forward)
    corners = np.array([[x, y, z] for x in (0, 4) for y in (0, 2) for z in (0, 8)], dtype=float)
    to_corner = corners - eye
    cos = to_corner @ forward / np.linalg.norm(to_corner, axis=1)
    assert np.all(cos >= np.cos(np.radians(30)) - 1e-9)  # every corner inside the 60° cone


def test_default_camera_prefers_the_scene_camera():
    scene = load_scene("quad")
    assert default_camera(scene) is scene.camera


# --- real files -----------------------------------------------------------------------------


def _shared_scene(name: str) -> Path:
    from conftest import scene_path  # skips when absent, fails when CI is set

    return Path(scene_path(name))


@pytest.mark.parametrize("name, tris, verts", [("cornell_box.ply", 36, 72),
                                               ("teapot.ply", 6320, 3644)])
def test_shared_ply_counts_match_readme(name, tris, verts):
    path = _shared_scene(name)
    scene = load_scene(str(path))
    assert (scene.triangle_count, len(scene.vertices)) == (tris, verts)
    assert scene.name == path.stem and scene.source == str(path)
    assert scene.vertices.dtype == np.float32 and scene.faces.dtype == np.uint32
    assert scene.camera is None and isinstance(default_camera(scene), Camera)


def test_obj_keeps_file_order_degenerates_and_unreferenced_vertices(tmp_path):
    # two materials interleaved: trimesh would group faces by material and renumber them
    (tmp_path / "m.mtl").write_text("newmtl A\nKd 1 0 0\nnewmtl B\nKd 0 1 0\n")
    (tmp_path / "m.obj").write_text(
        "mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nv 9 9 9\n"
        "usemtl A\nf 1 2 3\nusemtl B\nf 2/1/1 4/1/1 3/1/1\nusemtl A\nf 1 1 2\n"
        "usemtl B\nf -5 -4 -2 -3\n")
    scene = load_scene(str(tmp_path / "m.obj"))
    assert len(scene.vertices) == 5  # vertex 5 is unreferenced and kept
    np.testing.assert_array_equal(
        scene.faces, [[0, 1, 2], [1, 3, 2], [0, 0, 1], [0, 1, 3], [0, 3, 2]])
    assert scene.bounds[1].tolist() == [1.0, 1.0, 0.0]  # unreferenced vertex not in bounds


def _write_gltf(path: Path, meshes: list[list[np.ndarray]], nodes: list[dict], roots: list[int]):
    """Minimal glTF: one triangle per primitive; meshes[i] lists each primitive's 3 corners."""
    blob, views, accessors, gltf_meshes = b"", [], [], []
    for prims in meshes:
        primitives = []
        for corners in prims:
            data = np.asarray(corners, dtype=np.float32).tobytes()
            views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data)})
            accessors.append({"bufferView": len(views) - 1, "componentType": 5126, "count": 3,
                              "type": "VEC3", "min": np.min(corners, 0).tolist(),
                              "max": np.max(corners, 0).tolist()})
            primitives.append({"attributes": {"POSITION": len(accessors) - 1}})
            blob += data
        gltf_meshes.append({"primitives": primitives})
    uri = "data:application/octet-stream;base64," + base64.b64encode(blob).decode()
    path.write_text(json.dumps({
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": roots}], "nodes": nodes,
        "meshes": gltf_meshes, "buffers": [{"byteLength": len(blob), "uri": uri}],
        "bufferViews": views, "accessors": accessors}))


def test_gltf_concatenates_nodes_and_primitives_in_file_order_without_welding(tmp_path):
    def tri(x):  # a triangle at x; all share corner values so welding would be visible
        return [[x, 0, 0], [x + 1, 0, 0], [x, 1, 0]]

    meshes = [[tri(0)], [tri(1), tri(2)], [tri(3)], [tri(4)]]
    # file order, depth first: node0(mesh0) -> child node1 (mesh1, 2 primitives) -> node2
    # (mesh2); root node3 (mesh3)
    nodes = [{"name": "n0", "mesh": 0, "children": [1, 2]}, {"mesh": 1}, {"mesh": 2},
             {"name": "n3", "mesh": 3}]
    _write_gltf(tmp_path / "s.gltf", meshes, nodes, roots=[0, 3])
    scene = load_scene(str(tmp_path / "s.gltf"))
    assert scene.triangle_count == 5 and len(scene.vertices) == 15
    np.testing.assert_array_equal(scene.triangles[:, 0, 0], [0, 1, 2, 3, 4])


# --- bad input ------------------------------------------------------------------------------


def _bad(tmp_path: Path, name: str, content: bytes | str | None) -> str:
    path = tmp_path / name
    if isinstance(content, str):
        path.write_text(content)
    elif content is not None:
        path.write_bytes(content)
    return str(path)


@pytest.mark.parametrize("name, content, words", [
    ("missing.ply", None, "not found"),
    ("garbage.ply", bytes(range(256)) * 4, "cannot read"),
    ("empty.obj", "", "no triangles"),
    ("points.obj", "v 0 0 0\nv 1 0 0\n", "no triangles"),
    ("nan.obj", "v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n", "NaN/Inf"),
    ("inf.obj", "v 0 0 0\nv 1 inf 0\nv 0 1 0\nf 1 2 3\n", "NaN/Inf"),
    ("range.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 9\n", "out of range"),
    ("negrange.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 -4\n", "out of range"),
    ("text.obj", "v 0 zero 0\n", "cannot parse"),
    ("range.ply", "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
     "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
     "0 0 0\n1 0 0\n0 1 0\n3 0 1 5\n", "out of range"),
])
def test_bad_files_raise_one_line_scene_error(tmp_path, name, content, words):
    with pytest.raises(SceneError) as info:
        load_scene(_bad(tmp_path, name, content))
    message = str(info.value)
    assert words in message and "\n" not in message


def test_unknown_builtin_lists_the_valid_names():
    with pytest.raises(SceneError) as info:
        load_scene("atriun")
    assert all(name in str(info.value) for name in builtin_names())


def test_directory_is_not_a_scene(tmp_path):
    with pytest.raises(SceneError, match="not a file"):
        load_scene(str(tmp_path))
