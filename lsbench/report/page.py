"""Static HTML report of one run: index.html + SVG charts (PNG beside them) + CSV and LaTeX of
every table, opens from disk (no network, no JS).

Results first, environment last (issue 18): one section per ray workload (a table of rays/s per
structure with Embree's rays/s on the same rays as each scene's reference row, and a chart;
issue 14), the thesis' (Delgado Krämer 2019, chapter 6) Tables 1-3 (lsbench/report/tables.py),
what the cost model chose for the "auto" cases (lsbench/report/auto.py),
rays/s against memory and against accuracy with their Pareto fronts, image accuracy (ΔE),
build time against memory and the spread of the timing repeats (lsbench/report/charts.py), the
heatmaps (lsbench/report/images.py), every case in detail, the full text of every failure, and
the environment. A `compare.html` in the run folder (`lsbench compare --report`) is linked.
"""
from __future__ import annotations

import html
import json
import shutil
from collections import OrderedDict
from pathlib import Path

from lsbench.report.auto import auto_section
from lsbench.report.charts import (chart_build_memory, chart_rays_memory, chart_repeats,
                                   chart_speed_accuracy, chart_workload)
from lsbench.report.export import write_exports
from lsbench.report.format import fmt_mib, fmt_num, fmt_pct, fmt_seconds, fmt_si, slug
from lsbench.report.history_page import history_link
from lsbench.report.images import Files, heatmap_section, image_accuracy_section
from lsbench.report.records import case_label, label_scenes, resolution_label, scene_name, succeeded
from lsbench.report.tables import (Baselines, is_camera, one_per_build, table_html, thesis_tables, workload_label,
                                   workload_tables)
from lsbench.results.store import (format_commit, read_run, run_devices, run_settings,
                                   scenario_name)

e = html.escape


def _kv_table(d: dict) -> str:
    rows = []
    for k, v in d.items():
        if isinstance(v, dict) and v and all(not isinstance(x, (dict, list)) for x in v.values()):
            val = ", ".join(f"{e(str(a))}={e(str(b))}" for a, b in v.items())
        elif isinstance(v, (dict, list)):
            val = f"<pre>{e(json.dumps(v, indent=1, default=str))}</pre>"
        else:
            val = e(str(v))
        rows.append(f"<tr><th class='rl'>{e(str(k))}</th><td class='l'>{val}</td></tr>")
    return "<table class='grid kv'>" + "".join(rows) + "</table>"


def _environment(info, records) -> list[str]:
    out = ["<h2 id='env'>Environment</h2>"]
    if not info:
        out.append("<p class='warn'>No run.json in this run directory.</p>")
    top = OrderedDict()
    for k in ("date", "commit", "dirty", "host", "machine", "platform", "processor", "cpu_count",
              "python", "scenario", "scenario_name", "scenario_path", "command", "command_line"):
        if k in info:
            top[k] = info[k]
    if "commit" in top:
        top["commit"] = format_commit(info.get("commit"), info.get("dirty"))
        top.pop("dirty", None)
    for k, v in info.items():
        if k not in top and k not in ("devices", "dirty"):
            top[k] = v
    out.append(_kv_table(top))
    devs = run_devices(info, records)
    if devs:
        out.append("<h3>Devices</h3><table class='grid'><tr><th>backend</th><th>device</th>"
                   "<th>driver</th><th>backend version</th></tr>")
        for b, d in devs.items():
            out.append(f"<tr><th class='rl'>{e(str(b))}</th><td class='l'>{e(str(d.get('device', '-')))}</td>"
                       f"<td class='l'>{e(str(d.get('driver', '-')))}</td>"
                       f"<td class='l'>{e(str(d.get('backend_version', '-')))}</td></tr>")
        out.append("</table>")
    commits = {(r.get("commit"), r.get("dirty")) for r in records if r.get("commit")}
    if len(commits) > 1:
        out.append("<p class='warn'>Records in this run come from more than one commit: "
                   + e(", ".join(format_commit(c, d) for c, d in sorted(commits, key=str))) + "</p>")
    return out


DETAIL_COLS = [
    ("scene", scene_name), ("rays", lambda r: r.get("rays", "")),
    ("structure", lambda r: r.get("structure", "")), ("backend", lambda r: r.get("backend", "")),
    ("res.", lambda r: resolution_label(r.get("resolution", ""))), ("N", lambda r: r.get("ls_n") or ""),
    ("status", lambda r: r.get("status", "")),
    ("agreement", lambda r: fmt_pct(r.get("agreement"))),
    ("agree/tie/miss/extra/wrong", lambda r: "/".join(str(r.get(k, "-")) for k in ("agree", "ties", "missed", "extra", "wrong")) if succeeded(r) else ""),
    ("max |dt|", lambda r: f"{r['max_abs_dt']:.2g}" if r.get("max_abs_dt") is not None else "-"),
    ("build", lambda r: fmt_seconds(r.get("build_seconds"))),
    ("trace min", lambda r: fmt_seconds(r.get("trace_seconds_min"))),
    ("median", lambda r: fmt_seconds(r.get("trace_seconds"))),
    ("max", lambda r: fmt_seconds(r.get("trace_seconds_max"))),
    ("cv", lambda r: f"{r['trace_cv'] * 100:.1f}%" if r.get("trace_cv") is not None else "-"),
    ("n", lambda r: len(r.get("trace_seconds_all") or [])),
    ("clock", lambda r: r.get("clock", "")),
    ("rays/s", lambda r: fmt_si(r.get("rays_per_second"))),
    ("FPS", lambda r: fmt_num(r.get("fps"))),
    ("MiB", lambda r: fmt_mib(r.get("memory_bytes"))),
    ("ΔE mean/max", lambda r: (f"{r['image_delta_e_mean']:.3g}/{r['image_delta_e_max']:.3g}"
                               if r.get("image_delta_e_max") is not None else "-")),
    ("ΔE>2.3 px", lambda r: r.get("image_jnd_pixels") if r.get("image_jnd_pixels") is not None else "-"),
]


def _details(records, min_agree: float | None) -> list[str]:
    out = ["<h2 id='cases'>All cases</h2><p>Hover a row for its case key; 'show' opens its "
           "buffers and counters.</p><div class='scroll'><table class='grid detail'><tr>"]
    out += [f"<th>{e(h)}</th>" for h, _ in DETAIL_COLS] + ["<th>buffers, counters</th></tr>"]
    for r in records:
        below = min_agree is not None and (r.get("agreement") or 0) < min_agree
        cls = "fail" if not succeeded(r) else ("warn" if below else "")
        out.append(f"<tr class='{cls}' title='{e(r.get('key', ''))}'>")
        out += [f"<td>{e(str(fn(r)))}</td>" for _, fn in DETAIL_COLS]
        extra = {k: r.get(k) for k in ("buffers", "stats") if r.get(k)}
        if not succeeded(r):
            extra["reason"] = r.get("reason", "")
        extra["key"] = r.get("key")
        out.append(f"<td class='l'><details><summary>show</summary><pre>"
                   f"{e(json.dumps(extra, indent=1, default=str))}</pre></details></td></tr>")
    out.append("</table></div>")
    failed = [r for r in records if not succeeded(r)]
    if failed:
        out.append("<h2 id='failures'>Failures</h2>")
        for r in failed:
            out.append(f"<h4>{e(case_label(r, True))} <span class='small'>({e(str(r.get('rays', '')))})</span></h4>"
                       f"<pre class='failtext'>{e(str(r.get('reason', '')))}</pre>")
    return out


CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,sans-serif;margin:1.5em 2em;color:#222;
 max-width:1400px}
h1{margin-bottom:.2em} h2{border-bottom:2px solid #ddd;padding-bottom:.2em;margin-top:1.8em}
nav a{margin-right:1em}
table.grid{border-collapse:collapse;font-size:13px;margin:.5em 0 1em}
table.grid td,table.grid th{border:1px solid #ccc;padding:3px 7px;text-align:right;vertical-align:top}
table.grid th{background:#f0f0f0;text-align:center}
table.grid th.rl{text-align:left;background:#f7f7f7}
table.grid td.l{text-align:left}
table.kv td{max-width:900px}
td.fail,tr.fail td{background:#fbd5d5;color:#8a1010;text-align:left;max-width:260px;font-size:12px}
td.warn,tr.warn td{background:#fff1c7}
td.na{color:#aaa;text-align:center}
td.best{background:#dff3df}
tr.ref th,tr.ref td{background:#eef2f8;text-align:center}
p.exports{font-size:12px;margin:-.6em 0 1em}
img.row{max-width:100%;border:1px solid #eee}
.pair{display:flex;gap:4px}
.hrow figure,.hrow figure img{width:180px}
details.hm summary{font-weight:bold;margin:.6em 0;cursor:pointer}
.pair figure{width:160px}
.pair figure img{width:160px}
.small{font-size:11px;color:#555}
.warn{background:#fff3cd;border:1px solid #e0c060;padding:.4em .8em}
pre{margin:0;font-size:11px;white-space:pre-wrap}
pre.failtext{background:#fbeaea;padding:.5em;border-left:3px solid #c33;max-height:20em;overflow:auto}
.gallery{display:flex;flex-wrap:wrap;gap:12px}
figure{margin:0;width:260px;font-size:11px}
figure img{width:260px;image-rendering:pixelated;border:1px solid #ccc}
figure.missing div{height:80px;background:#eee;display:flex;align-items:center;justify-content:center}
img.chart{max-width:100%;border:1px solid #eee;margin:.3em 0}
figure.chart{width:auto;max-width:100%}
figure.chart img{width:auto;max-width:100%;image-rendering:auto;border:1px solid #eee}
table.detail{font-size:11px}
table.detail td{white-space:nowrap}
table.detail tr.fail td{max-width:none}
table.detail pre{white-space:pre}
.scroll{overflow-x:auto}
.side{display:flex;flex-wrap:wrap;gap:0 2.5em;align-items:flex-start}
"""


OLD_RUN_MIN_AGREEMENT = 0.9999  # the runner's default while run.json had no settings


class EmptyRunError(ValueError):
    """A run folder with no case record: there is nothing to report (one-line message)."""


def min_agreement(info: dict) -> float | None:
    """The run's agreement threshold: run.json's settings; for a run folder written before
    run.json held them, the threshold where older runners put it, else the default then."""
    settings = run_settings(info)
    if settings:
        value = settings.get("min_agreement")
        return None if value is None else float(value)
    scenario = info.get("scenario") if isinstance(info.get("scenario"), dict) else {}
    for src in (info, info.get("run") or {}, scenario, scenario.get("run") or {}):
        if isinstance(src, dict) and "min_agreement" in src:
            return float(src["min_agreement"])
    return OLD_RUN_MIN_AGREEMENT



def _chart_section(groups: dict, chart, charts_dir: Path, out_dir: Path, name: str) -> list[str]:
    """One chart per group of records ({(scene, ...): records}), or a line saying none had data.
    The page shows the SVG and links the PNG beside it."""
    out = []
    for group, recs in groups.items():
        parts = group if isinstance(group, tuple) else (group,)
        title = " — ".join(str(p) for p in parts)
        path = chart(recs, charts_dir / f"{name}_{slug(*parts)}.png", title)
        if path:
            svg = path.relative_to(out_dir).as_posix()
            png = path.with_suffix(".png").relative_to(out_dir).as_posix()
            out.append(f"<figure class='chart'><img class='chart' src='{e(svg)}' alt='{e(name.replace('_', ' '))} "
                       f"{e(title)}'><figcaption class='small'><a href='{e(svg)}'>SVG</a> · "
                       f"<a href='{e(png)}'>PNG</a></figcaption></figure>")
    return out or ["<p class='small'>No successful case to plot.</p>"]


def _grouped(records, key_fn) -> dict:
    groups: dict = OrderedDict()
    for r in sorted(records, key=key_fn):
        groups.setdefault(key_fn(r), []).append(r)
    return groups


def _tables(tables, out_dir: Path, empty_text: str) -> list[str]:
    """Tables side by side, each with its CSV and LaTeX beside the page."""
    if not tables:
        return [f"<p class='small'>{e(empty_text)}</p>"]
    out = ["<div class='side'>"]
    for t in tables:
        links = " · ".join(f"<a href='{e(rel)}'>{kind}</a>" for kind, rel in write_exports(t, out_dir).items())
        out.append(f"<div><h3>{e(t.caption)}</h3>{table_html(t)}<p class='exports'>{links}</p></div>")
    out.append("</div>")
    return out


def _workload_sections(records, baselines, min_agree, charts_dir: Path, out_dir: Path) -> tuple[list[str], list]:
    """One section per workload (ray set and query); returns the HTML and the nav entries."""
    out, nav = [], []
    camera_first = sorted(_grouped(records, workload_label).items(),
                          key=lambda kv: (not is_camera(kv[1][0]), kv[0]))
    for i, (workload, recs) in enumerate(camera_first):
        anchor = f"workload{i + 1}"
        stem = slug(anchor, recs[0].get("rays", ""))
        nav.append((anchor, workload))
        scenes = sorted({scene_name(r) for r in recs})
        counts = sorted({str(r.get("ray_count")) for r in recs if r.get("ray_count")})
        out.append(f"<h2 id='{anchor}'>Workload: {e(workload)}</h2>")
        out.append(f"<p>{len(recs)} cases on {e(', '.join(scenes))} ({e(', '.join(counts))} rays). "
                   "Rays/s per structure (median of the timed repeats; ×E = against Embree on the same "
                   f"rays, ×grid = against grid on the same rays and backend; ★ fastest in its row); each "
                   "scene's last row is Embree's rays/s on the same rays, the reference.</p>")
        out += _chart_section({(workload,): recs}, chart_workload, charts_dir, out_dir, stem)
        out += _tables(workload_tables(recs, baselines, min_agree, stem), out_dir,
                       "No case of this workload.")
    return out, nav


def _compare_link(run_dir: Path, out_dir: Path) -> str:
    """compare.html of this run (lsbench compare BASE RUN --report), copied beside the page."""
    src = run_dir / "compare.html"
    if not src.is_file():
        return ""
    if run_dir.resolve() != out_dir.resolve():
        shutil.copy2(src, out_dir / "compare.html")
    return ("<p class='warn'>This run was compared with a base run: <a href='compare.html'>compare.html</a> "
            "(cases sorted by severity).</p>")


def write_report(run_dir, out_dir=None) -> Path:
    """Write OUT_DIR/index.html (default OUT_DIR = RUN_DIR) with charts under OUT_DIR/charts/ and
    tables under OUT_DIR/tables/. Returns the path of index.html. FileNotFoundError when RUN_DIR
    is no folder, EmptyRunError when it holds no record (a page of empty tables would look like a
    run that did nothing)."""
    run_dir = Path(run_dir)
    info, records = read_run(run_dir)
    if not records:
        what = "results.jsonl is empty" if (run_dir / "results.jsonl").exists() else "no results.jsonl"
        raise EmptyRunError(f"{run_dir}: no case records ({what}); nothing to report")
    label_scenes(records)
    out_dir = Path(out_dir) if out_dir else run_dir
    out_dir.mkdir(parents=True, exist_ok=True)
    charts_dir = out_dir / "charts"
    for stale in ("charts", "tables", "heatmap_rows"):  # files of an earlier report of the same run
        if (out_dir / stale).is_dir():
            for p in (out_dir / stale).iterdir():
                if p.suffix in (".png", ".svg", ".csv", ".tex"):
                    p.unlink()
    min_agree = min_agreement(info)
    ok = sum(1 for r in records if succeeded(r))
    baselines = Baselines(records)
    by_scene = _grouped(records, scene_name)
    by_scene_workload = _grouped(records, lambda r: (scene_name(r), workload_label(r)))

    workloads, workload_nav = _workload_sections(records, baselines, min_agree, charts_dir, out_dir)
    body = list(workloads)
    for anchor, heading, text, tables in thesis_tables(records, baselines, min_agree):
        body.append(f"<h2 id='{anchor}'>{e(heading)}</h2><p>{e(text)}</p>")
        body += _tables(tables, out_dir, "No Line Space cases in this run." if anchor == "table3"
                        else "No plain-structure cases in this run.")

    auto = auto_section(records)
    body += auto

    body.append("<h2 id='memory'>Speed against memory</h2>")
    body.append("<p>rays/s against the structure's bytes, one marker per case (colour: structure, "
                "shape: backend). Ringed and labelled (structure, resolution, N): the Pareto front — "
                "no other case is faster with less memory. The Line Space structures buy speed with "
                "memory; this is that trade-off.</p>")
    body += _chart_section(by_scene_workload, chart_rays_memory, charts_dir, out_dir, "rays_memory")

    body.append("<h2 id='speed'>Speed against accuracy</h2>")
    body.append("<p>x: rays that disagree with Embree per million (0, then log; red ×: some "
                "disagreement the float64 classifier cannot explain). Up is faster, left agrees "
                "better. Ringed and labelled: the Pareto front — no other case is both faster and at "
                "least as accurate. When every case agrees, the chart says so and ranks them by speed; "
                "the image accuracy below says whether a disagreement shows.</p>")
    body += _chart_section(by_scene_workload, chart_speed_accuracy, charts_dir, out_dir, "speed_accuracy")

    files = Files(run_dir, out_dir)
    body += image_accuracy_section(records, files)

    body.append("<h2 id='build'>Build time against memory</h2>")
    body += _chart_section(_grouped(one_per_build(records), scene_name), chart_build_memory, charts_dir, out_dir,
                           "build_memory")

    body.append("<h2 id='repeats'>Spread of the timing repeats</h2>")
    body.append("<p>Every timed repeat of every case: a wide bar means a noisy measurement "
                "(compare uses these repeats to tell a real slowdown from noise).</p>")
    body += _chart_section(by_scene, chart_repeats, charts_dir, out_dir, "repeats")

    body += heatmap_section(records, files, out_dir)
    body += _details(records, min_agree)
    body += _environment(info, records)

    title = f"lsbench report — {scenario_name(info) or run_dir.name}"
    nav = [*workload_nav, ("table1", "Table 1 FPS"), ("table2", "Table 2 memory"),
           ("table3", "Table 3 Line Space"), *([("auto", "Auto settings")] if auto else []),
           ("memory", "Speed vs memory"), ("speed", "Speed vs accuracy"),
           ("image", "Image ΔE"), ("build", "Build vs memory"), ("repeats", "Repeats"),
           ("heatmaps", "Heatmaps"), ("cases", "All cases"), ("env", "Environment")]
    out = [f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>{e(str(title))}</title>",
           f"<style>{CSS}</style></head><body>",
           f"<h1>{e(str(title))}</h1>",
           f"<p>{e(str(run_dir))} · {e(str(info.get('date', '')))} · commit "
           f"{e(format_commit(info.get('commit'), info.get('dirty')))} · "
           f"<b>{ok}</b> cases ok, <b>{len(records) - ok}</b> failed</p>",
           "<nav>" + "".join(f"<a href='#{a}'>{e(t)}</a>" for a, t in nav) + "</nav>",
           _compare_link(run_dir, out_dir), *history_link(info, out_dir), *body, "</body></html>"]
    index = out_dir / "index.html"
    index.write_text("\n".join(out))
    return index
