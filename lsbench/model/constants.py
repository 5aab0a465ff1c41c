"""The cost model's constants per device (model/cost.py: seconds per ray = ray + step[family] x
iterations + test x candidate tests + lookup x Line Space lookups, the iterations and tests as the
device's SIMD groups issue them), fitted by `lsbench fit` from the work counters and device times
of a short calibration sweep, and stored one JSON file per device:

    $LSBENCH_FIT_DIR/<backend>-<device slug>.json      (default folder ~/.cache/lsbench/fit)
    {"device": ..., "backend": ..., "driver": ..., "ray": s, "step": {"grid": s, "svo": s, "esvo": s},
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


def family(structure: str) -> str:
    """Whose walk a structure runs (its step constant): grid, svo or esvo."""
    return structure.removesuffix("-ls")


@dataclass(frozen=True)
class Constants:
    ray: float  # seconds per ray, whatever it crosses (setup, hit store)
    step: dict  # seconds per walk iteration, per family (cost.family)
    test: float  # seconds per ray/triangle test
    lookup: float  # seconds per Line Space shaft lookup
    source: str = "defaults"
    extra: dict = field(default_factory=dict)  # what the file holds besides (cases, residual, ...)


# Fallback constants when no `lsbench fit` has run on a device: `lsbench fit` (atrium + spheres,
# 128x128, the calibration of commands/fit.py) on the idle 2-core development machine, 2026-12-02
# (llvmpipe 22.3.6, LLVM 15, SIMD groups of 8 lanes, `--repeats 5`; PoCL 3.1 on an AMD EPYC, one
# lane), rounded; fit residuals 10 % / 16 % rms (docs/fit.md). On any other device they rank
# settings only roughly: run `lsbench fit`.
DEFAULTS = {
    "glsl": Constants(ray=1.4e-8, step={"grid": 9.6e-9, "svo": 2.0e-8, "esvo": 1.7e-8}, test=5.9e-9,
                      lookup=8.7e-8, source="defaults (glsl, llvmpipe 22.3.6 on the development machine; docs/fit.md)"),
    "opencl": Constants(ray=3.1e-7, step={"grid": 1.8e-9, "svo": 1.0e-8, "esvo": 4.5e-9}, test=3.4e-9,
                        lookup=2.3e-8, source="defaults (opencl, PoCL 3.1 on the development machine; docs/fit.md)"),
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
    try:
        data = json.loads(path.read_text())
        lanes = simd_lanes(device)
        if data.get("simd_width") != lanes:  # fitted on other work than the model predicts here
            fallback = DEFAULTS[device.backend]
            return dataclasses.replace(fallback, source=(
                f"{fallback.source}; {path} was fitted for SIMD groups of {data.get('simd_width', 'unknown')} "
                f"lanes (before issued work was fitted, or another device), this device runs {lanes}: "
                "run `lsbench fit` again"))
        extra = {k: v for k, v in data.items() if k not in ("ray", "step", "test", "lookup")}
        return Constants(float(data["ray"]), {f: float(data["step"][f]) for f in FAMILIES}, float(data["test"]),
                         float(data["lookup"]), str(path), extra)
    except (OSError, ValueError, KeyError, TypeError) as exc:  # a damaged file: say so, use the defaults
        fallback = DEFAULTS[device.backend]
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


COLUMNS = ("ray", "step_grid", "step_svo", "step_esvo", "test", "lookup")


def design_row(structure: str, iterations: float, tests: float, lookups: float) -> list[float]:
    """One calibration case as a row of the least-squares system (COLUMNS)."""
    fam = family(structure)
    return [1.0] + [iterations if fam == f else 0.0 for f in FAMILIES] + [tests, lookups]


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


def constants_from_fit(coef: np.ndarray, source: str, extra: dict) -> Constants:
    c = dict(zip(COLUMNS, (float(v) for v in coef)))
    return Constants(c["ray"], {f: c[f"step_{f}"] for f in FAMILIES}, c["test"], c["lookup"], source, extra)
