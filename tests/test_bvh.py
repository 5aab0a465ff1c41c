"""`bvh` and `bvh-ls` (issue 15): the device build is a valid BVH (checked against a numpy walk of
the buffers it leaves), its Morton sort is a sort, and the traversals agree with Embree on the
built-in scenes and Sponza, closest and any hit, on both backends."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lsbench import backends
from lsbench.backends import BuildParams
from lsbench.backends.structures import bvh
from lsbench.inputs.rays import make_rays, primary_rays
from lsbench.inputs.scene import Camera, Scene
from lsbench.inputs.scenes import load_scene
from lsbench.oracle.classifier import judge_hits
from lsbench.oracle.embree import embree_closest

from conftest import scene_path
from helpers import check_structure, explain

SPONZA_CAMERA = Camera(eye=(1100, 180, -40), target=(-900, 420, 40), up=(0, 1, 0), fov_deg=65)


def _read_tree(built):
    """The nodes as the float layouts hold them: (n, 6, W) planes lo.x, hi.x, lo.y, hi.y, lo.z, hi.z
    of slots 0..W-1, (n, 2, W) refs and counts (float8: a node's two records side by side, W = 8;
    else W = 4); quantized nodes decoded in float32 as the traversal
    decodes them (origin + q * step, shaders/common/bvh.h), with (n, 3) steps; voxel_tris."""
    d = built.device
    n_nodes = built.stats["nodes"]
    tris = d.read(built.buffers["voxel_tris"], np.uint32)
    if built.stats["node_layout"] != "quantized":
        r = bvh.NODE_WIDTHS[built.stats["node_layout"]] // 4  # 4-slot records per node
        nodes = d.read(built.buffers["bvh_nodes"], np.float32, 24 * r * n_nodes).reshape(n_nodes, r, 6, 4)
        links = d.read(built.buffers["bvh_links"], np.uint32, 8 * r * n_nodes).reshape(n_nodes, r, 2, 4)
        return (nodes.transpose(0, 2, 1, 3).reshape(n_nodes, 6, 4 * r),
                links.transpose(0, 2, 1, 3).reshape(n_nodes, 2, 4 * r), tris, None)
    q = d.read(built.buffers["bvh_qnodes"], np.uint32, 16 * n_nodes).reshape(n_nodes, 4, 4)
    origin = q[:, 0, :3].copy().view(np.float32)
    exponents = (q[:, 0, 3:4] >> np.array([0, 8, 16], np.uint32)) & 0xFF
    assert np.all((exponents >= 1) & (exponents <= 254)) and np.all(q[:, 2, 3] == 0)
    steps = (exponents << 23).astype(np.uint32).view(np.float32)
    byte = lambda w: ((w[:, None] >> np.array([0, 8, 16, 24], np.uint32)) & 0xFF).astype(np.float32)
    words = [q[:, 1, 0], q[:, 1, 1], q[:, 1, 2], q[:, 1, 3], q[:, 2, 0], q[:, 2, 1]]
    nodes = np.stack([(origin[:, k // 2, None] + byte(w) * steps[:, k // 2, None]).astype(np.float32)
                      for k, w in enumerate(words)], axis=1)
    links = np.stack([q[:, 3], byte(q[:, 2, 2]).astype(np.uint32)], axis=1)
    return nodes, links, tris, steps


def _slot_box(nodes, node, slot):
    box = nodes[node, :, slot]  # lo.x, hi.x, lo.y, hi.y, lo.z, hi.z
    return box[0::2], box[1::2]


NONE = 0xFFFFFFFF


def check_tree(built, scene, leaf_size):
    """Walk the device's wide nodes from the root: every node reached once, every triangle in
    exactly one leaf, no leaf over leaf_size, the depth as the build says (the traversal's stack is
    sized from it). Float nodes: every slot's box holds the boxes of its node's slots, and a leaf's
    is its triangles' (exact float min/max: no tolerance). Quantized nodes (check_quantized): every
    slot's box, as the traversal decodes it, holds all triangles below it, within one step of
    their box. Returns the leaf sizes."""
    nodes, links, tris, steps = _read_tree(built)
    quantized = steps is not None
    width = nodes.shape[2]
    assert width == built.stats["width"] == bvh.NODE_WIDTHS[built.stats["node_layout"]]
    n = scene.triangle_count
    assert np.array_equal(np.sort(tris), np.arange(n, dtype=np.uint32)), "voxel_tris is no permutation"
    triangles = scene.triangles.astype(np.float32)
    seen_nodes = np.zeros(len(nodes), np.int64)
    covered = np.zeros(n, np.int64)
    leaf_sizes = []
    stack = [(0, 0)]
    deepest = 0
    while stack:
        node, depth = stack.pop()
        deepest = max(deepest, depth)
        seen_nodes[node] += 1
        used = [s for s in range(width) if links[node, 0, s] != NONE]
        assert used == list(range(len(used))) and (len(used) >= 2 or len(nodes) == 1), (node, used)
        for slot in used:
            ref, count = int(links[node, 0, slot]), int(links[node, 1, slot])
            lo, hi = _slot_box(nodes, node, slot)
            if count == 0:  # a node: this box holds its slots' boxes
                for s in range(width):
                    if links[ref, 0, s] != NONE and not quantized:  # quantized: check_quantized below
                        clo, chi = _slot_box(nodes, ref, s)
                        assert np.all(lo <= clo) and np.all(chi <= hi), (node, slot, ref)
                stack.append((ref, depth + 1))
            else:
                assert count <= leaf_size
                leaf_sizes.append(count)
                ids = tris[ref:ref + count]
                covered[ids] += 1
                v = triangles[ids].reshape(-1, 3)
                assert quantized or (np.array_equal(lo, v.min(0)) and np.array_equal(hi, v.max(0))), \
                    "leaf box is not tight"
    assert np.all(seen_nodes == 1), "a node is unreachable or reached twice (buffers sized exactly)"
    assert np.all(covered == 1), f"{np.count_nonzero(covered != 1)} triangles not in exactly one leaf"
    assert built.stats["leaves"] == len(leaf_sizes)
    # bvh.py's stack bound: wide levels = binary depth // (levels dropped + 1) + 1
    assert deepest + 1 <= bvh.wide_depth(built.stats)
    if quantized:
        check_quantized(nodes, links, tris, steps, triangles)
    return np.array(leaf_sizes)


def check_quantized(nodes, links, tris, steps, triangles):
    """Quantized nodes: each slot's decoded box holds the exact box of every triangle below it
    (leaf or subtree), and lies within one step of it on every side (the build takes the tightest
    q), or two float32 ulps where a step is finer; each node's steps are the smallest powers of two
    that span its box in 255 steps (up to the float32 rounding the build's loop settles, or the
    least step 2^-126)."""
    exact = {}

    def subtree_box(node):  # the exact (lo, hi) of all triangles below `node`
        if node not in exact:
            boxes = [slot_exact(node, s) for s in range(4) if links[node, 0, s] != NONE]
            exact[node] = (np.min([b[0] for b in boxes], 0), np.max([b[1] for b in boxes], 0))
        return exact[node]

    def slot_exact(node, s):
        ref, count = int(links[node, 0, s]), int(links[node, 1, s])
        if count == 0:
            return subtree_box(ref)
        v = triangles[tris[ref:ref + count]].reshape(-1, 3)
        return v.min(0), v.max(0)

    for node in range(len(nodes)):
        used = [s for s in range(4) if links[node, 0, s] != NONE]
        boxes = [slot_exact(node, s) for s in used]
        node_lo, node_hi = np.min([b[0] for b in boxes], 0), np.max([b[1] for b in boxes], 0)
        step = steps[node]
        span = (node_hi.astype(np.float64) - node_lo) / 255.0
        assert np.all((step <= 2.0 * span * (1 + 1e-6)) | (step == np.float32(2.0 ** -126)) |
                      (node_lo + np.float32(255.0) * (step / np.float32(2.0)) < node_hi)), (node, step, span)
        for s, (lo, hi) in zip(used, boxes):
            qlo, qhi = _slot_box(nodes, node, s)
            assert np.all(qlo <= lo) and np.all(qhi >= hi), ("a quantized box misses its triangles", node, s)
            # origin + q * step rounds once in float32: where a step is below the planes' ulp (tiny
            # triangles 1e5 out), two ulps are the finest a conservative plane can sit
            slack_lo = np.maximum(step, 2 * np.spacing(np.abs(lo)))
            slack_hi = np.maximum(step, 2 * np.spacing(np.abs(hi)))
            assert np.all(qlo > lo - slack_lo) and np.all(qhi < hi + slack_hi), ("a quantized box is not tight", node, s)


@pytest.mark.parametrize("layout", list(bvh.NODE_LAYOUTS))
@pytest.mark.parametrize("scene_name,leaf_size,quality,hierarchy", [
    ("cornell", 8, "treelet", "binned"), ("cornell", 64, "sah", "binned"), ("cornell", 64, "none", "morton"),
    ("single-triangle", 1, "treelet", "binned"), ("two-planes", 1, "treelet", "binned"), ("spheres", 4, "sah", "binned"),
    ("spheres", 4, "treelet", "morton"), ("spheres", 1, "treelet", "binned"), ("spheres", 16, "plain-treelet", "morton"),
    ("spheres", 16, "plain-treelet", "binned"), ("spheres", 255, "none", "binned"), ("awkward", 2, "treelet", "binned")])
def test_the_device_build_is_a_valid_bvh(device, scene_name, leaf_size, quality, hierarchy, layout):
    scene = _awkward_scene() if scene_name == "awkward" else load_scene(scene_name)
    if scene_name == "spheres":  # a few hundred triangles of it
        scene = _subset(scene, 600)
    built = backends.build(device, "bvh", scene, BuildParams(resolution=(1, 1, 1), leaf_size=leaf_size, options={
        "bvh_quality": quality, "bvh_nodes": layout, "bvh_hierarchy": hierarchy}))
    try:
        assert built.stats["node_layout"] == layout
        sizes = check_tree(built, scene, leaf_size)
        assert built.memory_bytes == bvh.NODE_LAYOUTS[layout] * built.stats["nodes"] + (4 + 48) * scene.triangle_count
        # The trace's records, in leaf order (LIST_ORDER_RECORDS): record i is voxel_tris[i]'s.
        tris = built.device.read(built.buffers["voxel_tris"], np.uint32)
        records = built.device.read(built.buffers["tri_verts"], np.float32)
        assert np.array_equal(records.reshape(-1, 12), backends.triangle_records(scene).reshape(-1, 12)[tris])
        # Each quality pass only takes a change that lowers the SAH cost: the collapse chooses per
        # node, the treelets rebuild only where cheaper; on the spheres' Morton tree the
        # restructuring gains (their binned SAH tree leaves it little: 0 to 2 %).
        stats = built.stats
        assert stats["hierarchy"] == hierarchy
        assert stats["sah_cost"] <= stats["sah_cost_collapse"] * (1 + 1e-6)
        assert stats["sah_cost_collapse"] <= stats["sah_cost_plain"] * (1 + 1e-6)
        if quality.endswith("treelet") and scene_name == "spheres" and hierarchy == "morton":
            assert stats["sah_cost"] < 0.95 * stats["sah_cost_collapse"]
        if scene.triangle_count <= leaf_size and quality == "none":  # one node, one leaf of all
            assert built.stats["nodes"] == 1 and list(sizes) == [scene.triangle_count]
    finally:
        built.release()


@pytest.mark.parametrize("quality", ["treelet", "plain-treelet"])
def test_restructuring_in_waves_builds_the_climbs_tree(device, monkeypatch, quality):
    """The treelet restructuring runs as one climb per primitive where work items run one after the
    other (PoCL) and as waves of the nodes whose subtrees are done where they run in SIMD lanes
    (llvmpipe, GPUs; bvh.py _restructure_in_waves). Both on this device: the same tree, bit for
    bit, and one the restructuring changed (on the Morton tree, which it changes most)."""
    scene = _subset(load_scene("spheres"), 600)
    trees, stats = [], []
    for serial in (True, False):
        monkeypatch.setattr(device, "serial_work_items", serial)
        built = backends.build(device, "bvh", scene, BuildParams(resolution=(1, 1, 1), leaf_size=4, options={
            "bvh_quality": quality, "bvh_nodes": "float", "bvh_hierarchy": "morton"}))
        trees.append({name: device.read(buf, np.uint8) for name, buf in built.buffers.items()})
        stats.append(built.stats)
        built.release()
    assert trees[0].keys() == trees[1].keys()
    for name in trees[0]:
        np.testing.assert_array_equal(trees[0][name], trees[1][name], err_msg=name)
    assert stats[0]["sah_cost"] == stats[1]["sah_cost"] < 0.95 * stats[1]["sah_cost_collapse"]


def test_plain_leaves_fill_to_the_leaf_size(device):
    """bvh_quality = "none": every subtree of at most leaf_size triangles is one leaf, so some leaf
    holds more than half of it (a Karras node of more triangles splits into two smaller ones)."""
    scene = _subset(load_scene("spheres"), 600)
    built = backends.build(device, "bvh", scene, BuildParams(resolution=(1, 1, 1), leaf_size=16,
                                                              options={"bvh_quality": "none"}))
    try:
        sizes = check_tree(built, scene, 16)
        assert sizes.max() > 8 and built.stats["sah_cost"] == built.stats["sah_cost_plain"]
    finally:
        built.release()


def _subset(scene, count):
    import dataclasses

    return dataclasses.replace(scene, faces=np.ascontiguousarray(scene.faces[:count]), _hash=None)


def test_morton_codes_are_sorted_stably(device):
    """Build steps 1-2 on their own: the device's codes match a numpy float32 reference and the
    radix sort returns them in the order of numpy's stable argsort."""
    scene = _subset(load_scene("spheres"), 700)  # 3 sort chunks of 256
    n = scene.triangle_count
    geometry, sb, u = _build_inputs(device, scene)
    keys, ids = bvh.sort_by_morton_code(device, sb, n, u)
    try:
        keys_np = device.read(keys, np.uint32, n)
        ids_np = device.read(ids, np.uint32, n)
    finally:
        for b in (keys, ids, *sb.values()):
            device.release(b)
    reference = _morton_reference(scene, geometry)
    assert np.array_equal(keys_np, reference[ids_np]), "a code differs from the numpy reference"
    assert np.array_equal(ids_np, np.argsort(reference, kind="stable"))
    assert len(np.unique(reference)) > n // 2  # codes that say something


def _awkward_scene():
    """Triangles that bin badly: 100 copies of one triangle (every centroid equal: the split at
    half, in a large node and in a small one), 80 slivers along x, 60 degenerate ones (a point, a
    segment), a far cluster (1e5 out) of 90 tiny ones, and 70 scattered."""
    rng = np.random.default_rng(7)
    tris = [np.tile([[0, 0, 0], [1, 0, 0], [0, 1, 0]], (100, 1, 1)).astype(np.float64)]
    x = rng.uniform(-5, 5, 80)
    tris.append(np.stack([np.stack([x, np.zeros(80), np.zeros(80)], 1), np.stack([x + 3, np.zeros(80), np.zeros(80)], 1),
                          np.stack([x, np.full(80, 1e-4), np.zeros(80)], 1)], 1))
    p = rng.uniform(-3, 3, (60, 1, 3))
    tris.append(np.concatenate([p, p, p + np.where(np.arange(60)[:, None, None] % 2 == 0, 0, 1) * [[1, 2, 0]]], 1))
    tris.append(1e5 + rng.uniform(0, 1e-2, (90, 1, 3)) + rng.uniform(0, 1e-3, (90, 3, 3)))
    tris.append(rng.uniform(-10, 10, (70, 1, 3)) + rng.uniform(-1, 1, (70, 3, 3)))
    v = np.concatenate(tris).reshape(-1, 3).astype(np.float32)
    return Scene("awkward", v, np.arange(len(v), dtype=np.uint32).reshape(-1, 3), "test:awkward")


def _build_inputs(device, scene):
    """What a build step run on its own takes: the geometry, the scene's vertex and face buffers
    (the caller releases them) and the build's uniforms."""
    geometry = backends.geometry_for("bvh", scene, BuildParams(resolution=(1, 1, 1)))
    bvh.prepare(device)
    sb = {"vertices": device.upload("vertices", np.ascontiguousarray(scene.vertices, np.float32).ravel()),
          "faces": device.upload("faces", np.ascontiguousarray(scene.faces, np.uint32).ravel())}
    u = dict(geometry.uniforms(), bvh_n=scene.triangle_count, bvh_leaf_size=1, bvh_sah=1, bvh_node_count=0)
    return geometry, sb, u


def _binned_tree(device, scene):
    """bvh.binned_hierarchy on its own: (order, children, ranges, parents) as numpy arrays."""
    n = scene.triangle_count
    _, sb, u = _build_inputs(device, scene)
    tree = {"bvh_children": device.alloc("bvh_children", 8 * (n - 1)),
            "bvh_ranges": device.alloc("bvh_ranges", 8 * (n - 1)), "bvh_parents": device.alloc("bvh_parents", 4 * (2 * n - 1))}
    order, rounds = bvh.binned_hierarchy(device, sb, n, u, tree)
    try:
        assert rounds >= 1
        return (device.read(order, np.uint32, n), device.read(tree["bvh_children"], np.uint32, 2 * (n - 1)).reshape(-1, 2),
                device.read(tree["bvh_ranges"], np.uint32, 2 * (n - 1)).reshape(-1, 2),
                device.read(tree["bvh_parents"], np.uint32, 2 * n - 1))
    finally:
        for b in (order, *tree.values(), *sb.values()):
            device.release(b)


def test_the_binned_hierarchy_bins_in_batches_as_at_once(device, monkeypatch):
    """Where a level's large nodes' bins overflow one buffer they are binned in batches
    (bvh.sah_batch): one node at a time gives the same tree, bit for bit."""
    scene = _subset(load_scene("spheres"), 600)
    whole = _binned_tree(device, scene)
    monkeypatch.setattr(bvh, "sah_batch", lambda device, most: 1)
    for name, a, b in zip(("order", "children", "ranges", "parents"), whole, _binned_tree(device, scene)):
        np.testing.assert_array_equal(a, b, err_msg=name)


@pytest.mark.parametrize("scene_name", ["spheres", "awkward"])
def test_the_binned_hierarchy_splits_at_the_least_cost_boundary(device, scene_name):
    """Build 3, "binned", on its own (bvh.binned_hierarchy) against a numpy reference: a binary
    tree over ranges of a permutation, named as Karras names them (the fit reads it as EMIT's);
    every split separates its children's centroids by a plane, and costs no more than the best
    boundary of the reference's bins (32 per axis from 64 triangles up, else 16: the centroids'
    extent divided in float32 as bvh.h does), SA(L) n_L + SA(R) n_R; where all centroids
    coincide it splits at half."""
    scene = _subset(load_scene("spheres"), 600) if scene_name == "spheres" else _awkward_scene()
    n = scene.triangle_count
    order_np, children, ranges, parents = _binned_tree(device, scene)
    assert np.array_equal(np.sort(order_np), np.arange(n, dtype=np.uint32)), "voxel_tris is no permutation"
    prim = np.uint32(0x80000000)
    t = scene.triangles.astype(np.float32)[order_np]
    lo, hi = t.min(axis=1), t.max(axis=1)
    centroid = (lo + hi) * np.float32(0.5)

    def area(a, b):
        e = np.maximum(b.astype(np.float64) - a, 0.0)
        return 2.0 * (e[..., 0] * e[..., 1] + e[..., 1] * e[..., 2] + e[..., 2] * e[..., 0])

    seen, leaves, medians = np.zeros(n - 1, int), np.zeros(n, int), 0
    assert parents[0] == NONE
    stack = [0]
    while stack:
        node = stack.pop()
        seen[node] += 1
        first, last = (int(x) for x in ranges[node])
        (left, right), spans = children[node], []
        for side, c in enumerate((left, right)):
            if c & prim:
                pos = int(c & ~prim)
                leaves[pos] += 1
                assert parents[n - 1 + pos] == node
                spans.append((pos, pos))
            else:
                assert parents[c] == node
                stack.append(int(c))
                spans.append(tuple(int(x) for x in ranges[c]))
        assert spans[0][0] == first and spans[0][1] + 1 == spans[1][0] and spans[1][1] == last, (node, spans)
        split = spans[0][1]
        c, count = centroid[first:last + 1], last - first + 1
        if np.all(c == c[0]):
            assert split - first + 1 == count // 2
            medians += 1
            continue
        cl, cr = centroid[first:split + 1], centroid[split + 1:last + 1]
        assert np.any(cl.max(axis=0) < cr.min(axis=0)), ("no plane separates the children's centroids", node)
        cost = area(lo[first:split + 1].min(0), hi[first:split + 1].max(0)) * len(cl) + \
            area(lo[split + 1:last + 1].min(0), hi[split + 1:last + 1].max(0)) * len(cr)
        bins = 32 if count >= bvh.SAH_LARGE else 16
        best = np.inf
        for a in range(3):
            cmin, cmax = c[:, a].min(), c[:, a].max()
            if not cmax > cmin:
                continue
            scale = np.float32(bins) / (cmax - cmin)
            k = np.minimum(np.maximum((c[:, a] - cmin) * scale, np.float32(0)), np.float32(bins - 1)).astype(int)
            for b in range(bins - 1):
                is_left = k <= b
                if 0 < is_left.sum() < count:
                    sl = np.arange(first, last + 1)[is_left]
                    sr = np.arange(first, last + 1)[~is_left]
                    best = min(best, area(lo[sl].min(0), hi[sl].max(0)) * len(sl) + area(lo[sr].min(0), hi[sr].max(0)) * len(sr))
        # the device prices the boundaries in float32: two near-equal costs may order either way
        # within its rounding (a few ulps, 2^-24 each)
        assert cost <= best * (1 + 8 * 2.0 ** -24), (node, count, cost, best)
    assert np.all(seen == 1) and np.all(leaves == 1), "a node or triangle reached not exactly once"
    if scene_name == "awkward":
        assert medians >= 2  # the copies split at half in a large node and again in a small one


def _morton_reference(scene, geometry):
    t = scene.triangles.astype(np.float32)
    g = (t - np.asarray(geometry.origin, np.float32)) * (1.0 / np.asarray(geometry.voxel_size)).astype(np.float32)
    res = np.asarray(geometry.resolution, np.float32)
    c = (g[:, 0] + g[:, 1] + g[:, 2]) * np.float32(1.0 / 3.0) / res * np.float32(1024.0)
    q = np.clip(c, 0, 1023).astype(np.uint32)

    def spread(x):
        out = np.zeros_like(x)
        for b in range(10):
            out |= ((x >> b) & 1) << (3 * b)
        return out

    return spread(q[:, 0]) | (spread(q[:, 1]) << 1) | (spread(q[:, 2]) << 2)


def _agree(scene, rays, built):
    hits = backends.trace(built, rays)
    ref_p, ref_t = embree_closest(scene, rays)
    acc, cl = judge_hits(scene, rays, hits.prim_ids, hits.distances, ref_p, ref_t)
    assert cl.unexplained == 0, (acc, cl)
    return hits, acc


@pytest.mark.parametrize("structure", ["bvh", "bvh-ls"])
@pytest.mark.parametrize("scene_name", ["atrium", "spheres", "sponza"])
def test_hits_agree_with_embree(device, structure, scene_name):
    """Closest hits of primary rays, and any hits of shadow rays, on the big scenes."""
    if scene_name == "sponza":
        from lsbench.inputs.scenes import load_scene as load

        scene, camera = load(scene_path("sponza.ply")), SPONZA_CAMERA
    else:
        scene, camera = load_scene(scene_name), None
    params = BuildParams(resolution=(1, 1, 1), ls_n=1 if structure == "bvh-ls" else 0,
                         ls_min_candidates=8 if structure == "bvh-ls" else 0)
    built = backends.build(device, structure, scene, params)
    try:
        size = 48
        _, acc = _agree(scene, primary_rays(scene, size, size, camera), built)
        assert acc.agreement >= 0.999
        lo, hi = scene.bounds
        light = 0.1 * float(np.linalg.norm(np.asarray(hi, np.float64) - lo))
        shadow = make_rays("shadow", scene, 24, 24, camera, {"light_size": light, "samples": 1})
        hits, acc = _agree(scene, shadow, built)
        occluded = hits.prim_ids >= 0
        assert 0.0 < occluded.mean() < 1.0 and acc.wrong == acc.distance == 0
        if structure == "bvh-ls":
            assert built.stats["linespace_leaves"] > 0 and built.stats["linespace_skipped_leaves"] > 0
    finally:
        built.release()


@pytest.mark.parametrize("structure,backend,width", [("bvh", "opencl", 8), ("bvh", "opencl", 16), ("bvh", "glsl", 4),
                                                     ("bvh-ls", "opencl", 8), ("bvh-ls", "glsl", 4)])
def test_packets_find_the_single_ray_hits(monkeypatch, structure, backend, width):
    """The packet traversal (`width` rays per work item, shaders/common/bvh.h BVH_PACKET: OpenCL's
    float8 / float16 lanes, GLSL's vec4) against the single-ray kernel and Embree: a ray count that
    leaves the last packet part empty, rays from inside the scene in every direction (lanes with
    different dominant axes), rays with a tmin and a per-ray tmax, and any-hit shadow rays. The
    same closest distance per ray; another triangle only at a tie (a box entry rounded past the hit
    leaves the single ray's walk one tie short), which Embree's check explains. bvh-ls: its leaves'
    Line Spaces looked up lane by lane."""
    device = backends.get_device(backend)
    scene = load_scene("atrium")
    line_space = {"ls_n": 2, "ls_min_candidates": 4} if structure == "bvh-ls" else {}
    built = backends.build(device, structure, scene, BuildParams(resolution=(1, 1, 1), **line_space))
    if structure == "bvh-ls":
        assert built.stats["linespace_leaves"] > 0
    lo, hi = scene.bounds
    light = 0.1 * float(np.linalg.norm(np.asarray(hi, np.float64) - lo))
    primary = primary_rays(scene, 37, 29)
    rng = np.random.default_rng(5)
    clipped = dataclasses.replace(primary, name="clipped", tmin=0.25 * light,
                                  tmax=rng.uniform(0.5, 8.0, primary.count).astype(np.float32) * light,
                                  width=0, height=0, _hash=None)
    sets = [primary, clipped, make_rays("incoherent", scene, 23, 19, None, {}),
            make_rays("shadow", scene, 21, 17, None, {"light_size": light, "samples": 1})]
    try:
        for rays in sets:
            monkeypatch.setenv("LSBENCH_PACKET", "1")
            single = backends.trace(built, rays)
            monkeypatch.setenv("LSBENCH_PACKET", str(width))
            packed = backends.trace(built, rays)
            assert (single.packet, packed.packet) == (1, width)
            assert np.array_equal(single.prim_ids >= 0, packed.prim_ids >= 0), rays.name
            if rays.query == "closest":
                same = single.prim_ids == packed.prim_ids
                assert np.array_equal(single.distances[same], packed.distances[same]), rays.name
                assert same.mean() > 0.99, rays.name
                np.testing.assert_allclose(packed.distances, single.distances, rtol=1e-6, err_msg=rays.name)
            ref_p, ref_t = embree_closest(scene, rays)
            _, cl = judge_hits(scene, rays, packed.prim_ids, packed.distances, ref_p, ref_t)
            assert cl.unexplained == 0, (rays.name, cl)
        work = backends.trace(built, primary, work=True).work  # counted: each lane its packet's work
        assert work.shape == (primary.count, 4) and np.all(work[:, 0] >= 1) and np.all(work[:, 0] <= built.stats["nodes"])
    finally:
        built.release()


@pytest.mark.parametrize("backend,width", [("opencl", 8), ("glsl", 4)])
@pytest.mark.parametrize("scene_name,structure", [("cornell", "bvh"), ("spheres", "bvh"), ("spheres", "bvh-ls")])
def test_packets_on_adversarial_rays_are_explained(monkeypatch, scene_name, structure, backend, width):
    """Adversarial rays (along edges and faces, through vertices, grazing) forced into packets: a
    lane may now test triangles its own walk's boxes ruled out (a box face the ray lies in), and
    every answer must still be one Embree's check explains (the grazing-vertex distance of
    geometry.h's triangle_plane_t came from here)."""
    monkeypatch.setenv("LSBENCH_PACKET", str(width))
    scene = load_scene(scene_name)
    out = check_structure(backends.get_device(backend), structure, scene, (1, 1, 1), ls_n=2 if structure == "bvh-ls" else 0)
    assert out["hits"].packet == width and out["unexplained"] == [], explain(out)


def test_packets_for_coherent_rays_on_cpu_devices_refills_for_rays_without_locality(device, monkeypatch):
    """backends.packet_width: primary rays go in packets on PoCL (a CPU device, Device.packet_width
    8) and llvmpipe (4 per SIMD lane); incoherent and ambient-occlusion rays, llvmpipe's any-hit
    rays, GPUs, a sliced trace and structures without a packet traversal take one ray per work item.
    backends.refill_rays: incoherent rays (no locality) are refilled where work items run in SIMD
    lanes (llvmpipe), REFILL_RAYS per work item; an image's rays, secondary
    rays from primary hits, PoCL (work items one at a time), a sliced trace and structures without
    the kernel take one ray per work item. A bad LSBENCH_PACKET or LSBENCH_REFILL is one line
    naming it."""
    monkeypatch.delenv("LSBENCH_PACKET", raising=False)
    monkeypatch.delenv("LSBENCH_REFILL", raising=False)
    scene = load_scene("spheres")
    built = backends.build(device, "bvh", scene, BuildParams(resolution=(1, 1, 1)))
    grid_built = backends.build(device, "grid", scene, BuildParams(resolution=(8, 8, 8)))
    try:
        primary = primary_rays(scene, 32, 32)
        incoherent = make_rays("incoherent", scene, 32, 32, None, {})
        ao = make_rays("ao", scene, 32, 32, None, {"samples": 4})
        assert backends.ray_coherence(primary, 8) > backends.PACKET_MIN_COHERENCE > backends.ray_coherence(ao, 8)
        expect = {"opencl": 8, "glsl": 4}[device.backend] if device.serial_work_items or getattr(device, "is_llvmpipe", False) else 1
        assert device.packet_width == expect
        assert backends.packet_width(built, primary, None) == expect
        assert backends.packet_width(built, incoherent, None) == 1
        assert backends.packet_width(built, ao, None) == 1
        assert backends.packet_width(built, primary, 1000) == 1  # bounded slices: one ray per item
        shadow = make_rays("shadow", scene, 32, 32, None, {})  # any hit: packets on PoCL only
        if "any" not in device.packet_queries:
            assert backends.packet_width(built, shadow, None) == 1
        assert backends.packet_width(grid_built, primary, None) == 1
        assert backends.trace(built, primary).packet == expect
        # bvh-ls: packets in SIMD lanes only (StructureInfo.serial_packets)
        ls_built = backends.build(device, "bvh-ls", scene, BuildParams(resolution=(1, 1, 1), ls_n=1))
        try:
            assert backends.packet_width(ls_built, primary, None) == (1 if device.serial_work_items else expect)
            assert backends.packet_width(ls_built, incoherent, None) == 1
        finally:
            ls_built.release()
        refill = 1 if device.serial_work_items else backends.REFILL_RAYS
        assert backends.refill_rays(built, incoherent, None) == refill
        assert backends.refill_rays(built, primary, None) == 1
        assert backends.refill_rays(built, ao, None) == 1
        assert backends.refill_rays(built, incoherent, 1000) == 1  # bounded slices
        assert backends.refill_rays(grid_built, incoherent, None) == 1
        hits = backends.trace(built, incoherent)
        assert hits.refill == refill
        monkeypatch.setenv("LSBENCH_REFILL", "0")
        with pytest.raises(ValueError, match="LSBENCH_REFILL must be auto or a whole number of rays >= 1, got '0'"):
            backends.trace(built, incoherent)
        monkeypatch.setenv("LSBENCH_PACKET", "4" if device.backend == "opencl" else "8")
        allowed = "auto, 1, 8, 16 on opencl, got '4'" if device.backend == "opencl" else "auto, 1, 4 on glsl, got '8'"
        with pytest.raises(ValueError, match=f"LSBENCH_PACKET must be one of {allowed}"):
            backends.trace(built, primary)
    finally:
        built.release()
        grid_built.release()


@pytest.mark.parametrize("structure", ["bvh", "bvh-ls"])
def test_refilled_lanes_find_the_one_ray_hits_and_work(device, monkeypatch, structure):
    """The refilled kernel (bvh.h BVH_REFILL: a work item's rays one after the other, a lane starting
    its next ray where its last one ended) against one ray per work item, on both devices: every
    ray's hit, distance and counted visits and tests identical, for closest and any hit, renderer
    and adversarial rays, at 3 rays per item (ray counts that leave the last item's rays part
    taken) and at REFILL_RAYS; then Embree's check."""
    scene = load_scene("atrium")
    params = BuildParams(resolution=(1, 1, 1), ls_n=2 if structure == "bvh-ls" else 0)
    built = backends.build(device, structure, scene, params)
    lo, hi = scene.bounds
    light = 0.1 * float(np.linalg.norm(np.asarray(hi, np.float64) - lo))
    sets = [make_rays("incoherent", scene, 23, 19, None, {}), make_rays("adversarial", scene, 16, 16, None, {}),
            make_rays("shadow", scene, 21, 17, None, {"light_size": light, "samples": 1}),
            make_rays("diffuse", scene, 19, 13, None, {})]
    try:
        for rays in sets:
            monkeypatch.setenv("LSBENCH_PACKET", "1")
            monkeypatch.setenv("LSBENCH_REFILL", "1")
            one = backends.trace(built, rays, work=True)
            for per_item in (3, backends.REFILL_RAYS):
                monkeypatch.setenv("LSBENCH_REFILL", str(per_item))
                refilled = backends.trace(built, rays, work=True)
                assert (one.refill, refilled.refill) == (1, per_item), rays.name
                assert np.array_equal(one.prim_ids, refilled.prim_ids), (rays.name, per_item)
                assert np.array_equal(one.distances, refilled.distances), (rays.name, per_item)
                assert np.array_equal(one.work[:, :3], refilled.work[:, :3]), (rays.name, per_item)
            ref_p, ref_t = embree_closest(scene, rays)
            _, cl = judge_hits(scene, rays, refilled.prim_ids, refilled.distances, ref_p, ref_t)
            assert cl.unexplained == 0, (rays.name, cl)
    finally:
        built.release()


def test_a_refilled_trace_the_driver_cut_runs_again_one_ray_per_item(device, monkeypatch):
    """llvmpipe's loop budget is one per SIMD group, so a lane's refilled rays share it; a ray it
    cut reads LOOP_CUT_PRIM (trace.h: cut_hit). The trace then runs the set again one ray per work
    item, and so do later traces and timings of that set (Built.refill_cut). The cut is planted:
    the refilled launch's hit ids are read back with one ray marked cut."""
    monkeypatch.setenv("LSBENCH_PACKET", "1")
    monkeypatch.setenv("LSBENCH_REFILL", "4")
    scene = load_scene("spheres")
    built = backends.build(device, "bvh", scene, BuildParams(resolution=(1, 1, 1)))
    rays = make_rays("incoherent", scene, 16, 16, None, {})
    read = device.read
    planted = []

    def read_with_a_cut(buf, dtype, count=None, *args):
        out = read(buf, dtype, count, *args)
        if buf.name == "hit_prim" and not planted:
            out = out.copy()
            out[7] = backends.LOOP_CUT_PRIM
            planted.append(True)
        return out

    try:
        monkeypatch.setattr(device, "read", read_with_a_cut)
        hits = backends.trace(built, rays)
        monkeypatch.setattr(device, "read", read)
        assert planted and hits.refill == 1 and (rays.content_hash, rays.query) in built.refill_cut
        assert not np.any(hits.prim_ids == backends.LOOP_CUT_PRIM)
        assert backends.refill_rays(built, rays, None) == 1
        monkeypatch.setenv("LSBENCH_REFILL", "1")
        assert np.array_equal(backends.trace(built, rays).prim_ids, hits.prim_ids)
    finally:
        built.release()


def test_llvmpipes_loop_budget_cuts_refilled_lanes_and_the_set_runs_one_ray_per_item(device, monkeypatch):
    """A real cut: 8000 tiny triangles 1e5 units from the origin, whose float32 boxes overlap so
    that an incoherent ray visits ~300 nodes and tests ~1100 triangles (up to 2000). 64 such rays
    per lane pass llvmpipe's 65535 loop iterations per SIMD group; the lanes' rays after the cut
    are never started, and read as cut (the hit ids start as LOOP_CUT_PRIM). The trace, and a
    timing taken first on a fresh build, then run the set one ray per work item (Built.refill_cut),
    with the hits of one ray per item. PoCL has no budget: there the 64 per item run."""
    rng = np.random.default_rng(3)
    tris = 1e5 + rng.uniform(0, 1e-2, (8000, 1, 3)) + rng.normal(0, 2e-4, (8000, 3, 3))
    v = tris.reshape(-1, 3).astype(np.float32)
    scene = Scene("far-dense", v, np.arange(len(v), dtype=np.uint32).reshape(-1, 3), "test:far-dense")
    rays = make_rays("incoherent", scene, 16, 16, None, {})
    key = (rays.content_hash, rays.query)
    monkeypatch.setenv("LSBENCH_PACKET", "1")
    built = backends.build(device, "bvh", scene, BuildParams(resolution=(1, 1, 1)))
    timed = backends.build(device, "bvh", scene, BuildParams(resolution=(1, 1, 1)))
    try:
        monkeypatch.setenv("LSBENCH_REFILL", "1")
        one = backends.trace(built, rays)
        monkeypatch.setenv("LSBENCH_REFILL", "64")
        hits = backends.trace(built, rays)
        assert np.array_equal(hits.prim_ids, one.prim_ids) and np.array_equal(hits.distances, one.distances)
        cut = device.loop_budget is not None  # llvmpipe
        assert hits.refill == (1 if cut else 64) and (key in built.refill_cut) == cut
        backends.time_trace(timed, rays, 0, 1)
        assert (key in timed.refill_cut) == cut
    finally:
        built.release()
        timed.release()


def test_both_push_orders_find_the_same_hits(device, monkeypatch):
    """The single-ray walk pushes a node's hit slots nearest on top either by an insertion sort into
    the stack (work items run one at a time: PoCL) or sorted in registers first (BVH_SORT_SLOTS:
    SIMD lanes, llvmpipe and GPUs; bvh.py traversal). Both, on this device, on primary, incoherent
    and any-hit shadow rays: the same closest distance per ray, another triangle only at a tie,
    and nothing Embree's check does not explain."""
    monkeypatch.setenv("LSBENCH_PACKET", "1")
    scene = load_scene("atrium")
    built = backends.build(device, "bvh", scene, BuildParams(resolution=(1, 1, 1)))
    defines = dict(built.trace_spec.defines)
    assert ("BVH_SORT_SLOTS" in defines) == (not device.serial_work_items)
    other = dataclasses.replace(built)
    if "BVH_SORT_SLOTS" in defines:
        other.trace_spec = dataclasses.replace(built.trace_spec, defines=tuple(
            (k, v) for k, v in built.trace_spec.defines if k != "BVH_SORT_SLOTS"))
    else:
        other.trace_spec = built.trace_spec.with_defines(BVH_SORT_SLOTS=1)
    lo, hi = scene.bounds
    light = 0.1 * float(np.linalg.norm(np.asarray(hi, np.float64) - lo))
    sets = [primary_rays(scene, 29, 23), make_rays("incoherent", scene, 27, 21, None, {}),
            make_rays("shadow", scene, 21, 17, None, {"light_size": light, "samples": 1})]
    try:
        for rays in sets:
            ours, theirs = backends.trace(built, rays), backends.trace(other, rays)
            assert np.array_equal(ours.prim_ids >= 0, theirs.prim_ids >= 0), rays.name
            if rays.query == "closest":
                np.testing.assert_array_equal(ours.distances, theirs.distances, err_msg=rays.name)
            ref_p, ref_t = embree_closest(scene, rays)
            for hits in (ours, theirs):
                _, cl = judge_hits(scene, rays, hits.prim_ids, hits.distances, ref_p, ref_t)
                assert cl.unexplained == 0, (rays.name, cl)
    finally:
        built.release()


@pytest.mark.parametrize("structure", ["bvh", "bvh-ls"])
@pytest.mark.parametrize("scene_name", ["atrium", "adversarial"])
def test_all_node_layouts_find_the_same_hits(device, structure, scene_name):
    """Float, float8 and quantized nodes (bvh.py NODE_LAYOUTS; the device picks one,
    options["bvh_nodes"] forces any) on this device: primary, incoherent and any-hit shadow rays,
    and on the adversarial scene (strips in the bounding planes, slivers, all 1e4 units from the
    origin) its adversarial rays. All answer every ray as Embree's check explains, and on the
    renderer's rays float8 and quantized find float's closest distance (another triangle only at a
    tie) and its occluded rays. On the adversarial rays float8 (the same boxes as float, two levels
    of three kept instead of one of two) may end at a hit one float step apart where a ray grazes a
    box whose rounded entry lies past a triangle's rounded hit, so the walks' order decides; a
    quantized box holds its float box
    and more, so on the adversarial rays that lie in a box's face plane (a triangle's own plane: a
    graze) the quantized walk may find a grazed triangle nearer than the float walk's hit, never a
    farther one; bvh-ls builds its Line Spaces over the leaves' boxes as the nodes hold them, so its
    shafts differ too and a graze may go either way."""
    scene = load_scene(scene_name)
    lo, hi = scene.bounds
    light = 0.1 * float(np.linalg.norm(np.asarray(hi, np.float64) - lo))
    sets = [primary_rays(scene, 29, 23), make_rays("incoherent", scene, 27, 21, None, {}),
            make_rays("shadow", scene, 21, 17, None, {"light_size": light, "samples": 1})]
    if scene_name == "adversarial":
        sets.append(make_rays("adversarial", scene, 1, 1, None, {}))
    ls = structure == "bvh-ls"
    built = {layout: backends.build(device, structure, scene, BuildParams(
        resolution=(1, 1, 1), ls_n=2 if ls else 0, ls_min_candidates=8 if ls else 0,
        options={"bvh_nodes": layout})) for layout in bvh.NODE_LAYOUTS}
    try:
        assert {layout: b.stats["node_bytes"] for layout, b in built.items()} == bvh.NODE_LAYOUTS
        for rays in sets:
            hits = {layout: backends.trace(b, rays) for layout, b in built.items()}
            ref_p, ref_t = embree_closest(scene, rays)
            for layout, h in hits.items():
                _, cl = judge_hits(scene, rays, h.prim_ids, h.distances, ref_p, ref_t)
                assert cl.unexplained == 0, (layout, rays.name, cl)
            ours = hits["float"]
            for layout in ("float8", "quantized"):
                theirs = hits[layout]
                if rays.name == "adversarial":
                    differ = np.count_nonzero(theirs.distances != ours.distances)
                    assert differ <= 0.01 * rays.count, (layout, differ)
                    assert ls or layout == "float8" or np.all(theirs.distances <= ours.distances)
                    continue
                assert np.array_equal(ours.prim_ids >= 0, theirs.prim_ids >= 0), (layout, rays.name)
                if rays.query == "closest":
                    np.testing.assert_array_equal(ours.distances, theirs.distances, err_msg=f"{layout} {rays.name}")
    finally:
        for b in built.values():
            b.release()


@pytest.mark.parametrize("leaf_size", [1, 2, 255])
def test_leaf_entries_that_hold_their_range_find_what_cell_entries_find(device, monkeypatch, leaf_size):
    """bvh's stack holds a leaf as its range of voxel_tris (bvh.h BVH_LEAF_RANGE_BITS: first << bits
    | count, bits from the leaf size) where the triangle count fits the bits left, else as its cell
    (4 * record + slot, the range read from the node's links; bvh-ls always: its Line Spaces are
    found by cell). Both entries, in every node layout, one ray per work item and in packets: the
    same hits, distances and work per ray, on the renderer's rays and on the adversarial scene's."""
    assert bvh.leaf_range_bits({"leaf_size": 2, "triangles": 2**29 - 1}) == 2
    assert bvh.leaf_range_bits({"leaf_size": 2, "triangles": 2**29}) == 0
    assert bvh.leaf_range_bits({"leaf_size": 255, "triangles": 2**23 - 1}) == 8
    assert bvh.leaf_range_bits({"leaf_size": 255, "triangles": 2**23}) == 0
    scene = load_scene("adversarial")
    sets = [primary_rays(scene, 29, 23), make_rays("incoherent", scene, 27, 21, None, {}),
            make_rays("adversarial", scene, 1, 1, None, {})]
    for layout in bvh.NODE_LAYOUTS:
        built = backends.build(device, "bvh", scene, BuildParams(resolution=(1, 1, 1), leaf_size=leaf_size,
                                                                 options={"bvh_nodes": layout}))
        try:
            defines = dict(built.trace_spec.defines)
            assert defines["BVH_LEAF_RANGE_BITS"] == str(leaf_size.bit_length())
            cells = dataclasses.replace(built, trace_spec=dataclasses.replace(built.trace_spec, defines=tuple(
                (k, v) for k, v in built.trace_spec.defines if k != "BVH_LEAF_RANGE_BITS")))
            for packet in ("1", "8") if device.backend == "opencl" else ("1", "4"):
                monkeypatch.setenv("LSBENCH_PACKET", packet)
                for rays in sets:
                    ours, theirs = backends.trace(built, rays, work=True), backends.trace(cells, rays, work=True)
                    assert (ours.prim_ids >= 0).any(), rays.name
                    np.testing.assert_array_equal(ours.prim_ids, theirs.prim_ids, err_msg=f"{layout} {rays.name}")
                    np.testing.assert_array_equal(ours.distances, theirs.distances, err_msg=f"{layout} {rays.name}")
                    np.testing.assert_array_equal(ours.work[:, :3], theirs.work[:, :3], err_msg=f"{layout} {rays.name}")
        finally:
            built.release()
    ls = backends.build(device, "bvh-ls", scene, BuildParams(resolution=(1, 1, 1), ls_n=2, ls_min_candidates=8))
    try:
        assert "BVH_LEAF_RANGE_BITS" not in dict(ls.trace_spec.defines)
    finally:
        ls.release()


def test_node_layout_is_checked(device):
    """options["bvh_nodes"]: auto picks by the device (float where work items run one after the
    other, quantized in SIMD lanes); anything else is one line naming the allowed values."""
    assert bvh.node_layout(device, {}) == ("float8" if device.serial_work_items else "quantized")
    assert bvh.node_layout(device, {"bvh_nodes": "quantized"}) == "quantized"
    with pytest.raises(ValueError, match="bvh_nodes must be one of auto, float8, float, quantized, got 'half'"):
        bvh.node_layout(device, {"bvh_nodes": "half"})


def test_work_counters_count_node_visits_and_tests(device):
    scene = load_scene("cornell")
    built = backends.build(device, "bvh", scene, BuildParams(resolution=(1, 1, 1)))
    try:
        rays = primary_rays(scene, 16, 16)
        hits = backends.trace(built, rays, work=True)
        steps, tests = hits.work[:, 0], hits.work[:, 1]
        assert np.all(steps >= 1) and np.all(steps <= built.stats["nodes"])
        assert np.all(tests[hits.prim_ids >= 0] >= 1)
    finally:
        built.release()


def test_leaf_size_is_checked():
    with pytest.raises(ValueError, match="leaf_size must be one of 1, 2, 4"):
        bvh.check_leaf_size(3)


def test_leaf_size_key_and_flag(tmp_path):
    """The scenario key: checked with the allowed values named, crossed only into the BVH cases,
    part of their key and record (the other structures' keys stay as they were)."""
    from lsbench.inputs.scenario import ScenarioError, load_scenario
    from lsbench.running.execute import new_record

    path = tmp_path / "s.toml"
    path.write_text('[[cases]]\nscenes = ["cornell"]\nstructures = ["grid", "bvh", "bvh-ls"]\n'
                    'backends = ["opencl"]\nresolutions = [8]\nleaf_size = [0, 4]\n')
    cases = load_scenario(str(path)).cases
    keys = sorted(c.key for c in cases)
    assert len(cases) == 5 and sum(k.endswith("|l4") for k in keys) == 2
    assert any(k.endswith(f"|bvh|opencl|r8|n0|k0|l{bvh.DEFAULT_LEAF_SIZE}") for k in keys)  # 0: the default, as built
    assert any(k.endswith("|bvh-ls|opencl|r8|n2|k0|l16") for k in keys)
    assert [k for k in keys if "|grid|" in k] == ["cornell|primary@64x64|grid|opencl|r8|n0|k0"]
    bvh_case = next(c for c in cases if c.structure == "bvh" and c.leaf_size == 4)
    assert new_record(bvh_case, load_scenario(str(path)).settings).leaf_size == 4
    path.write_text('[[cases]]\nscenes = ["cornell"]\nstructures = ["bvh"]\nresolutions = [8]\nleaf_size = 3\n')
    with pytest.raises(ScenarioError, match=r"leaf_size.* 3 is not 0 \(the structure's default\) or one of 1, 2, 4"):
        load_scenario(str(path))
