"""The structure catalogue: one entry per structure, in display order (tables, charts, reports).

Each entry's `recipe` has prepare(device) (compile what the build uses) and
build(device, scene_buffers, n_tris, geometry, params) -> BuildResult (base.py), written against
the Device interface only. A recipe's module docstring names its kernels' headers in
shaders/common/: grid.h, grid_ls.h, octree.h with svo.h / esvo.h, octree_ls.h, linespace.h, bvh.h."""
from __future__ import annotations

from dataclasses import dataclass

from . import bvh, esvo, grid, grid_ls, svo
from . import bvh_ls as bvh_ls_module
from .bvh_ls import bvh_ls
from .octree_ls import esvo_ls, svo_ls


@dataclass(frozen=True)
class StructureInfo:
    name: str
    recipe: object  # module or object with prepare() and build()
    cubic_power_of_two: bool  # octrees: cubic power-of-two resolution of the bounding cube (over the scene's box)
    line_space: bool  # takes ls_n / ls_min_candidates
    what: str  # one line, with the thesis section (Delgado Krämer 2019)
    leaf_size: int = 0  # BVHs: the default most triangles per leaf (leaf_size key); 0: takes none
    packets: bool = False  # its trace kernel has a packet traversal (Device.packet_width; bvh.h BVH_PACKET)
    # The packets are picked by default also where work items run one at a time (Device.serial_work_items:
    # PoCL); bvh-ls, whose packet tests a leaf's Line Space lane by lane, gains only where they run in
    # SIMD lanes (llvmpipe; docs/profiles.md, section 27).
    serial_packets: bool = True
    refill: bool = False  # its trace kernel can refill a lane whose ray ended (backends.refill_rays; bvh.h BVH_REFILL)


CATALOGUE: tuple[StructureInfo, ...] = (
    StructureInfo("grid", grid, False, False, "uniform grid, 3D-DDA (3.3.1)"),
    StructureInfo("svo", svo, True, False, "node-pool octree, stack traversal (3.3.2, Alg. 1)"),
    StructureInfo("esvo", esvo, True, False, "Laine & Karras descriptors, PUSH/ADVANCE/POP (5.2)"),
    StructureInfo("grid-ls", grid_ls, False, True, "grid with a Line Space per non-empty voxel (3.3.3, Alg. 2)"),
    StructureInfo("svo-ls", svo_ls, True, True, "adaptive Line Space in svo leaves (4, 5.1, Alg. 3)"),
    StructureInfo("esvo-ls", esvo_ls, True, True, "adaptive Line Space in esvo leaves (5.2)"),
    StructureInfo("bvh", bvh, False, False, "binary BVH: binned SAH, treelet restructuring (Fig. 4c baseline)",
                  bvh.DEFAULT_LEAF_SIZE, packets=True, refill=True),
    StructureInfo("bvh-ls", bvh_ls, False, True, "BVH with a Line Space in its large leaves (7, future work)",
                  bvh_ls_module.DEFAULT_LEAF_SIZE, packets=True, serial_packets=False, refill=True),
)
STRUCTURES: dict[str, StructureInfo] = {s.name: s for s in CATALOGUE}


def structure_info(name: str) -> StructureInfo:
    """The catalogue entry of `name`; ValueError naming the known structures otherwise."""
    try:
        return STRUCTURES[name]
    except KeyError:
        raise ValueError(f"unknown structure {name!r}; choose one of {', '.join(STRUCTURES)}") from None


def display_order(name: str) -> tuple[int, str]:
    """Sort key: catalogue order, unknown names (old records) last."""
    names = list(STRUCTURES)
    return (names.index(name) if name in names else len(names), name)
