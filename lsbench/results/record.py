"""The result record: one per case, one JSON object per line of results.jsonl.

Defined once here; every field is explained (name, unit, meaning) in docs/record.md, and
tests/test_record.py fails when the two disagree. The accuracy fields are those of
`lsbench.oracle.verify.Accuracy` and `lsbench.oracle.classifier.Classification`, flattened into
the record, so a field added there is a column here without being listed twice.

What decides whether a stored record still stands for a case (resume, lsbench/running/runner.py)
is here too: its identity (key, scene and ray contents) and environment (code, device, settings
that change results) must equal what the run would produce now (`reuse_mismatch`).
"""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field

from lsbench.oracle.classifier import Classification
from lsbench.oracle.verify import Accuracy

# 2: the first defined record (resolution_x/y/z, per-ray work means, settings, diff_hash);
# 3: ray_params and query (the workloads of issue 14); records without `schema_version` are
# older and are never reused.
SCHEMA_VERSION = 3


@dataclass
class Record:
    # what ran: the case (lsbench.inputs.scenario.Case) and its inputs
    key: str
    scene: str
    scene_source: str
    structure: str
    backend: str
    resolution: str
    resolution_x: int | None
    resolution_y: int | None
    resolution_z: int | None
    ls_n: int
    ls_min_candidates: int
    rays: str
    width: int
    height: int
    camera: dict | None = None
    ray_params: dict = field(default_factory=dict)
    query: str = "closest"
    leaf_size: int = 0
    scene_hash: str | None = None
    triangles: int | None = None
    rays_hash: str | None = None
    ray_count: int | None = None
    # what it ran on
    commit: str | None = None
    dirty: bool | None = None
    diff_hash: str | None = None
    versions: dict = field(default_factory=dict)
    planted_defect: str | None = None
    device: str | None = None
    driver: str | None = None
    backend_version: str | None = None
    node: dict | None = None  # the cluster node that ran the case (lsbench/running/cluster.py)
    settings: dict = field(default_factory=dict)
    budget_mib: float | None = None  # device-memory budget of the structure (case's, else the run's)
    auto: dict | None = None  # an "auto" case: what the cost model chose and why (lsbench/model/cost.py)
    # what came out
    status: str = "failed"
    reason: str = ""
    build_seconds: float | None = None
    memory_bytes: int | None = None
    buffers: dict = field(default_factory=dict)
    stats: dict = field(default_factory=dict)
    accuracy: Accuracy | None = None  # flattened into the record's columns by to_dict
    classification: Classification | None = None  # likewise
    trace_seconds: float | None = None
    trace_seconds_all: list = field(default_factory=list)
    trace_seconds_min: float | None = None
    trace_seconds_max: float | None = None
    trace_cv: float | None = None
    clock: str | None = None
    trace_slices: int | None = None
    slice_budget: int | None = None
    trace_packet: int | None = None
    trace_refill: int | None = None
    trace_order: str | None = None
    trace_order_probe: dict | None = None
    rays_per_second: float | None = None
    fps: float | None = None
    embree_trace_seconds: float | None = None
    embree_rays_per_second: float | None = None
    iterations_per_ray: float | None = None
    candidate_tests_per_ray: float | None = None
    linespace_lookups_per_ray: float | None = None
    simd_efficiency_steps_w32: float | None = None
    simd_efficiency_tests_w32: float | None = None
    simd_width_device: int | None = None
    simd_width_source: str | None = None
    simd_efficiency_steps_device: float | None = None
    simd_efficiency_tests_device: float | None = None
    work_counters_error: str | None = None
    predicted: dict | None = None  # an "auto" case: the model's prediction of the chosen setting
    heatmaps: dict = field(default_factory=dict)
    image_delta_e_mean: float | None = None  # lsbench/oracle/image.py
    image_delta_e_max: float | None = None
    image_jnd_pixels: int | None = None
    image_files: dict = field(default_factory=dict)
    work_clock: dict | None = None
    wall_seconds: float | None = None
    schema_version: int = SCHEMA_VERSION

    def update(self, **values) -> None:
        """Set fields by name; a name the record does not define is an error, not a new key."""
        for name, value in values.items():
            if name not in _OWN_FIELDS:
                raise AttributeError(f"Record has no field {name!r} (lsbench/results/record.py)")
            setattr(self, name, value)

    def to_dict(self) -> dict:
        """The record as stored: every column present (None where not measured), so each line
        of results.jsonl has the same fields and pandas gives each column one type."""
        out = {}
        for name in _OWN_FIELDS:
            if name in FLATTENED:
                group = getattr(self, name)
                for column in FLATTENED[name]:
                    out[column] = None if group is None else getattr(group, column)
            else:
                value = getattr(self, name)
                out[name] = dict(value) if isinstance(value, dict) else value
        return out


_OWN_FIELDS = tuple(f.name for f in dataclasses.fields(Record))
# Groups whose fields are record columns: Accuracy's (ray_count is already the record's own, the
# same number) and the classifier's.
FLATTENED = {group: tuple(f.name for f in dataclasses.fields(cls) if f.name not in _OWN_FIELDS)
             for group, cls in (("accuracy", Accuracy), ("classification", Classification))}


def field_names() -> tuple[str, ...]:
    """Every column of a stored record, in order (what docs/record.md documents)."""
    names: list[str] = []
    for name in _OWN_FIELDS:
        names.extend(FLATTENED.get(name, (name,)))
    return tuple(names)


# Fields a line of results.jsonl must have to be read at all (store.read_records skips others).
REQUIRED_FIELDS = ("key", "status")

# RunSettings that do not change what an ok case measures, so they are not part of a record's
# `settings`: the case's own fields carry what ran (image size, ray set), the gate's thresholds
# (min_agreement, max_unexplained) are verdicts applied when judging, timeout and memory budget
# only decide whether a case fails (the device-memory budget_mib is a result setting where it is set:
# "auto" cases choose under it)
# (failed cases are retried), and a record with heatmaps serves a run without them (one without
# is redone when they are wanted). Any other setting, including one added later, counts as
# changing results.
NOT_RESULT_SETTINGS = frozenset({"width", "height", "gpu_width", "gpu_height", "rays", "ray_params",
                                 "min_agreement", "max_unexplained", "timeout_seconds", "memory_budget_mb", "heatmaps"})


def result_settings(settings) -> dict:
    """The run settings (lsbench.inputs.scenario.RunSettings) that change a case's results, as
    a stored record holds them (through JSON: a tuple setting compares as the list it is read as)."""
    chosen = {k: v for k, v in dataclasses.asdict(settings).items() if k not in NOT_RESULT_SETTINGS}
    if chosen.get("budget_mib") is None:  # no device-memory budget: records of runs before it stand
        chosen.pop("budget_mib", None)
    return json.loads(json.dumps(chosen, default=str))


# Environment fields that must be equal for a record to be reused, in the order reasons are told.
ENVIRONMENT_FIELDS = ("commit", "dirty", "diff_hash", "versions", "planted_defect", "device", "driver",
                      "backend_version")
_WHAT_CHANGED = {"scene_hash": "scene changed", "rays_hash": "rays changed", "commit": "code changed",
                 "dirty": "code changed", "diff_hash": "uncommitted changes differ",
                 "versions": "package versions changed", "planted_defect": "planted defect changed",
                 "device": "device changed",
                 "driver": "driver changed", "backend_version": "backend version changed"}


def reuse_mismatch(old: dict, expected: dict, heatmaps_wanted: bool, keep_failed: bool) -> str | None:
    """Why the stored record `old` cannot stand for the case now (a few words, for the log), or
    None when it can. `expected` holds what this run would record: scene_hash, rays_hash, the
    ENVIRONMENT_FIELDS and settings (runner.plan_cases)."""
    if old.get("schema_version") != SCHEMA_VERSION:
        return f"record format {old.get('schema_version', 1)} is not {SCHEMA_VERSION}"
    if old.get("status") != "ok" and not keep_failed:
        return "failed earlier"
    for name in ("scene_hash", "rays_hash", *ENVIRONMENT_FIELDS):
        if old.get(name) != expected.get(name):
            return _WHAT_CHANGED[name]
    if old.get("settings") != expected.get("settings"):
        old_s, new_s = old.get("settings") or {}, expected.get("settings") or {}
        changed = sorted(k for k in old_s.keys() | new_s.keys() if old_s.get(k) != new_s.get(k))
        return "settings changed (" + ", ".join(changed) + ")"
    if heatmaps_wanted and old.get("status") == "ok" and not old.get("heatmaps"):
        return "heatmaps wanted"
    return None
