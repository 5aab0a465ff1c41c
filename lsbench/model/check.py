"""The fit check (issue 17, scenarios/fit-check.toml): each auto case beside the best ok case of
the fixed settings swept for the same scene, rays, structure, backend and budget (a swept case over
the budget failed, so the best ok one is the best that fits), and the time the choice took beside
the sweep's.

Speed is compared in rays/s (the best swept case is the fastest). Where every case of the group
timed Embree, x Embree (rays/s over Embree's on the same rays in the same worker) and its ratio are
shown beside it: under a load that changes between the cases the ratio in one process cancels
some of it, but on llvmpipe Embree's own rate also swings with what the driver's threads still do
(atrium, svo 256^3 run twice in a row on an idle machine: 0.97 and 0.96 Mrays/s, 0.076x and
0.134x Embree), so neither alone decides."""
from __future__ import annotations

import statistics
from dataclasses import dataclass, field


@dataclass
class CheckRow:
    scene: str
    structure: str
    backend: str
    budget_mib: float | None
    auto_setting: str
    auto_rays_per_second: float | None  # None: the auto case failed
    auto_mib: float | None
    predicted_rays_per_second: float | None
    best_setting: str | None  # None: no swept case ran ok
    best_rays_per_second: float | None
    best_mib: float | None
    choose_seconds: float | None
    sweep_seconds: float  # wall time of the swept cases, failed ones included
    swept: int
    auto_x_embree: float | None = None  # rays/s over Embree's in the same worker (None: not timed)
    best_x_embree: float | None = None
    auto_record: dict | None = field(default=None, repr=False)  # what pair_rows rebuilds
    best_record: dict | None = field(default=None, repr=False)
    paired: "Paired | None" = None  # the two settings rerun alternated (pair_rows)
    not_paired: str = ""  # why pair_rows could not rerun them

    @property
    def choose_share(self) -> float | None:
        """The seconds the choice took over the sweep's wall time."""
        if self.choose_seconds is None or not self.sweep_seconds:
            return None
        return self.choose_seconds / self.sweep_seconds

    @property
    def same_setting(self) -> bool:
        """The auto case built the best swept setting: their ratio is then the timing noise."""
        return self.best_setting == self.auto_setting

    @property
    def ratio(self) -> float | None:
        """Auto rays/s over the best swept rays/s (1.0 = as fast)."""
        if self.auto_rays_per_second is None or not self.best_rays_per_second:
            return None
        return self.auto_rays_per_second / self.best_rays_per_second

    @property
    def ratio_x_embree(self) -> float | None:
        """The same as x Embree (None where a case did not time Embree)."""
        if self.auto_x_embree is None or not self.best_x_embree:
            return None
        return self.auto_x_embree / self.best_x_embree


@dataclass(frozen=True)
class Paired:
    """Auto's rays/s over the best swept setting's, both rebuilt in one process and their traces
    alternated: the median and quartiles of the per-pair ratios (best's device time over auto's)."""
    ratio: float
    low: float
    high: float
    pairs: int


def x_embree(rec: dict) -> float | None:
    """rays/s over Embree's rays/s in the same worker, or None where Embree was not timed."""
    embree = rec.get("embree_rays_per_second")
    return rec["rays_per_second"] / embree if embree and rec.get("rays_per_second") else None


def setting_of(dims, n=0, k=0) -> str:
    """A setting in a few words: "128" (cubic) or "103x43x63", then " N=3 K=16" for a Line Space."""
    dims = tuple(int(d) for d in dims)
    text = str(dims[0]) if len(set(dims)) == 1 else "x".join(map(str, dims))
    return text + (f" N={n} K={k or 0}" if n else "")


def setting_text(rec: dict) -> str:
    if rec.get("resolution_x") is None:
        return "-"
    return setting_of((rec["resolution_x"], rec["resolution_y"], rec["resolution_z"]), rec.get("ls_n"),
                      rec.get("ls_min_candidates"))


def check_rows(records: list[dict]) -> list[CheckRow]:
    def group(r):
        return (r.get("scene"), r.get("rays_hash") or r.get("rays"), r.get("structure"), r.get("backend"),
                r.get("budget_mib"))

    swept: dict = {}
    for r in records:
        if not r.get("auto") and "|rauto|" not in r.get("key", "") and "|nauto|" not in r.get("key", "") \
                and "|kauto|" not in r.get("key", ""):
            swept.setdefault(group(r), []).append(r)
    rows = []
    for r in records:
        if r.get("auto") is None and "auto|" not in r.get("key", ""):
            continue
        others = swept.get(group(r), [])
        ok = [o for o in others if o.get("status") == "ok" and o.get("rays_per_second")]
        auto_ok = r.get("status") == "ok"
        by_embree = all(x_embree(o) is not None for o in ok + ([r] if auto_ok else []))
        best = max(ok, key=lambda o: o["rays_per_second"]) if ok else None
        predicted = r.get("predicted") or {}
        rows.append(CheckRow(
            r.get("scene"), r.get("structure"), r.get("backend"), r.get("budget_mib"), setting_text(r),
            r.get("rays_per_second") if auto_ok else None,
            r["memory_bytes"] / 2**20 if auto_ok and r.get("memory_bytes") is not None else None,
            predicted.get("rays_per_second"), setting_text(best) if best else None,
            best["rays_per_second"] if best else None, best["memory_bytes"] / 2**20 if best else None,
            (r.get("auto") or {}).get("choose_seconds"),
            sum(o.get("wall_seconds") or 0.0 for o in others), len(others),
            x_embree(r) if auto_ok and by_embree else None, x_embree(best) if best and by_embree else None,
            r if auto_ok else None, best))
    return rows


def _build_params(rec: dict):
    from lsbench.backends import BuildParams

    return BuildParams(resolution=(rec["resolution_x"], rec["resolution_y"], rec["resolution_z"]),
                       ls_n=rec.get("ls_n") or 0, ls_min_candidates=rec.get("ls_min_candidates") or 0,
                       leaf_size=rec.get("leaf_size") or 0)


def _case_inputs(rec: dict):
    """The record's scene and rays, made again."""
    from lsbench.inputs.rays import make_rays
    from lsbench.inputs.scene import Camera
    from lsbench.inputs.scenes import load_scene

    scene = load_scene(rec["scene_source"].removeprefix("builtin:"))
    cam = rec.get("camera")
    camera = Camera(tuple(cam["eye"]), tuple(cam["target"]), tuple(cam["up"]), cam["fov"]) if cam else None
    return scene, make_rays(rec["rays"], scene, rec["width"], rec["height"], camera, rec.get("ray_params") or {})


def _inputs_changed(rec: dict, scene, rays) -> str:
    """Why `scene` and `rays` are not what the record traced (its scene_hash, rays_hash), else ""."""
    changed = [name for name, now in (("scene_hash", scene.content_hash), ("rays_hash", rays.content_hash))
               if rec.get(name) != now]
    return f"{rec['scene_source']}: {' and '.join(changed)} differ from the run's" if changed else ""


def pair_rows(rows: list[CheckRow], pairs: int, log=print) -> None:
    """Sets `paired` on every row whose auto case chose another setting than the best swept one
    (both ok): on this machine's device of the row's backend, both settings are built once and
    traced alternately `pairs` times (auto first in odd pairs, best first in even ones), so both
    see the same load. One run of each setting, minutes apart, swings by up to 1.55x on llvmpipe
    (docs/fit.md); the paired median resolves a few percent. A row whose scene or rays are no longer
    what the run traced, or whose rebuild fails, gets `not_paired` (the reason) instead."""
    from lsbench import backends

    todo = [r for r in rows if r.auto_record and r.best_record and not r.same_setting]
    inputs: dict = {}
    for i, row in enumerate(todo, 1):
        a, b = row.auto_record, row.best_record
        log(f"[{i}/{len(todo)}] {row.scene} {row.structure} {row.backend}: {row.auto_setting} against "
            f"{row.best_setting}, {pairs} alternated pairs")
        key = (a["scene_source"], a["rays"], a["width"], a["height"], str(a.get("camera")), str(a.get("ray_params")))
        try:
            if key not in inputs:
                inputs.clear()  # one scene's rays at a time
                inputs[key] = _case_inputs(a)
            scene, rays = inputs[key]
            changed = _inputs_changed(a, scene, rays) or _inputs_changed(b, scene, rays)
            if changed:
                raise ValueError(changed)
            row.paired = _alternate(backends.get_device(row.backend), row.structure, scene, rays, a, b, pairs)
        except Exception as exc:  # noqa: BLE001 - a row that cannot be rerun says why; the others still run
            row.not_paired = f"{type(exc).__name__}: {exc}".splitlines()[0]
            log(f"  not paired: {row.not_paired}")


def _alternate(device, structure: str, scene, rays, auto: dict, best: dict, pairs: int) -> Paired:
    from lsbench import backends

    built = []
    try:
        for rec in (auto, best):
            built.append(backends.build(device, structure, scene, _build_params(rec)))
        for x in built:
            backends.trace(x, rays)  # warm-up (and the sorted order's first launch)
        ratios = []
        for k in range(pairs):
            order = (0, 1) if k % 2 == 0 else (1, 0)
            seconds = {j: backends.time_trace(built[j], rays, warmup=0, repeats=1).seconds[0] for j in order}
            ratios.append(seconds[1] / seconds[0])
    finally:
        for x in built:
            x.release()
    q = statistics.quantiles(ratios, n=4) if len(ratios) > 1 else [ratios[0]] * 3
    return Paired(statistics.median(ratios), q[0], q[2], pairs)


def check_table(rows: list[CheckRow]) -> list[str]:
    from lsbench.report.format import text_table

    def num(v, fmt):
        return "-" if v is None else format(v, fmt)

    header = ("scene", "structure", "backend", "budget MiB", "auto setting", "auto Mrays/s", "auto x Embree",
              "auto MiB", "predicted Mrays/s", "best swept", "best Mrays/s", "best x Embree", "best MiB",
              "auto/best", "same", "x Embree auto/best", "choose s", "sweep s", "choose/sweep")
    body = [(r.scene, r.structure, r.backend, num(r.budget_mib, "g"), r.auto_setting,
             num(r.auto_rays_per_second and r.auto_rays_per_second / 1e6, ".3f"), num(r.auto_x_embree, ".3f"),
             num(r.auto_mib, ".1f"), num(r.predicted_rays_per_second and r.predicted_rays_per_second / 1e6, ".3f"),
             r.best_setting or "-", num(r.best_rays_per_second and r.best_rays_per_second / 1e6, ".3f"),
             num(r.best_x_embree, ".3f"), num(r.best_mib, ".1f"), num(r.ratio, ".2f"), "=" if r.same_setting else "",
             num(r.ratio_x_embree, ".2f"), num(r.choose_seconds, ".1f"), f"{r.sweep_seconds:.0f}",
             "-" if r.choose_share is None else f"{100 * r.choose_share:.1f} %")
            for r in rows]
    if any(r.paired or r.not_paired for r in rows):
        header += ("paired auto/best", "quartiles")
        body = [b + ((f"{r.paired.ratio:.2f}", f"{r.paired.low:.2f}-{r.paired.high:.2f}") if r.paired
                     else ("not paired", r.not_paired) if r.not_paired else ("-", "-"))
                for b, r in zip(body, rows)]
    return text_table(header, body, right={3, 5, 6, 7, 8, 10, 11, 12, 13, 15, 16, 17, 18, 19, 20})
