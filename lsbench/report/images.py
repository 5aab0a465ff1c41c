"""The report's image sections: heatmaps (one row of structures per scene, workload, backend and
counter, thesis Fig. 4 side by side) and image accuracy (the ΔE image and the map of missed /
extra / wrong pixels of each camera case, lsbench/oracle/image.py).

The files are the ones the records name (`heatmaps`, `image_files`, relative to the run folder);
a missing one is a grey box that says so, never a broken image. A row of one counter is drawn at
one shared scale by lsbench.profile.heatmaps.write_heatmap_row from the cases' EXRs where that
renderer exists and every EXR is there; otherwise the cases' own PNGs stand side by side, each
at its own scale (the row says which)."""
from __future__ import annotations

import html
import shutil
from collections import OrderedDict
from pathlib import Path

from lsbench.backends.structures import display_order
from lsbench.report.format import slug
from lsbench.report.records import case_label, resolution_order, scene_name
from lsbench.report.tables import workload_label

e = html.escape
BROWSER_IMAGES = {".png", ".jpg", ".jpeg", ".gif", ".svg", ".webp"}
# EXR channels; simd_*_w32: mean ÷ max per 32-ray group (lsbench/profile/simd.py), drawn 0 .. 1
ROW_COUNTERS = ("iterations", "candidate_tests", "linespace_lookups", "clock", "simd_steps_w32", "simd_tests_w32")


class Files:
    """Where a record's file is, and its address in the page (copied when the page is elsewhere,
    so the report folder stands alone)."""

    def __init__(self, run_dir: Path, out_dir: Path):
        self.run_dir, self.out_dir = run_dir, out_dir
        self.same = run_dir.resolve() == out_dir.resolve()

    def source(self, rel: str) -> Path:
        return self.run_dir / rel

    def href(self, rel: str) -> str | None:
        src = self.source(rel)
        if not src.is_file():
            return None
        if self.same:
            return Path(rel).as_posix()
        dest = self.out_dir / "heatmaps" / slug(rel)
        dest.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(src, dest)
        return dest.relative_to(self.out_dir).as_posix()


def _figure(files: Files, rel: str, caption: str, alt: str) -> str:
    href = files.href(rel)
    if href is None:
        return (f"<figure class='missing'><div>missing: {e(str(rel))}</div>"
                f"<figcaption>{caption}</figcaption></figure>")
    if Path(rel).suffix.lower() in BROWSER_IMAGES:
        body = f"<a href='{e(href)}'><img src='{e(href)}' alt='{e(alt)}' loading='lazy'></a>"
    else:
        body = f"<div><a href='{e(href)}'>{e(Path(rel).name)}</a> (open in an image viewer)</div>"
    return f"<figure>{body}<figcaption>{caption}</figcaption></figure>"


def _case_order(r):
    return (display_order(r.get("structure")), r.get("ls_n") or 0, resolution_order(r.get("resolution")))


def _rows(records, field: str) -> dict:
    """{(scene, workload, backend): records with files in `field`}, cases in catalogue order."""
    groups: dict = OrderedDict()
    for r in sorted(records, key=lambda r: (scene_name(r), workload_label(r), str(r.get("backend")), _case_order(r))):
        if r.get(field):
            groups.setdefault((scene_name(r), workload_label(r), r.get("backend", "?")), []).append(r)
    return groups


def _shared_row(recs, counter: str, files: Files, out_dir: Path, name: str) -> str | None:
    """One PNG of the counter for every case of the row at one scale, or None where the
    renderer or an EXR is missing."""
    from lsbench.profile import heatmaps

    render = getattr(heatmaps, "write_heatmap_row", None)
    exrs = [(case_label(r), files.source(r["heatmaps"].get("exr", ""))) for r in recs]
    if render is None or not all(r["heatmaps"].get("exr") and p.is_file() for r, (_, p) in zip(recs, exrs)):
        return None
    path = out_dir / "heatmap_rows" / f"{name}.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        drawn = render(exrs, counter, path)
    except (KeyError, OSError, ValueError):  # a channel an older EXR lacks: the cases' own PNGs
        return None
    rel = path.relative_to(out_dir).as_posix()
    return (f"<a href='{e(rel)}'><img class='row' src='{e(rel)}' alt='{e(counter)} row'></a>"
            f"<p class='small'>one scale for the row: 0 .. {float(drawn.get('max', 0)):g} "
            f"({e(str(drawn.get('rule', '')))})</p>")


def heatmap_section(records, files: Files, out_dir: Path) -> list[str]:
    out = ["<h2 id='heatmaps'>Heatmaps</h2>"]
    groups = _rows(records, "heatmaps")
    if not groups:
        out.append("<p class='small'>No heatmaps in this run (they are written by profiling runs "
                   "with work counters: <code>lsbench run --heatmaps</code>).</p>")
        return out
    out.append("<p>Per scene, workload and backend one row per work counter, the structures side by "
               "side (thesis Fig. 4): iterations = traversal steps per ray, candidate tests = "
               "ray/triangle tests per ray. Other files of each case are under 'more'.</p>")
    for (scene, workload, backend), recs in groups.items():
        heading = f"{e(scene)} — {e(workload)} — {e(backend)}"
        camera = all(r.get("query", "closest") == "closest" and r.get("width") and r.get("fps") for r in recs)
        # the camera images first and open; the other workloads' (rays laid out as an image) folded
        out.append(f"<h3>{heading}</h3>" if camera else f"<details class='hm'><summary>{heading}</summary>")
        for counter in ROW_COUNTERS:
            have = [r for r in recs if counter in r["heatmaps"]]
            if not have:
                continue
            shared = _shared_row(have, counter, files, out_dir, slug(scene, workload, backend, counter))
            out.append(f"<h4>{e(counter.replace('_', ' '))}</h4>")
            if shared:
                out.append(shared)
                continue
            out.append("<p class='small'>each image at its own scale (0 .. its 99th percentile; "
                       "the case's colour bars under 'more')</p><div class='gallery hrow'>")
            out += [_figure(files, r["heatmaps"][counter], e(case_label(r)), counter) for r in have]
            out.append("</div>")
        rest = [(r, name, rel) for r in recs for name, rel in r["heatmaps"].items()
                if name not in ROW_COUNTERS and name not in ("exr", "summary")]
        links = [(r, name, rel) for r in recs for name, rel in r["heatmaps"].items() if name in ("exr", "summary")]
        if rest or links:
            out.append("<details><summary>more</summary><div class='gallery'>")
            out += [_figure(files, rel, f"{e(case_label(r))}<br>{e(name)}", name) for r, name, rel in rest]
            out.append("</div><p class='small'>")
            for r, name, rel in links:
                href = files.href(rel)
                out.append(f"<a href='{e(href)}'>{e(case_label(r))} {e(name)}</a> " if href
                           else f"missing: {e(rel)} ")
            out.append("</p></details>")
        if not camera:
            out.append("</details>")
    return out


def image_accuracy_section(records, files: Files) -> list[str]:
    """Per camera case: the map of disagreeing pixels and the ΔE image, with its numbers."""
    out = ["<h2 id='image'>Image accuracy (CIEDE2000)</h2>",
           "<p>Each camera case's hits and Embree's, shaded alike (eye light × geometric normal), "
           "compared per pixel with CIEDE2000; ΔE &gt; 2.3 is a difference a person can see. Left: "
           "the pixels whose ray disagrees (<span style='color:#e61e1e'>missed</span>, "
           "<span style='color:#286eff'>extra</span>, <span style='color:#e628e6'>wrong</span>, "
           "<span style='color:#c8b000'>distance</span>) over the dimmed image; right: ΔE "
           "(inferno, 0 .. 10).</p>"]
    groups = _rows(records, "image_files")
    if not groups:
        measured = [r for r in records if r.get("image_delta_e_max") is not None]
        out.append(f"<p class='small'>No ΔE images in this run ({len(measured)} cases have ΔE figures; "
                   "the images are written with the heatmaps: <code>lsbench run --heatmaps</code>).</p>")
        return out
    measured = [r for r in records if r.get("image_jnd_pixels") is not None]
    seen = [r for r in measured if r["image_jnd_pixels"] > 0]
    out.append(f"<p><b>{len(seen)}</b> of {len(measured)} camera cases have pixels past the JND"
               + (": " + e(", ".join(case_label(r, True) for r in seen)) if seen else "") + ". Within a row, "
               "the cases with the most such pixels come first.</p>")
    for (scene, workload, backend), recs in groups.items():
        out.append(f"<h3>{e(scene)} — {e(workload)} — {e(backend)}</h3><div class='gallery'>")
        for r in sorted(recs, key=lambda r: -(r.get("image_jnd_pixels") or 0)):  # stable: catalogue order
            planted = f"<br>planted defect: {e(str(r['planted_defect']))}" if r.get("planted_defect") else ""
            caption = (f"{e(case_label(r))}<br>ΔE mean {r.get('image_delta_e_mean') or 0:.3g}, max "
                       f"{r.get('image_delta_e_max') or 0:.3g}, {r.get('image_jnd_pixels') or 0} px &gt; 2.3"
                       + planted)
            pair = [r["image_files"].get(k) for k in ("pixel_errors", "delta_e")]
            out.append("<div class='pair'>" + "".join(_figure(files, rel, caption if k else "", name)
                                                      for k, (rel, name) in enumerate(zip(pair, ("pixels", "ΔE")))
                                                      if rel) + "</div>")
        out.append("</div>")
    return out
