"""A/B of two variants of one case in ONE process, their trace launches alternated (A B A B ...),
so both see the same load on a shared machine (docs/profiles.md, section 7):

    python -m lsbench.profile.ab SCENE STRUCTURE BACKEND RES [--rays SET] [--size WxH]
        [--camera ex,ey,ez:tx,ty,tz[:fov]] [--pairs K] [--leaf-size L]
        (--defines NAME[=VALUE],... | --local-size N | --leaf-size-b L | --packet-b P)

A is the case as built; B is its trace kernel compiled with extra defines (a variant kept behind
an #ifdef while it is measured; a define the build already sets, e.g. BVH_STACK, is replaced),
with another work-group size, a second build with another leaf size, or the packet traversal
with P rays per work item (bvh, bvh-ls: 8 or 16 on OpenCL, 4 on GLSL; A then runs one ray per work item:
LSBENCH_PACKET). Prints each variant's min and median device time, the median of the K per-pair ratios
B/A with its quartiles, and whether B's hits equal A's (prim ids and distances). A single pair
swings by ±10 % under load; the median of 20 pairs resolves about 3 %.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import statistics

import numpy as np


def main(argv=None) -> None:
    from lsbench import backends
    from lsbench.profile.hotloop import case_arguments, load_case

    p = case_arguments("python -m lsbench.profile.ab", __doc__, size="512x512")
    p.add_argument("--pairs", type=int, default=20)
    p.add_argument("--leaf-size", type=int, default=0, help="A's leaf size (BVHs; 0: the default)")
    variant = p.add_mutually_exclusive_group(required=True)
    variant.add_argument("--defines", help="B's extra defines: NAME[=VALUE],...")
    variant.add_argument("--local-size", type=int, help="B's work-group size (on PoCL, where a trace's work "
                         "group runs as one work item's loop, KernelSpec.item_loop: the items per loop)")
    variant.add_argument("--leaf-size-b", type=int, help="B: a second build with this leaf size")
    widths = sorted({w for ws in backends.PACKET_WIDTHS.values() for w in ws})
    variant.add_argument("--packet-b", type=int, choices=widths,
                         help="B: this many rays per work item (the backend's backends.PACKET_WIDTHS)")
    args = p.parse_args(argv)
    _, rays, _, build = load_case(args)

    a = build(args.leaf_size)
    packets = {"A": None, "B": None}  # LSBENCH_PACKET of each variant (None: as the host picks)
    if args.leaf_size_b is not None:
        b, label = build(args.leaf_size_b), f"leaf size {args.leaf_size_b}"
    elif args.packet_b is not None:
        b, label = dataclasses.replace(a), f"{args.packet_b} rays per work item"
        packets = {"A": "1", "B": str(args.packet_b)}
    else:
        b = dataclasses.replace(a)
        if args.local_size is not None:
            b.trace_spec, label = dataclasses.replace(a.trace_spec, local_size=args.local_size), \
                f"local size {args.local_size}"
        else:
            given = {k: (v if sep else "1") for k, sep, v in (d.partition("=") for d in args.defines.split(","))}
            kept = tuple((k, v) for k, v in a.trace_spec.defines if k not in given)  # a define given replaces A's
            b.trace_spec = dataclasses.replace(a.trace_spec, defines=kept + tuple(given.items()))
            label = args.defines
    def as_variant(name: str, run):
        if packets[name] is None:
            return run()
        old = os.environ.get("LSBENCH_PACKET")
        os.environ["LSBENCH_PACKET"] = packets[name]
        try:
            return run()
        finally:
            if old is None:
                os.environ.pop("LSBENCH_PACKET", None)
            else:
                os.environ["LSBENCH_PACKET"] = old

    hits_a = as_variant("A", lambda: backends.trace(a, rays))
    hits_b = as_variant("B", lambda: backends.trace(b, rays))
    same = (np.array_equal(hits_a.prim_ids, hits_b.prim_ids)
            and np.array_equal(hits_a.distances, hits_b.distances))
    times = ([], [])
    for _ in range(args.pairs):
        for name, built, out in zip("AB", (a, b), times):
            out.append(min(as_variant(name, lambda: backends.time_trace(built, rays, warmup=0, repeats=1)).seconds))
    ta, tb = times
    ratios = [b_s / a_s for a_s, b_s in zip(ta, tb)]
    print(f"{args.structure} {args.backend} {args.rays}, B = {label}: "
          f"A min {min(ta) * 1e3:.1f} median {statistics.median(ta) * 1e3:.1f} ms | "
          f"B min {min(tb) * 1e3:.1f} median {statistics.median(tb) * 1e3:.1f} ms | "
          f"B/A median {statistics.median(ratios):.3f} (quartiles {np.quantile(ratios, 0.25):.3f}-"
          f"{np.quantile(ratios, 0.75):.3f}, {args.pairs} pairs) | hits identical: {same}")


if __name__ == "__main__":
    main()
