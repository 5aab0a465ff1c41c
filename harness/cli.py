"""`lsbench` command line: run, gate, trace (+ runs, report, compare from their modules)."""
from __future__ import annotations

import argparse
import datetime as _dt
import json
import platform
import subprocess
import sys
from pathlib import Path

from .scenario import REPO_ROOT, Case, RunSettings, ScenarioError, load_scenario


class UsageError(ValueError):
    pass


def git_state(repo: Path = REPO_ROOT) -> tuple[str, bool]:
    from .store import git_state as _git_state

    commit, dirty = _git_state(repo)
    return (commit or "unknown"), bool(dirty)


def record_env() -> dict:
    commit, dirty = git_state()
    return {"commit": commit, "dirty": dirty}


def _print(*a, **k):
    print(*a, **k, flush=True)


def _uses_gpu(backend_names) -> bool:
    import backends

    for name in backend_names:
        info = backends.get_device(name).info()
        if name == "opencl" and "GPU" in str(info.get("device_type", "")):
            return True
        if name == "glsl" and not any(s in info["device"].lower() for s in ("llvmpipe", "softpipe", "lavapipe")):
            return True
    return False


def default_out_dir(name: str) -> Path:
    commit, dirty = git_state()
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    return REPO_ROOT / "reports" / f"{name}-{stamp}-{commit[:7]}{'-dirty' if dirty else ''}"


def _write_run_json(out: Path, scenario, argv) -> None:
    import backends

    from .store import environment_info, write_run_info

    commit, dirty = git_state()
    info = environment_info()
    devices = {}
    for name in sorted({c.backend for c in scenario.cases}):
        try:
            d = backends.get_device(name).info()
            devices[name] = {"device": d["device"], "driver": d["driver"]}
        except Exception as exc:  # the cases will fail with the reason; run.json says it too
            devices[name] = {"device": None, "error": str(exc).splitlines()[0]}
    info.update({"commit": commit, "dirty": dirty, "devices": devices, "scenario": scenario.path,
                 "scenario_name": scenario.name, "command": " ".join(argv)})
    write_run_info(out, info)


def _check_inputs(scenario) -> None:
    """Load every scene file and .npz ray file of the scenario once, before any case runs: a
    missing or corrupt file is a one-line error (exit 2), not a run of failed cases."""
    from .rays import load_rays_file
    from .scenes import builtin_names, load_scene

    for spec in dict.fromkeys(c.scene for c in scenario.cases):
        if spec not in builtin_names():
            load_scene(spec)
    for spec in dict.fromkeys(c.rays for c in scenario.cases):
        if spec.lower().endswith(".npz"):
            load_rays_file(spec)


def cmd_run(args) -> int:
    from .runner import run_scenario, summary_table

    scenario = load_scenario(args.scenario)
    if scenario.settings.gpu_width:
        scenario = load_scenario(args.scenario, gpu=_uses_gpu({c.backend for c in scenario.cases}))
    if args.memory_budget:
        import dataclasses
        scenario.settings = dataclasses.replace(scenario.settings, memory_budget_mb=args.memory_budget)
    _check_inputs(scenario)
    out = Path(args.out) if args.out else default_out_dir(scenario.name)
    out.mkdir(parents=True, exist_ok=True)
    _write_run_json(out, scenario, sys.argv)
    _print(f"lsbench run {scenario.name}: {len(scenario.cases)} cases -> {out}")
    records = run_scenario(scenario, out, record_env(), fresh=args.fresh,
                           heatmaps=True if args.heatmaps else None, log=_print)
    _print()
    _print(summary_table(records))
    _print(f"\nresults: {out / 'results.jsonl'}")
    args._records = records
    args._scenario = scenario
    return 0


def gate_failures(records, settings: RunSettings) -> list[str]:
    out = []
    for r in records:
        if r.get("status") != "ok":
            out.append(f"{r.get('key')}: FAILED: {r.get('reason')}")
        elif r["agreement"] < settings.min_agreement:
            out.append(f"{r.get('key')}: agreement {r['agreement']:.6f} < {settings.min_agreement} "
                       f"(missed {r.get('missed')}, extra {r.get('extra')}, wrong {r.get('wrong')}, "
                       f"ties {r.get('ties')}, of {r.get('ray_count')} rays)")
    return out


def cmd_gate(args) -> int:
    cmd_run(args)
    failures = gate_failures(args._records, args._scenario.settings)
    if failures:
        _print(f"\nGATE FAILED: {len(failures)} of {len(args._records)} cases below tolerance "
               f"(min agreement {args._scenario.settings.min_agreement}):")
        for f in failures:
            _print("  " + f)
        return 1
    _print(f"\ngate passed: {len(args._records)} cases at agreement >= {args._scenario.settings.min_agreement}")
    return 0


def _parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
        if w < 1 or h < 1:
            raise ValueError
        return w, h
    except ValueError:
        raise UsageError(f"--size must look like 512x512, got {text!r}") from None


def _parse_camera(text: str):
    """"ex,ey,ez:tx,ty,tz[:fov]" -> ((eye), (target), (up), fov)."""
    try:
        parts = text.split(":")
        eye = tuple(float(v) for v in parts[0].split(","))
        target = tuple(float(v) for v in parts[1].split(","))
        fov = float(parts[2]) if len(parts) > 2 else 60.0
        if len(eye) != 3 or len(target) != 3:
            raise ValueError
    except (ValueError, IndexError):
        raise UsageError(f"--camera must look like 'ex,ey,ez:tx,ty,tz[:fov]', got {text!r}") from None
    return (eye, target, (0.0, 1.0, 0.0), fov)


def cmd_trace(args) -> int:
    from .execute import execute
    from .rays import make_rays
    from .scenes import load_scene

    width, height = _parse_size(args.size)
    camera = _parse_camera(args.camera) if args.camera else None
    scene = load_scene(args.scene)  # bad input fails here, before anything looks like a result
    case = Case(args.scene, args.structure, args.backend, str(args.resolution), args.ls_n,
                args.ls_min_candidates, args.rays, width, height, camera)
    rays = make_rays(args.rays, scene, width, height, case.camera_object())
    settings = RunSettings(width=width, height=height, rays=args.rays, repeats=args.repeats,
                           warmup=args.warmup, rel_tol=args.rel_tol)
    rec = execute(case, settings, record_env(), dump_hits=args.dump_hits, heatmap_dir=args.heatmaps,
                  scene=scene, rays=rays)
    if args.json:
        print(json.dumps(rec, default=str))
    else:
        from .runner import progress_text, summary_table
        print(summary_table([rec]))
    return 0 if rec["status"] == "ok" else 1


def build_parser() -> argparse.ArgumentParser:
    import backends

    p = argparse.ArgumentParser(prog="lsbench", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)

    for name, fn, text in (("run", cmd_run, "run every case of a scenario"),
                           ("gate", cmd_gate, "run a scenario; exit 1 if any case is below its accuracy tolerance")):
        s = sub.add_parser(name, help=text)
        s.add_argument("scenario", help="scenario TOML file, e.g. scenarios/default.toml")
        s.add_argument("--out", help="run folder (default reports/<name>-<date>-<commit>); an existing one resumes")
        s.add_argument("--fresh", action="store_true", help="redo cases already in --out")
        s.add_argument("--heatmaps", action="store_true", help="write heatmaps for every case")
        s.add_argument("--memory-budget", type=float, metavar="MiB", help="host memory limit per case worker")
        s.set_defaults(func=fn)

    t = sub.add_parser("trace", help="build and trace one case, print its record")
    t.add_argument("--scene", required=True, help="built-in name or mesh file")
    t.add_argument("--structure", required=True, choices=backends.structure_names())
    t.add_argument("--backend", required=True, choices=list(backends.BACKENDS))
    t.add_argument("--resolution", default="64", help="64 (cubic) or RxRyRz")
    t.add_argument("--ls-n", type=int, default=0, help="Line Space patches per face edge")
    t.add_argument("--ls-min-candidates", type=int, default=0)
    t.add_argument("--size", default="256x256", help="image size WxH for camera rays")
    t.add_argument("--camera", help="eye and target 'ex,ey,ez:tx,ty,tz[:fov]' (default: the scene's)")
    t.add_argument("--rays", default="primary", help="ray set name or .npz file with origins/directions")
    t.add_argument("--repeats", type=int, default=5)
    t.add_argument("--warmup", type=int, default=1)
    t.add_argument("--rel-tol", type=float, default=1e-4)
    t.add_argument("--json", action="store_true", help="print the record as one JSON object")
    t.add_argument("--dump-hits", metavar="FILE.npz", help="write rays and hits (and Embree's) to FILE.npz")
    t.add_argument("--heatmaps", metavar="DIR", help="write work/clock heatmaps (EXR + PNG) to DIR")
    t.set_defaults(func=cmd_trace)

    for module in ("store", "report", "compare", "profile"):
        try:
            mod = __import__(f"harness.{module}", fromlist=["register"])
        except ImportError:
            continue
        if hasattr(mod, "register"):
            mod.register(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    from .rays import RayError
    from .scene import SceneError

    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (SceneError, RayError, ScenarioError, UsageError) as exc:
        print(f"lsbench: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("lsbench: interrupted; finished cases are kept in results.jsonl", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
