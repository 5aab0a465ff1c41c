"""Static HTML report of one run: index.html + PNG charts, opens from disk (no network, no JS).

Sections follow the thesis' (Delgado Krämer 2019) evaluation (chapter 6): the environment, Tables 1-3
(lsbench/report/tables.py), speed against accuracy, build time against memory and the spread of
the timing repeats (lsbench/report/charts.py), the heatmap gallery (images named in the records'
`heatmaps`), every case in detail (counts, buffers, counters), and the full text of every failure.
"""
from __future__ import annotations

import html
import json
import shutil
from collections import OrderedDict
from pathlib import Path

from lsbench.report.charts import chart_build_memory, chart_repeats, chart_speed_accuracy
from lsbench.report.format import fmt_mib, fmt_num, fmt_pct, fmt_seconds, fmt_si, slug
from lsbench.report.records import case_label, label_scenes, resolution_label, scene_name, succeeded
from lsbench.report.tables import thesis_tables
from lsbench.results.store import (format_commit, read_run, run_devices, run_settings,
                                   scenario_name)

BROWSER_IMAGES = {".png", ".jpg", ".jpeg", ".gif", ".svg", ".webp"}

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


def _gallery(records, run_dir: Path, out_dir: Path) -> list[str]:
    out = ["<h2 id='heatmaps'>Heatmaps</h2>"]
    items = [(r, name, rel) for r in records for name, rel in (r.get("heatmaps") or {}).items()]
    if not items:
        out.append("<p class='small'>No heatmaps in this run (they are written by profiling runs "
                   "with work counters).</p>")
        return out
    same = run_dir.resolve() == out_dir.resolve()
    out.append("<div class='gallery'>")
    for r, name, rel in items:
        src = run_dir / rel
        if not src.exists():
            out.append(f"<figure class='missing'><div>missing: {e(str(rel))}</div>"
                       f"<figcaption>{e(case_label(r, True))}<br>{e(name)}</figcaption></figure>")
            continue
        if same:
            href = Path(rel).as_posix()
        else:  # copy so the report folder stands alone
            dest = out_dir / "heatmaps" / slug(rel)
            dest.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest)
            href = dest.relative_to(out_dir).as_posix()
        if src.suffix.lower() in BROWSER_IMAGES:
            body = f"<a href='{e(href)}'><img src='{e(href)}' alt='{e(name)}' loading='lazy'></a>"
        else:
            body = f"<div><a href='{e(href)}'>{e(src.name)}</a> (open in an image viewer)</div>"
        out.append(f"<figure>{body}<figcaption>{e(case_label(r, True))}<br>{e(name)}</figcaption></figure>")
    out.append("</div>")
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
.small{font-size:11px;color:#555}
.warn{background:#fff3cd;border:1px solid #e0c060;padding:.4em .8em}
pre{margin:0;font-size:11px;white-space:pre-wrap}
pre.failtext{background:#fbeaea;padding:.5em;border-left:3px solid #c33;max-height:20em;overflow:auto}
.gallery{display:flex;flex-wrap:wrap;gap:12px}
figure{margin:0;width:260px;font-size:11px}
figure img{width:260px;image-rendering:pixelated;border:1px solid #ccc}
figure.missing div{height:80px;background:#eee;display:flex;align-items:center;justify-content:center}
img.chart{max-width:100%;border:1px solid #eee;margin:.3em 0}
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
    """One chart per group of records ({(scene, ...): records}), or a line saying none had data."""
    out = []
    for group, recs in groups.items():
        parts = group if isinstance(group, tuple) else (group,)
        title = parts[0] + "".join(f" — rays '{p}'" for p in parts[1:])
        path = chart(recs, charts_dir / f"{name}_{slug(*parts)}.png", title)
        if path:
            out.append(f"<img class='chart' src='{e(path.relative_to(out_dir).as_posix())}' "
                       f"alt='{e(name.replace('_', ' '))} {e(parts[0])}'>")
    return out or ["<p class='small'>No successful case to plot.</p>"]


def _grouped(records, key_fn) -> dict:
    groups: dict = OrderedDict()
    for r in sorted(records, key=key_fn):
        groups.setdefault(key_fn(r), []).append(r)
    return groups


def write_report(run_dir, out_dir=None) -> Path:
    """Write OUT_DIR/index.html (default OUT_DIR = RUN_DIR) with charts under OUT_DIR/charts/.
    Returns the path of index.html. FileNotFoundError when RUN_DIR is no folder, EmptyRunError
    when it holds no record (a page of empty tables would look like a run that did nothing)."""
    run_dir = Path(run_dir)
    info, records = read_run(run_dir)
    if not records:
        what = "results.jsonl is empty" if (run_dir / "results.jsonl").exists() else "no results.jsonl"
        raise EmptyRunError(f"{run_dir}: no case records ({what}); nothing to report")
    label_scenes(records)
    out_dir = Path(out_dir) if out_dir else run_dir
    out_dir.mkdir(parents=True, exist_ok=True)
    charts_dir = out_dir / "charts"
    if charts_dir.exists():  # stale charts of an earlier report of the same run
        for p in charts_dir.glob("*.png"):
            p.unlink()
    min_agree = min_agreement(info)
    ok = sum(1 for r in records if succeeded(r))

    title = f"lsbench report — {scenario_name(info) or run_dir.name}"
    out = [f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>{e(str(title))}</title>",
           f"<style>{CSS}</style></head><body>",
           f"<h1>{e(str(title))}</h1>",
           f"<p>{e(str(run_dir))} · {e(str(info.get('date', '')))} · commit "
           f"{e(format_commit(info.get('commit'), info.get('dirty')))} · "
           f"<b>{ok}</b> cases ok, <b>{len(records) - ok}</b> failed</p>",
           "<nav><a href='#env'>Environment</a><a href='#table1'>Table 1 FPS</a>"
           "<a href='#table2'>Table 2 memory</a><a href='#table3'>Table 3 Line Space</a>"
           "<a href='#speed'>Speed vs accuracy</a><a href='#build'>Build vs memory</a>"
           "<a href='#repeats'>Repeats</a><a href='#heatmaps'>Heatmaps</a>"
           "<a href='#cases'>All cases</a></nav>"]
    out += _environment(info, records)
    out += thesis_tables(records, min_agree)
    by_scene = _grouped(records, scene_name)

    out.append("<h2 id='speed'>Speed against accuracy</h2>")
    out.append("<p>One marker per case (colour: structure, shape: backend). Up is faster, left "
               "agrees better with Embree (0 = every ray agrees). Ringed and labelled: the Pareto "
               "front — no other case is both faster and at least as accurate.</p>")
    out += _chart_section(_grouped(records, lambda r: (scene_name(r), str(r.get("rays", "")))),
                          chart_speed_accuracy, charts_dir, out_dir, "speed_accuracy")

    out.append("<h2 id='build'>Build time against memory</h2>")
    out += _chart_section(by_scene, chart_build_memory, charts_dir, out_dir, "build_memory")

    out.append("<h2 id='repeats'>Spread of the timing repeats</h2>")
    out.append("<p>Every timed repeat of every case: a wide bar means a noisy measurement "
               "(compare uses these repeats to tell a real slowdown from noise).</p>")
    out += _chart_section(by_scene, chart_repeats, charts_dir, out_dir, "repeats")

    out += _gallery(records, run_dir, out_dir)
    out += _details(records, min_agree)
    out.append("</body></html>")
    index = out_dir / "index.html"
    index.write_text("\n".join(out))
    return index
