"""Image-level accuracy: how different a case's picture looks from Embree's (issue 18).

Ray-level agreement (lsbench/oracle/verify.py) counts rays; it cannot say whether a disagreement
shows. Here both answers are shaded the same way and compared as a person would see them:

- shading: eye light times geometric normal, |n · d| for the hit triangle's unit normal n (from
  the scene's own triangles, not a device buffer) and the unit ray direction d, as linear grey;
  a miss is the background colour (a blue, so a missed pixel differs in hue as well as
  lightness from a dark grazing hit). A tie on a coplanar neighbour shades alike, as it should.
- colour difference: the linear value is encoded as sRGB (IEC 61966-2-1), taken to CIE L*a*b*
  (D65) and compared per pixel with CIEDE2000 (Sharma, Wu & Dalal 2005) through colour-science
  (`colour.delta_E(..., method="CIE 2000")`).
- the record keeps the mean and the maximum ΔE over the image and the count of pixels above a
  just-noticeable difference, ΔE > 2.3 (Sharma 2003, "Digital Color Imaging Handbook", the JND
  of CIELAB), so a chart has a figure that is not zero for every case that agrees.

Only camera ray sets that ask for the closest hit are images (`is_image`); shadow, AO, diffuse
and ray files have no picture. `write_images` writes the ΔE image and a map of the pixels
whose ray disagrees (missed red, extra blue, wrong magenta, distance yellow over the grey scene).
"""
from __future__ import annotations

import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from lsbench.oracle import verify

JND = 2.3  # CIELAB just-noticeable difference (Sharma 2003)
BACKGROUND = (0.05, 0.12, 0.35)  # linear sRGB of a miss
DELTA_E_SCALE = 10.0  # the ΔE image: black at 0, the top colour at 10 or more
# the pixel map: each disagreement category's colour (8-bit sRGB) over the scene at 35 % grey
CATEGORY_COLORS = {verify.MISSED: (230, 30, 30), verify.EXTRA: (40, 110, 255),
                   verify.WRONG: (230, 40, 230), verify.DISTANCE: (250, 220, 20)}
SCENE_WEIGHT = 0.35


def _colour():
    """colour-science, imported without its warning that SciPy (not needed here) is absent."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import colour
    return colour


@dataclass
class ImageAccuracy:
    """What the record keeps (docs/record.md, the image_* fields)."""

    image_delta_e_mean: float
    image_delta_e_max: float
    image_jnd_pixels: int  # pixels with ΔE > JND

    def to_dict(self) -> dict:
        return asdict(self)


def is_image(rays) -> bool:
    """A camera image of closest-hit rays: one ray per pixel, row-major from the top."""
    return rays.query == "closest" and rays.width > 0 and rays.width * rays.height == rays.count


def shade(scene, directions: np.ndarray, prim_ids: np.ndarray) -> np.ndarray:
    """(N, 3) linear RGB: |n · d| grey for a hit, BACKGROUND for a miss (prim id < 0 or not a
    triangle of the scene)."""
    prim = np.asarray(prim_ids).astype(np.int64)
    faces = scene.faces.astype(np.int64)
    out = np.tile(np.asarray(BACKGROUND, np.float64), (len(prim), 1))
    hit = (prim >= 0) & (prim < len(faces))
    tri = scene.vertices.astype(np.float64)[faces[prim[hit]]]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    d = np.asarray(directions, np.float64)[hit]
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    out[hit] = np.abs(np.einsum("ij,ij->i", n, d))[:, None]
    return out


def to_lab(linear_rgb: np.ndarray) -> np.ndarray:
    """Linear sRGB -> CIE L*a*b* (D65), through the sRGB encoding as a display shows it."""
    colour = _colour()
    encoded = colour.cctf_encoding(np.clip(linear_rgb, 0.0, 1.0), function="sRGB")
    return colour.XYZ_to_Lab(colour.sRGB_to_XYZ(encoded))


def delta_e(scene, rays, prim_ids, ref_prim_ids) -> np.ndarray:
    """CIEDE2000 per ray between the case's shaded hits and Embree's (N,)."""
    ours = to_lab(shade(scene, rays.directions, prim_ids))
    theirs = to_lab(shade(scene, rays.directions, ref_prim_ids))
    return np.asarray(_colour().delta_E(ours, theirs, method="CIE 2000"), np.float64)


def summarize(de: np.ndarray) -> ImageAccuracy:
    return ImageAccuracy(image_delta_e_mean=float(de.mean()) if de.size else 0.0,
                         image_delta_e_max=float(de.max()) if de.size else 0.0,
                         image_jnd_pixels=int(np.count_nonzero(de > JND)))


def delta_e_rgb(de: np.ndarray, height: int, width: int) -> np.ndarray:
    """(H, W, 3) uint8: ΔE 0 .. DELTA_E_SCALE in inferno (clamped above)."""
    from matplotlib import colormaps

    rgb = colormaps["inferno"](np.clip(de / DELTA_E_SCALE, 0.0, 1.0).reshape(height, width))[..., :3]
    return (rgb * 255.0 + 0.5).astype(np.uint8)


def pixel_map_rgb(scene, rays, prim_ids, categories: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8: the case's shaded image dimmed, each disagreeing pixel in its
    category's colour (CATEGORY_COLORS)."""
    grey = shade(scene, rays.directions, prim_ids) * SCENE_WEIGHT
    rgb = (np.clip(grey, 0, 1) * 255.0 + 0.5).astype(np.uint8)
    for cat, col in CATEGORY_COLORS.items():
        rgb[categories == cat] = col
    return rgb.reshape(rays.height, rays.width, 3)


def write_images(out_dir, file_stem: str, scene, rays, prim_ids, de: np.ndarray,
                 categories: np.ndarray) -> dict[str, str]:
    """OUT_DIR/<stem>_delta_e.png and <stem>_pixel_errors.png. Returns {name: path relative to
    out_dir's parent} (runs write into RUN_DIR/heatmaps, so records hold "heatmaps/<file>")."""
    from lsbench.profile.heatmaps import write_png

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = {}
    for name, rgb in (("delta_e", delta_e_rgb(de, rays.height, rays.width)),
                      ("pixel_errors", pixel_map_rgb(scene, rays, prim_ids, categories))):
        path = out / f"{file_stem}_{name}.png"
        write_png(path, rgb)
        files[name] = path.relative_to(out.parent).as_posix()
    return files


def image_accuracy(scene, rays, prim_ids, distances, ref_prim_ids, ref_distances, accuracy,
                   out_dir=None, case_key: str = "") -> dict:
    """The record's image fields for a camera image of closest hits (all None otherwise):
    image_delta_e_mean/max, image_jnd_pixels and, with out_dir, image_files (the two PNGs).
    accuracy: the case's verify.Accuracy, whose tolerances the pixel map's categories use."""
    empty = {name: None for name in ImageAccuracy.__dataclass_fields__}
    if not is_image(rays):
        return dict(empty, image_files={})
    de = delta_e(scene, rays, prim_ids, ref_prim_ids)
    fields = dict(summarize(de).to_dict(), image_files={})
    if out_dir:
        from lsbench.profile.heatmaps import case_slug  # the heatmaps' file names: side by side

        categories = verify.classify(prim_ids, distances, ref_prim_ids, ref_distances,
                                     rel_tol=accuracy.rel_tol, abs_tol=accuracy.abs_tol,
                                     query=rays.query, tmax=rays.tmax_array, tmin=rays.tmin)
        fields["image_files"] = write_images(out_dir, case_slug(case_key), scene, rays,
                                             prim_ids, de, categories)
    return fields
