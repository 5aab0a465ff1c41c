"""The cost model's constants per device (model/cost.py: seconds per ray = launch / rays in the
launch + ray + step[structure] x iterations + test x candidate tests + lookup x Line Space lookups,
the iterations and tests as the device's SIMD groups issue them), fitted by `lsbench fit` from the
work counters and device times of a short calibration sweep, and stored one JSON file per device:

    $LSBENCH_FIT_DIR/<backend>-<device slug>.json      (default folder ~/.cache/lsbench/fit)
    {"device": ..., "backend": ..., "driver": ..., "launch": s, "ray": s, "step": {structure: s for STEPS},
     "test": s, "lookup": s, "simd_width": lanes the issued work was counted for,
     "cases": [the calibration cases: structure, setting, work (mean and issued), seconds/ray],
     "residual": relative rms error of the fit, "made": ISO time, "commit": ...}

A device without a stored file uses DEFAULTS (measured on this project's machines, below), and
the record of an auto case says which it used (`auto.constants`: the file, or "defaults (...)").
"""
from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lsbench.profile.simd import simd_lanes
from lsbench.report.format import slug

FAMILIES = ("grid", "svo", "esvo")
# One step constant per structure. A Line Space structure runs its plain walk (its family's), and
# its loop also holds the shaft lookup: on llvmpipe an iteration of it cost 1.4-1.8 times the plain
# walk's (fitted on the 2026-12-02 sweeps of four scenes, 135 cases: grid 12.5 / grid-ls 22.3, svo
# 20.0 / svo-ls 28.3, esvo 15.3 / esvo-ls 27.2 ns), on PoCL about the same (4.2 / 4.9, 16.2 / 16.2,
# 7.0 / 8.2). With one step per family the model ranked 3 of 12 auto/best pairs of the Line Space
# check wrong on llvmpipe (docs/fit.md). Fitted as the family's step plus a non-negative extra
# (design_row), so the few Line Space calibration cases cannot trade the step for the lookup.
STEPS = FAMILIES + tuple(f"{f}-ls" for f in FAMILIES)


@dataclass(frozen=True)
class Constants:
    ray: float  # seconds per ray, whatever it crosses (setup, hit store)
    step: dict  # seconds per walk iteration, per structure (STEPS)
    test: float  # seconds per ray/triangle test
    lookup: float  # seconds per Line Space shaft lookup
    launch: float = 0.0  # seconds per launch, whatever its rays (shared by them: launch / rays)
    source: str = "defaults"
    extra: dict = field(default_factory=dict)  # what the file holds besides (cases, residual, ...)


# Fallback constants when no `lsbench fit` has run on a device: four runs of `lsbench fit
# --repeats 5` (atrium + spheres, 128x128; two of them with the 256x256 launch cases) on the idle
# 2-core development machine, 2026-12-02 (an Intel Xeon, skylake-avx512: llvmpipe 22.3.6, LLVM 15,
# SIMD groups of 8 lanes; PoCL 3.1, one lane), their 120 cases per backend fitted together, rounded;
# fit residuals 14 % / 17 % rms (docs/fit.md). On any other device they rank settings only
# roughly: run `lsbench fit`.
DEFAULTS = {
    "glsl": Constants(ray=0.0, step={"grid": 1.43e-8, "svo": 2.48e-8, "esvo": 2.16e-8, "grid-ls": 2.70e-8,
                                     "svo-ls": 3.40e-8, "esvo-ls": 3.05e-8}, test=1.07e-8, lookup=0.0, launch=1.05e-2,
                      source="defaults (glsl, llvmpipe 22.3.6 on the development machine; docs/fit.md)"),
    "opencl": Constants(ray=8.6e-8, step={"grid": 3.1e-9, "svo": 1.28e-8, "esvo": 6.3e-9, "grid-ls": 3.1e-9,
                                          "svo-ls": 1.28e-8, "esvo-ls": 1.22e-8}, test=4.9e-9, lookup=2.0e-8,
                        launch=1.23e-2, source="defaults (opencl, PoCL 3.1 on the development machine; docs/fit.md)"),
}


def fit_dir() -> Path:
    env = os.environ.get("LSBENCH_FIT_DIR")
    return Path(env) if env else Path.home() / ".cache" / "lsbench" / "fit"


def constants_path(backend: str, device_name: str, folder: Path | None = None) -> Path:
    return (folder or fit_dir()) / f"{slug(backend, device_name)}.json"


def load_constants(device, folder: Path | None = None) -> Constants:
    """The stored constants of `device` (a backends Device), else its backend's DEFAULTS."""
    info = device.info()
    path = constants_path(device.backend, info["device"], folder)
    if not path.is_file():
        return DEFAULTS[device.backend]
    fallback = DEFAULTS[device.backend]
    try:
        data = json.loads(path.read_text())
        lanes = simd_lanes(device)
        if data.get("simd_width") != lanes:  # fitted on other work than the model predicts here
            return dataclasses.replace(fallback, source=(
                f"{fallback.source}; {path} was fitted for SIMD groups of {data.get('simd_width', 'unknown')} "
                f"lanes (before issued work was fitted, or another device), this device runs {lanes}: "
                "run `lsbench fit` again"))
        missing = [f"step {s}" for s in STEPS if s not in data["step"]] + (["launch"] if "launch" not in data else [])
        if missing:  # a file of one step per walk and no launch term (before 2026-12-02, evening)
            return dataclasses.replace(fallback, source=(
                f"{fallback.source}; {path} has no {', '.join(missing)} constant (fitted before each structure's "
                "step and the launch were fitted on their own): run `lsbench fit` again"))
        extra = {k: v for k, v in data.items() if k not in ("launch", "ray", "step", "test", "lookup")}
        return Constants(float(data["ray"]), {f: float(data["step"][f]) for f in STEPS}, float(data["test"]),
                         float(data["lookup"]), float(data["launch"]), str(path), extra)
    except (OSError, ValueError, KeyError, TypeError) as exc:  # a damaged file: say so, use the defaults
        return dataclasses.replace(fallback, source=f"{fallback.source}; {path} unreadable "
                                                    f"({type(exc).__name__}: {exc}; run `lsbench fit` again)")


def save_constants(data: dict, backend: str, device_name: str, folder: Path | None = None) -> Path:
    """Write a device's constants file (the module docstring's fields), atomically."""
    path = constants_path(backend, device_name, folder)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data, indent=1) + "\n")
    tmp.replace(path)
    return path


COLUMNS = (("launch", "ray") + tuple(f"step_{f}" for f in FAMILIES) + tuple(f"extra_step_{f}-ls" for f in FAMILIES)
           + ("test", "lookup"))


def design_row(structure: str, rays: int, iterations: float, tests: float, lookups: float) -> list[float]:
    """One calibration case (`rays` in its launch) as a row of the least-squares system (COLUMNS):
    its iterations under its family's step and, for a Line Space structure, under its extra step too."""
    fam = structure.removesuffix("-ls")
    return ([1.0 / rays, 1.0] + [iterations if fam == f else 0.0 for f in FAMILIES]
            + [iterations if structure == f"{f}-ls" else 0.0 for f in FAMILIES] + [tests, lookups])


def steps_from_fit(c: dict) -> dict:
    """Each structure's step constant from the fitted coefficients by name (COLUMNS)."""
    steps = {f: c[f"step_{f}"] for f in FAMILIES}
    steps.update({f"{f}-ls": c[f"step_{f}"] + c[f"extra_step_{f}-ls"] for f in FAMILIES})
    return steps


def fit_constants(rows: list[list[float]], seconds: list[float]) -> tuple[np.ndarray, float]:
    """Non-negative least squares of seconds per ray on the work (Lawson & Hanson's active set
    reduced to its simplest loop: solve, drop the most negative coefficient, solve again), each
    row weighted by 1 / its time so that every case counts by its relative error. Returns the
    coefficients (COLUMNS order) and the relative rms residual."""
    a = np.asarray(rows, np.float64)
    y = np.asarray(seconds, np.float64)
    w = 1.0 / np.maximum(y, 1e-30)
    active = np.ones(a.shape[1], bool)
    active &= np.abs(a).sum(axis=0) > 0  # a column no case exercises stays 0
    coef = np.zeros(a.shape[1])
    while active.any():
        sol, *_ = np.linalg.lstsq(a[:, active] * w[:, None], y * w, rcond=None)
        if (sol >= 0).all():
            coef[:] = 0
            coef[active] = sol
            break
        drop = np.flatnonzero(active)[int(np.argmin(sol))]
        active[drop] = False
    residual = float(np.sqrt(np.mean(((a @ coef - y) * w) ** 2))) if len(y) else 0.0
    return coef, residual
