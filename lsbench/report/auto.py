"""The report's "Auto settings" section (issue 17): for every case whose resolution, N or K was
"auto", what the cost model chose under the device-memory budget and why (lsbench/model/cost.py,
docs/fit.md): the constants it used (fitted by `lsbench fit`, or the documented defaults), the
chosen setting's predicted rays/s and bytes beside the measured ones, the runners-up, and, where
the same run also swept fixed settings of the case's group (scenarios/fit-check.toml,
fit-thesis.toml), the best of them that fit and the time the choice took against the sweep's
(lsbench/model/check.py: the same rows as `lsbench fit --check`)."""
from __future__ import annotations

import html

from lsbench.model.check import check_rows, setting_of, setting_text
from lsbench.report.records import scene_name, succeeded

e = html.escape
RUNNERS_UP = 3  # runners-up shown per case; the record keeps them all


def is_auto(rec: dict) -> bool:
    return rec.get("auto") is not None


def used_default_constants(rec: dict) -> bool:
    """The choice ranked settings with DEFAULTS (model/constants.py), not this device's own fit."""
    return str((rec.get("auto") or {}).get("constants", "")).startswith("defaults")


def option_setting(option: dict) -> str:
    """The setting of one option of a choice (Option.summary: resolution "RxRyRz", ls_n, ...)."""
    return setting_of(option["resolution"].split("x"), option.get("ls_n"), option.get("ls_min_candidates"))


def option_text(option: dict) -> str:
    """One option of a choice ("chosen" or a runner-up) in a few words."""
    rate = option.get("predicted_rays_per_second")
    mib = option.get("predicted_bytes")
    parts = [f"{rate / 1e6:.3f} Mrays/s" if rate else "no rate",
             f"{'' if option.get('bytes_exact') else '~'}{mib / 2**20:.1f} MiB" if mib is not None else "? MiB"]
    if option.get("fits_budget") is False:
        parts.append("over the budget")
    return f"{option_setting(option)}: {', '.join(parts)}"


def _rebuilt_text(auto: dict) -> str:
    """The options built first and found over the budget (a Line Space's bytes are estimated from a
    sample of cells; model/cost.py), which the case then passed over for the next that fits."""
    over = auto.get("rebuilt_over_budget") or []
    return "".join(f"; first built {option_setting(o)} at {o['built_bytes'] / 2**20:.1f} MiB, "
                   "over the budget" for o in over if o.get("built_bytes") is not None)


def _num(v, fmt: str) -> str:
    return "-" if v is None else format(v, fmt)


def auto_section(records: list[dict]) -> list[str]:
    """HTML for the section (empty when the run has no auto case)."""
    autos = [r for r in records if is_auto(r)]
    if not autos:
        return []
    checks = {id(row.auto_record): row for row in check_rows(records) if row.auto_record is not None}
    out = ["<h2 id='auto'>Auto settings</h2>",
           "<p>What the cost model chose for each case with an \"auto\" resolution, N or K: the cheapest "
           "predicted setting that fits the device-memory budget (docs/fit.md). Predicted beside measured; "
           "~ marks a byte estimate from a sample of cells (Line Spaces), the rest are exact. "
           "Where this run also swept fixed settings of the same scene, rays, structure, backend and "
           "budget, the best of them that ran is shown with the choice's share of the sweep's time.</p>"]
    defaults = [r for r in autos if used_default_constants(r)]
    if defaults:
        out.append(f"<p class='warn'>{len(defaults)} of {len(autos)} auto cases ranked their settings with "
                   "the documented default constants, measured on another machine: run <code>lsbench fit</code> "
                   "on this one so that they use its own.</p>")
    head = ("scene", "rays", "structure", "backend", "budget MiB", "chosen", "constants", "predicted Mrays/s",
            "measured Mrays/s", "measured / predicted", "predicted MiB", "built MiB", "options (over budget, "
            "over device limits)", "choose s", "runners-up (predicted)", "best swept", "auto / best swept",
            "choose / sweep")
    out.append("<div class='scroll'><table class='grid detail'><tr>" + "".join(f"<th>{e(h)}</th>" for h in head)
               + "</tr>")
    for r in autos:
        a = r["auto"]
        chosen = a.get("chosen") or {}
        ok = succeeded(r)
        predicted = chosen.get("predicted_rays_per_second")
        measured = r.get("rays_per_second") if ok else None
        constants = str(a.get("constants", "?"))
        defaults_used = used_default_constants(r)
        row = checks.get(id(r))
        best = ("-" if row is None or row.best_setting is None else
                f"{row.best_setting}: {row.best_rays_per_second / 1e6:.3f} Mrays/s (best of {row.swept})")
        cells = [
            scene_name(r), f"{r.get('rays')}@{r.get('width')}x{r.get('height')}", r.get("structure"), r.get("backend"),
            _num(a.get("budget_bytes") and a["budget_bytes"] / 2**20, "g"),
            (setting_text(r) if ok else (option_text(chosen) if chosen else "none fits")) + _rebuilt_text(a),
            "defaults (run lsbench fit)" if defaults_used else constants.rsplit("/", 1)[-1],
            _num(predicted and predicted / 1e6, ".3f"), _num(measured and measured / 1e6, ".3f"),
            _num(measured / predicted if measured and predicted else None, ".2f"),
            (f"{'' if chosen.get('bytes_exact') else '~'}{chosen['predicted_bytes'] / 2**20:.1f}"
             if chosen.get("predicted_bytes") is not None else "-"),
            _num(r.get("memory_bytes") / 2**20 if ok and r.get("memory_bytes") is not None else None, ".1f"),
            f"{a.get('options', '?')} ({a.get('options_over_budget', 0)}, {a.get('options_over_device_limits', 0)})",
            _num(a.get("choose_seconds"), ".1f"),
            "; ".join(option_text(o) for o in (a.get("runners_up") or [])[:RUNNERS_UP]) or "-",
            best, _num(row.ratio if row else None, ".2f"),
            "-" if row is None or row.choose_share is None else f"{100 * row.choose_share:.1f} %",
        ]
        cls = "fail" if not ok else ("warn" if defaults_used else "")
        out.append(f"<tr class='{cls}' title='{e(r.get('key', ''))}'>"
                   + "".join(f"<td>{e(str(c))}</td>" for c in cells) + "</tr>")
    out.append("</table></div>")
    return out
