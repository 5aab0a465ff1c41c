"""Predicted device bytes of a structure at one setting, from the statistics of model/stats.py,
through each recipe's own predicted_bytes (backends/structures/*: the layout is written down once,
beside the code that allocates it).

Exact (equal to Built.memory_bytes, tests/test_fit.py): grid, svo, esvo from the count pass, and
every buffer of the Line Space structures except what their distinct candidate sets take (one list
per distinct set of a cell, linespace.h): the sets' offsets (in ls_shaft_offsets, beside the exact
per-cell part) and their cell-local candidate ids (ls_shaft_tris, 16 bits where the densest cell
holds at most 65,536 candidates). Before the build those are estimates: the
sets and set ids per reference of a sample of cells (stats.LineSpaceSample) times the references of
the cells that get a Line Space; given the build's counts (linespace.ListSizes.of(stats)) they are
exact. `exact` says which the prediction is.
"""
from __future__ import annotations

from dataclasses import dataclass

from lsbench.backends.device import Device
from lsbench.backends.structures import STRUCTURES, grid, grid_ls, svo
from lsbench.backends.structures.linespace import ListSizes, candidate_id_bits
from lsbench.model.stats import LineSpaceSample, VoxelCounts


@dataclass(frozen=True)
class BytesPrediction:
    buffers: dict  # name -> bytes
    exact: bool  # False: the shaft candidates are estimated from a sample

    @property
    def total(self) -> int:
        return int(sum(self.buffers.values()))

    @property
    def estimated_bytes(self) -> int:
        """What a Line Space prediction estimates from its sample: the sets' ids (ls_shaft_tris,
        with the buffers it is split over); 0 when exact."""
        if self.exact:
            return 0
        return int(sum(v for k, v in self.buffers.items() if k.startswith("ls_shaft_tris")))


def predict_bytes(device: Device, structure: str, counts: VoxelCounts, n: int = 0, k: int = 0,
                  sample: LineSpaceSample | None = None, lists: ListSizes | None = None) -> BytesPrediction:
    """Bytes of `structure` built over counts.geometry (with N = n, K = k for a Line Space
    structure). The distinct sets: `lists` when known (then the prediction is exact), else
    estimated from `sample`."""
    info = STRUCTURES[structure]
    octree = info.cubic_power_of_two
    if octree:
        per_level = counts.level_cells()
        nodes, leaves = sum(per_level[:-1]), per_level[-1]
    if not info.line_space:
        if octree:
            return BytesPrediction(svo.predicted_bytes(structure, nodes, leaves, counts.references), True)
        return BytesPrediction(grid.predicted_bytes(counts.voxels, counts.references), True)
    ls_cells, ls_refs = counts.above(k)
    exact = lists is not None
    if not exact:
        if sample is None:
            raise ValueError(f"{structure}: a Line Space prediction needs a sample or the built sets' sizes")
        sets, set_refs = sample.lists_per_reference(k)
        lists = ListSizes(round(sets * ls_refs), round(set_refs * ls_refs), candidate_id_bits(counts.densest))
    if octree:
        buffers = info.recipe.predicted_bytes(device, nodes, leaves, counts.references, ls_cells, n, lists)
    else:
        buffers = grid_ls.predicted_bytes(device, counts.voxels, counts.references, ls_cells, n, lists)
    return BytesPrediction(buffers, exact)
