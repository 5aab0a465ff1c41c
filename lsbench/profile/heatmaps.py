"""Profiling: per-ray work counters as heatmaps (EXR + PNG + JSON summary) and the device clock
(the timing-stability experiment is lsbench/profile/stability.py).

Heatmaps (Delgado Krämer 2019, Fig. 4 and Fig. 20): the profiling variant of a traversal kernel (COUNT_WORK,
backends.trace(..., work=True)) writes per ray uint4(iterations, candidate tests, Line Space
lookups, clock ticks). `write_heatmaps` lays them out as the ray image (row 0 = top, as
lsbench.inputs.rays.primary_rays) and writes into OUT_DIR:

    <case>.exr                       float32, one channel per counter (CHANNELS), exact values
    <case>_iterations_p99.png        inferno, 0 .. 99th percentile (clamped above)
    <case>_candidate_tests_p99.png   inferno, 0 .. 99th percentile
    <case>_candidate_tests_max32.png inferno, 0 .. 32 ("32 or more tests", thesis Fig. 4; the
                                     fixed scale compares across cases, saturates on dense scenes)
    <case>_linespace_lookups_p99.png inferno, 0 .. 99th percentile      (only if any are non-zero)
    <case>_clock_p99.png             inferno, 0 .. 99th percentile      (only with a device clock)
    <case>_clock_over_scene_p99.png  clock in red over the grey-shaded hits (thesis Fig. 20b)
    <case>_combined.png              iterations in yellow (0 .. p99), candidate tests in blue
                                     (0 .. p99), like thesis Fig. 20a (both high = white)
    <case>_simd_steps_w32.png        SIMD efficiency per group of 32 rays in dispatch order (mean ÷
    <case>_simd_tests_w32.png        max of the group's steps / candidate tests, lsbench/profile/simd.py),
                                     0 .. 1 (1 = no lane idles), every ray painted with its group's value;
                                     black: the group did no such work
    <case>_simd_{steps,tests}_wW.png the same for the device's own group width W where known and not 1 or 32
    <case>_colorbars.png             the colour bar and scale of every PNG above (one legend per case)
    <case>_work.json                 per counter mean/max/percentiles, the normalization of every
                                     PNG, the clock's unit (or why there is none)

The EXR holds a standard luminance channel Y beside the named ones, so ordinary viewers show
it: candidate tests ÷ 32 (the thesis' Fig. 4 scale: 1.0 = 32 tests; attribute lsbench_Y).

Thesis Fig. 4 side by side: `write_heatmap_row` renders one counter of several cases (the
structures of one scene) from their EXRs as one PNG at ONE shared scale, with a colour bar
(`shared_scale`: the largest 99th percentile among them, at least 1: the SIMD efficiencies get
0 .. 1), so equal colours mean equal work; lsbench/report/images.py draws a run's rows with it.

<case> is the case key with every character outside [A-Za-z0-9.-] replaced by '_'. The returned
dict maps names (exr, iterations, candidate_tests, ..., summary) to paths RELATIVE TO
OUT_DIR's PARENT: runs write into RUN_DIR/heatmaps, so records hold "heatmaps/<file>" relative to
the run folder (what lsbench.report.page expects); `lsbench trace --heatmaps DIR` gives paths relative
to DIR/.. in the same way. Ray sets that are not images (width 0, e.g. a .npz) are laid out row-major
as the case's WxH when that holds exactly the rays, else in a near-square image, ray i at
(i // W, i % W), padding NaN in the EXR and black in the PNGs.

Clock: CLOCK_START()/CLOCK_ELAPSED() (preludes, common/trace.h). GLSL reads clock2x32ARB().x
where the driver has GL_ARB_shader_clock (Mesa llvmpipe: nanoseconds, only the low 32 bits valid,
8 SIMD lanes share one value, so the clock image is constant over runs of 8 rays; NVIDIA: shader
clock cycles). OpenCL C has no clock builtin: NVIDIA devices read %clock by inline PTX, every other
device (PoCL's CPU device here) has none and its clock field is 0; `clock_info` says why. With a
clock the profiling trace runs CLOCK_RUNS times and keeps each ray's minimum clock: the counters
are deterministic, and on llvmpipe the ns clock is wall time, so a preempted host thread would
otherwise paint an 8-ray streak of milliseconds.
"""
from __future__ import annotations

import json
import math
import re
import struct
import zlib
from pathlib import Path

import numpy as np

from lsbench.backends.structures.base import WORK_CHANNELS

CHANNELS = WORK_CHANNELS  # the counters of Hits.work, one image each
CANDIDATE_TESTS_MAX = 32  # thesis Fig. 4: "blue = 32 or more tests"
PERCENTILE = 99.0
CLOCK_RUNS = 3  # profiling traces per case where there is a clock (per-ray minimum is kept)
COLORMAP = "inferno"
Y_RULE = f"candidate_tests / {CANDIDATE_TESTS_MAX} (thesis Fig. 4 scale: 1.0 = {CANDIDATE_TESTS_MAX} tests)"


# ---- clock ------------------------------------------------------------------------------------
def clock_info(device) -> dict:
    """What the clock field of the work counters holds on `device`: Device.clock_info, beside the
    Device.clock_defines that decide whether the kernels read a clock."""
    return device.clock_info()


# ---- layout -----------------------------------------------------------------------------------
def image_shape(rays, case_key: str = "") -> tuple[int, int]:
    """(height, width) of the heatmap: the camera image; else the case's WxH (the key's '@WxH')
    when it holds exactly the rays (a .npz of camera rays traced with --size WxH); else a
    near-square layout."""
    if rays.width > 0 and rays.height > 0 and rays.width * rays.height == rays.count:
        return rays.height, rays.width
    m = re.search(r"@(\d+)x(\d+)", case_key)
    if m and int(m.group(1)) * int(m.group(2)) == rays.count:
        return int(m.group(2)), int(m.group(1))
    w = max(1, math.ceil(math.sqrt(rays.count)))
    return max(1, math.ceil(rays.count / w)), w


def to_image(values: np.ndarray, shape: tuple[int, int], fill=np.nan) -> np.ndarray:
    """Per-ray values (ray i = row-major pixel i, row 0 = top) as a float32 (H, W) image."""
    h, w = shape
    flat = np.full(h * w, fill, np.float32)
    flat[:len(values)] = values
    return flat.reshape(h, w)


def counter_images(work: np.ndarray, shape: tuple[int, int]) -> dict[str, np.ndarray]:
    return {name: to_image(work[:, i].astype(np.float32), shape) for i, name in enumerate(CHANNELS)}


def case_slug(case_key: str) -> str:
    from lsbench.report.format import slug

    return slug(case_key, empty="case")


# ---- files ------------------------------------------------------------------------------------
def write_exr(path, channels: dict[str, np.ndarray], attributes: dict | None = None) -> None:
    """float32 scanline EXR, one named channel per array (OpenEXR 3.x Python API)."""
    import OpenEXR

    header = {"type": OpenEXR.scanlineimage, "compression": OpenEXR.ZIP_COMPRESSION}
    header.update({k: str(v) for k, v in (attributes or {}).items()})
    data = {k: np.ascontiguousarray(v, np.float32) for k, v in channels.items()}
    OpenEXR.File(header, data).write(str(path))


def read_exr(path) -> dict[str, np.ndarray]:
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        return {name: np.array(ch.pixels) for name, ch in f.channels().items()}


def write_png(path, rgb: np.ndarray) -> None:
    """8-bit RGB PNG from an (H, W, 3) uint8 array (no imaging library needed)."""
    rgb = np.ascontiguousarray(rgb, np.uint8)
    h, w, _ = rgb.shape
    raw = b"".join(b"\x00" + rgb[y].tobytes() for y in range(h))  # filter 0 on every row

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)

    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
           + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))
    Path(path).write_bytes(png)


def png_size(path) -> tuple[int, int]:
    """(width, height) from a PNG's IHDR."""
    data = Path(path).read_bytes()[:24]
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError(f"{path} is not a PNG")
    return struct.unpack(">II", data[16:24])


def normalize(img: np.ndarray, vmax: float) -> np.ndarray:
    """0 .. vmax -> 0 .. 1, clamped; NaN (padding) -> 0."""
    out = np.nan_to_num(img / max(float(vmax), 1e-30), nan=0.0)
    return np.clip(out, 0.0, 1.0)


def colorize(img: np.ndarray, vmax: float, cmap: str = COLORMAP) -> np.ndarray:
    from matplotlib import colormaps

    rgb = colormaps[cmap](normalize(img, vmax))[..., :3]
    rgb[np.isnan(img)] = 0.0
    return (rgb * 255.0 + 0.5).astype(np.uint8)


def colorbar_rgb(entries: list[tuple[str, float, str]], width: int = 420) -> np.ndarray:
    """One legend image: per (label, vmax, colormap) a labelled colour bar from 0 to vmax
    (matplotlib, Agg), as (H, W, 3) uint8."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import cm, colors, pyplot

    rows = max(len(entries), 1)
    fig = pyplot.figure(figsize=(width / 100.0, 0.62 * rows + 0.1), dpi=100)
    for k, (label, vmax, cmap) in enumerate(entries):
        ax = fig.add_axes([0.04, 1.0 - (k + 1) * (1.0 / rows) + 0.55 / rows, 0.92, 0.2 / rows])
        bar = fig.colorbar(cm.ScalarMappable(colors.Normalize(0.0, vmax), cmap), cax=ax, orientation="horizontal")
        bar.ax.tick_params(labelsize=7)
        ax.set_title(label, fontsize=8, loc="left", pad=2)
    fig.canvas.draw()
    rgb = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    pyplot.close(fig)
    return rgb


def shared_scale(images: list[np.ndarray]) -> float:
    """One scale for one counter across cases: the largest of their 99th percentiles (>= 1)."""
    return max([_p99(np.nan_to_num(img, nan=0.0).ravel()) for img in images] or [1.0])


def write_heatmap_row(exrs: list[tuple[str, object]], counter: str, out_path, vmax: float | None = None,
                      cmap: str = COLORMAP) -> dict:
    """Thesis Fig. 4 side by side: channel `counter` of each (label, EXR path) (the structures
    of one scene, from write_heatmaps) in one PNG row at one scale with a colour bar; vmax None
    = shared_scale of them. Returns what was drawn: {file, counter, max, rule, labels}."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot

    images = [read_exr(path)[counter] for _, path in exrs]
    scale = float(vmax) if vmax is not None else shared_scale(images)
    fig, axes = pyplot.subplots(1, len(images), figsize=(2.6 * len(images) + 0.8, 2.9), squeeze=False)
    shown = None
    for ax, (label, _), img in zip(axes[0], exrs, images):
        shown = ax.imshow(np.ma.masked_invalid(img), cmap=cmap, vmin=0.0, vmax=scale, interpolation="nearest")
        ax.set_title(label, fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    bar = fig.colorbar(shown, ax=list(axes[0]), fraction=0.025, pad=0.02, extend="max")
    bar.set_label(f"{counter} (0 .. {scale:g}, one scale)", fontsize=8)
    fig.savefig(str(out_path), dpi=100, bbox_inches="tight")
    pyplot.close(fig)
    return {"file": str(out_path), "counter": counter, "max": scale, "labels": [label for label, _ in exrs],
            "rule": "largest 99th percentile of the cases (shared_scale)" if vmax is None else "given"}


def combined_rgb(iterations: np.ndarray, tests: np.ndarray, it_max: float, tests_max: float) -> np.ndarray:
    """Thesis Fig. 20a: iterations in the yellow channel (red + green), candidate tests in blue."""
    it = normalize(iterations, it_max)
    ct = normalize(tests, tests_max)
    rgb = np.stack([it, it, ct], axis=-1)
    return (rgb * 255.0 + 0.5).astype(np.uint8)


def shading(built, rays, hits) -> np.ndarray:
    """|cos| between ray and the hit triangle's normal (0 for a miss): a grey view of the scene."""
    d = built.device
    verts = d.read(built.scene_buffers["vertices"], np.float32).reshape(-1, 3)
    faces = d.read(built.scene_buffers["faces"], np.uint32).reshape(-1, 3)
    prim = hits.prim_ids
    out = np.zeros(len(prim), np.float32)
    ok = (prim >= 0) & (prim < len(faces))
    tri = verts[faces[prim[ok]]]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    out[ok] = np.abs(np.einsum("ij,ij->i", n, rays.directions[ok]))
    return out


def clock_over_scene(clock: np.ndarray, shade: np.ndarray, vmax: float, scene_weight: float = 0.25) -> np.ndarray:
    """Thesis Fig. 20b: clock in red over the scene drawn grey (there at 5 % opacity; 25 % here
    so the small images stay readable)."""
    c = normalize(clock, vmax)
    g = np.nan_to_num(shade, nan=0.0) * scene_weight
    rgb = np.stack([np.maximum(c, g), g * (1.0 - c), g * (1.0 - c)], axis=-1)
    return (np.clip(rgb, 0, 1) * 255.0 + 0.5).astype(np.uint8)


def counter_stats(values: np.ndarray) -> dict:
    v = values.astype(np.float64)
    if v.size == 0:
        return {"mean": 0.0, "max": 0, "p50": 0.0, "p99": 0.0, "sum": 0, "nonzero": 0}
    return {"mean": float(v.mean()), "max": int(values.max()), "p50": float(np.percentile(v, 50)),
            "p99": float(np.percentile(v, PERCENTILE)), "sum": int(values.astype(np.uint64).sum()),
            "nonzero": int(np.count_nonzero(values))}


def _p99(values: np.ndarray) -> float:
    return max(1.0, float(np.percentile(values.astype(np.float64), PERCENTILE))) if values.size else 1.0


# ---- heatmaps ---------------------------------------------------------------------------------
def profile_trace(built, rays, clock_runs: int = CLOCK_RUNS):
    """The profiling trace, run clock_runs times where the device has a clock: the counters must
    agree between runs (they are deterministic); the clock is the per-ray minimum, which drops
    the host threads' preemption that the llvmpipe ns clock (wall time) otherwise shows as
    isolated 8-pixel streaks of milliseconds. Returns (hits, work)."""
    from lsbench import backends

    hits = backends.trace(built, rays, work=True)
    work = hits.work.copy()
    if clock_info(built.device)["available"] and work[:, 3].any():  # skip kernels that leave it 0
        for _ in range(max(clock_runs, 1) - 1):
            again = backends.trace(built, rays, work=True).work
            if not np.array_equal(again[:, :3], work[:, :3]):
                raise RuntimeError(f"{built.structure}: work counters differ between two identical profiling traces")
            work[:, 3] = np.minimum(work[:, 3], again[:, 3])
    return hits, work


def write_heatmaps(built, rays, out_dir, case_key: str, clock_runs: int = CLOCK_RUNS) -> dict[str, str]:
    """Trace `rays` with the profiling kernel of `built` and write the heatmaps listed in the
    module docstring to out_dir. Returns {name: path relative to out_dir's parent}."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    base = out.parent
    slug = case_slug(case_key)
    hits, work = profile_trace(built, rays, clock_runs)
    shape = image_shape(rays, case_key)
    images = counter_images(work, shape)
    clock = dict(clock_info(built.device))
    if clock["available"] and work[:, 3].any():
        clock["runs"] = max(clock_runs, 1)
        clock["combine"] = "per-ray minimum over the runs (drops host preemption)"
    info = built.device.info()
    files: dict[str, str] = {}

    def rel(p: Path) -> str:
        return p.relative_to(base).as_posix()

    from lsbench import backends
    from lsbench.profile import simd

    order = backends.launch_order(rays)
    width, _ = simd.device_simd_width(info)
    widths = [simd.WARP] + ([width] if width and width not in (1, simd.WARP) else [])
    simd_images = {f"simd_{short}_w{w}": to_image(simd.per_ray_group_efficiency(
                       work[:, CHANNELS.index(counter)], order, w).astype(np.float32), shape)
                   for w in widths for counter, short in simd.COUNTERS.items()}

    exr = out / f"{slug}.exr"
    write_exr(exr, {**images, **simd_images, "Y": images["candidate_tests"] / np.float32(CANDIDATE_TESTS_MAX)},
              {"lsbench_case": case_key, "lsbench_clock_unit": clock["unit"] or "none (zero)",
               "lsbench_device": info.get("device", ""), "lsbench_Y": Y_RULE})
    files["exr"] = rel(exr)

    norms: dict[str, dict] = {}
    stats = {name: counter_stats(work[:, i]) for i, name in enumerate(CHANNELS)}
    clock["filled"] = stats["clock"]["nonzero"] > 0  # False: no clock, or the kernel does not read it
    skipped = {}
    maps = [(name, i, _p99(work[:, i]), f"{PERCENTILE:g}th percentile clamp", "p99")
            for i, name in enumerate(CHANNELS)]
    # The thesis' fixed scale too (Fig. 4), comparable across cases; it saturates on dense scenes.
    maps.insert(2, ("candidate_tests_max32", 1, float(CANDIDATE_TESTS_MAX),
                    f"fixed maximum {CANDIDATE_TESTS_MAX} (32 or more tests = top colour, thesis Fig. 4)", ""))
    for name, i, vmax, rule, tag in maps:
        if i >= 2 and stats[CHANNELS[i]]["nonzero"] == 0:
            if name != "clock":
                skipped[name] = f"all zero for {built.structure}"
            elif not clock["available"]:
                skipped[name] = clock["note"]
            else:
                skipped[name] = (f"the {built.structure} kernel leaves the clock field 0 (no "
                                 "CLOCK_START()/CLOCK_ELAPSED() in its COUNT_WORK block)")
            continue
        path = out / (f"{slug}_{name}_{tag}.png" if tag else f"{slug}_{name}.png")
        write_png(path, colorize(images[CHANNELS[i]], vmax))
        files[name] = rel(path)
        norms[name] = {"file": rel(path), "colormap": COLORMAP, "min": 0.0, "max": vmax, "rule": rule}

    it_max, ct_max = norms["iterations"]["max"], norms["candidate_tests"]["max"]
    path = out / f"{slug}_combined.png"
    write_png(path, combined_rgb(images["iterations"], images["candidate_tests"], it_max, ct_max))
    files["combined"] = rel(path)
    norms["combined"] = {"file": rel(path), "rule": "thesis Fig. 20a: red+green (yellow) = iterations / max_iterations, "
                         "blue = candidate tests / max_candidate_tests, both clamped to 1 (99th percentiles)",
                         "max_iterations": it_max, "max_candidate_tests": ct_max}

    if "clock" in files:
        shade = to_image(shading(built, rays, hits), shape)
        vmax = norms["clock"]["max"]
        path = out / f"{slug}_clock_over_scene_p99.png"
        write_png(path, clock_over_scene(images["clock"], shade, vmax))
        files["clock_over_scene"] = rel(path)
        norms["clock_over_scene"] = {"file": rel(path), "rule": "thesis Fig. 20b: red = clock / max (99th "
                                     "percentile clamp) over the hits shaded grey at 25 %", "max": vmax}

    for name, img in simd_images.items():
        path = out / f"{slug}_{name}.png"
        write_png(path, colorize(img, 1.0))
        files[name] = rel(path)
        norms[name] = {"file": rel(path), "colormap": COLORMAP, "min": 0.0, "max": 1.0,
                       "rule": f"mean ÷ max per {name.rsplit('_w', 1)[1]}-ray group (dispatch order, "
                               "lsbench/profile/simd.py); black: the group did none of this work"}

    legend = [(f"{name}" + (f" [{clock['unit']}]" if name == "clock" else "") + f": {n['rule'].split(' (')[0][:48]}",
               n["max"], n.get("colormap", COLORMAP)) for name, n in norms.items() if "colormap" in n]
    path = out / f"{slug}_colorbars.png"
    write_png(path, colorbar_rgb(legend))
    files["colorbars"] = rel(path)

    hit = hits.prim_ids >= 0
    summary = {
        "case": case_key, "structure": built.structure, "device": info.get("device"), "driver": info.get("driver"),
        "backend": info.get("backend"), "ray_count": int(rays.count), "width": shape[1], "height": shape[0],
        "layout": ("camera image, row 0 = top, ray i = pixel (i % width, i // width)" if rays.width > 0
                   and rays.width * rays.height == rays.count else
                   "ray file laid out as the case's WxH: ray i at row i // width, column i % width"
                   if shape[0] * shape[1] == rays.count else
                   "not an image: ray i at row i // width, column i % width; padding NaN (EXR) / black (PNG)"),
        "hit_fraction": float(hit.mean()) if hit.size else 0.0,
        "clock": clock, "counters": stats,
        "counters_hit_rays": {name: counter_stats(work[hit, i]) for i, name in enumerate(CHANNELS)},
        "normalization": norms, "not_drawn": skipped,
        "simd": {**simd.simd_fields(work, order, info, hits.packet), "widths_drawn": widths},
        "exr_channels": [*CHANNELS, *simd_images, "Y"], "exr_Y": Y_RULE, "files": dict(files),
    }
    path = out / f"{slug}_work.json"
    path.write_text(json.dumps(summary, indent=2))
    files["summary"] = rel(path)
    return files
