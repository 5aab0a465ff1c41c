"""The result record: defined once (lsbench/results/record.py), documented field by field
(docs/record.md), read by pandas in one line with stable types; the store that alone reads and
writes run folders (durable appends, skipped bad lines, compaction, atomic --fresh, the lock);
case identity (Case.key)."""
from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import pytest

from lsbench.inputs.scenario import Case, RunSettings, load_scenario
from lsbench.oracle.verify import Accuracy
from lsbench.results import record as record_module
from lsbench.results import store

REPO = Path(__file__).resolve().parents[1]
SETTINGS = RunSettings(width=16, height=12, repeats=2, embree_timing=False)


@pytest.fixture(scope="module")
def real_records():
    """An ok record (cornell, grid 4^3 on OpenCL) and a failed one, as the runner makes them."""
    from lsbench.inputs.rays import make_rays
    from lsbench.inputs.scenes import load_scene
    from lsbench.running.environment import record_env
    from lsbench.running.execute import case_inputs, execute, failed_record

    env = record_env()
    ok_case = Case("cornell", "grid", "opencl", "4", width=16, height=12)
    ok = execute(ok_case, SETTINGS, env)
    bad_case = Case("cornell", "svo", "opencl", "4x4x2", width=16, height=12)
    scene = load_scene("cornell")
    inputs = case_inputs(scene, make_rays("primary", scene, 16, 12))
    failed = failed_record(bad_case, SETTINGS, "worker crashed (signal SIGKILL) before reporting", env, inputs)
    return ok, failed


def documented_fields() -> list[str]:
    text = (REPO / "docs" / "record.md").read_text()
    return re.findall(r"^\| `([a-z0-9_]+)` \|", text, flags=re.M)


def test_docs_document_every_field_once():
    names = record_module.field_names()
    documented = documented_fields()
    assert len(documented) == len(set(documented)), "a field documented twice"
    assert set(names) - set(documented) == set(), "fields missing from docs/record.md"
    assert set(documented) - set(names) == set(), "docs/record.md documents fields the record lacks"
    # Accuracy's fields are columns without being listed again (ray_count is the record's own)
    assert {f.name for f in dataclasses.fields(Accuracy)} <= set(names)


def test_record_has_every_field_and_the_numbers(real_records):
    ok, failed = real_records
    for rec in (ok, failed):
        assert list(rec) == list(record_module.field_names())
        assert rec["schema_version"] == record_module.SCHEMA_VERSION
    assert ok["status"] == "ok" and ok["agreement"] == 1.0 and ok["ray_count"] == 16 * 12
    assert (ok["resolution"], ok["resolution_x"], ok["resolution_y"], ok["resolution_z"]) == ("4", 4, 4, 4)
    assert (failed["resolution"], failed["resolution_x"], failed["resolution_y"], failed["resolution_z"]) \
        == ("4x4x2", 4, 4, 2)
    # the work-counter trace: a 4^3 grid over the box visits at least one cell per ray and every
    # hit ray tests at least one triangle
    assert ok["iterations_per_ray"] >= 1.0 and ok["candidate_tests_per_ray"] > 0
    assert ok["linespace_lookups_per_ray"] == 0.0 and ok["work_counters_error"] == ""
    assert ok["settings"] == {"repeats": 2, "warmup": 1, "rel_tol": 1e-4, "embree_timing": False}
    assert failed["agreement"] is None and failed["scene_hash"] == ok["scene_hash"]


def test_record_rejects_undefined_fields():
    rec = record_module.Record("k", "s", "builtin:s", "grid", "glsl", "4", 4, 4, 4, 0, 0, "primary", 4, 4)
    with pytest.raises(AttributeError, match="no field 'agreemnt'"):
        rec.update(agreemnt=1.0)


def test_pandas_reads_a_run_with_stable_types(tmp_path, real_records):
    import pandas  # the `test` extra installs it
    ok, failed = real_records
    for rec in (ok, failed):
        store.append_record(tmp_path, rec)
    df = pandas.read_json(tmp_path / "results.jsonl", lines=True, dtype=False)
    only_ok = pandas.read_json(tmp_path / "results.jsonl", lines=True, dtype=False, nrows=1)
    assert list(df.columns) == list(record_module.field_names()) and len(df) == 2
    assert list(df["resolution"]) == ["4", "4x4x2"]  # as given: strings, never ints
    for column in ("resolution_x", "resolution_y", "resolution_z", "ls_n", "triangles", "ray_count",
                   "width", "schema_version"):
        assert df[column].dtype == "int64", column
        assert only_ok[column].dtype == "int64", column
    for column in ("agreement", "trace_seconds", "iterations_per_ray", "candidate_tests_per_ray"):
        assert df[column].dtype == "float64", column
    assert df["agreement"].isna().tolist() == [False, True]
    assert df.loc[0, "buffers"] == ok["buffers"] and df.loc[0, "settings"] == ok["settings"]  # dicts stay dicts


def test_read_records_skips_lines_that_are_no_record(tmp_path):
    path = tmp_path / "results.jsonl"
    path.write_text('{"key": "a", "status": "ok"}\nnull\n[1, 2]\n{"status": "ok"}\n{"key": "a", "status": "failed"}\n'
                    '{"key": "b", "status": "ok"}\n{"key": "c", "sta')
    with pytest.warns(UserWarning) as caught:
        recs = store.read_records(path)
    assert [(r["key"], r["status"]) for r in recs] == [("a", "failed"), ("b", "ok")]  # later one wins
    messages = [str(w.message) for w in caught]
    assert any("line 2 is not a record (a JSON NoneType)" in m for m in messages)
    assert any("line 3 is not a record (a JSON list)" in m for m in messages)
    assert any("line 4 lacks key" in m for m in messages)
    assert any("truncated last line" in m for m in messages)
    store.compact(path)  # one line per case, nothing else
    assert [json.loads(line)["key"] for line in path.read_text().splitlines()] == ["a", "b"]


def test_fresh_results_supersede_only_when_complete(tmp_path):
    for key in ("x", "y"):
        store.append_record(tmp_path, {"key": key, "status": "ok", "round": 1})
    before = (tmp_path / "results.jsonl").read_bytes()
    interrupted = store.RunResults(tmp_path, fresh=True)
    assert interrupted.earlier == {}
    interrupted.append({"key": "x", "status": "ok", "round": 2})
    message = interrupted.finish(complete=False)
    assert "unchanged" in message and "1 finished cases" in message
    assert (tmp_path / "results.jsonl").read_bytes() == before
    done = store.RunResults(tmp_path, fresh=True)  # starts the side file anew
    done.append({"key": "x", "status": "ok", "round": 3})
    assert "1 earlier ones" in done.finish(complete=True)
    recs = store.read_records(tmp_path / "results.jsonl")
    assert sorted((r["key"], r["round"]) for r in recs) == [("x", 3), ("y", 1)]  # y: not in this run
    assert not (tmp_path / store.FRESH_RESULTS).exists()


def test_lock_is_exclusive_and_names_its_holder(tmp_path):
    with store.RunLock(tmp_path, "lsbench run first.toml"):
        with pytest.raises(store.ResultsError, match=r"in use by another run \(pid \d+ on .*lsbench run first.toml"):
            with store.RunLock(tmp_path, "lsbench run second.toml"):
                pass
    with store.RunLock(tmp_path, "lsbench run third.toml"):  # free again
        pass


def test_check_writable_before_any_case(tmp_path):
    (tmp_path / "results.jsonl").mkdir()
    with pytest.raises(store.ResultsError, match="results.jsonl: not a file"):
        store.check_writable(tmp_path, fresh=False)


def test_case_key_names_the_file_and_the_parameters_built(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    a, b = (Case(f"{d}/box.ply", "grid", "glsl", "8") for d in ("a", "b"))
    assert a.key != b.key and a.key.startswith("a/box.ply|")
    outside = Case("/elsewhere/box.ply", "grid", "glsl", "8")
    assert outside.key.startswith("/elsewhere/box.ply|")
    assert Case("cornell", "grid", "glsl", "8").key == Case("cornell", "grid", "glsl", "8x8x8").key
    assert Case("cornell", "svo-ls", "glsl", "8", ls_n=0).key.endswith("|n1|k0")  # N = 0 builds N = 1
    assert Case("cornell", "grid", "glsl", "8", ls_n=3, ls_min_candidates=4).key.endswith("|n0|k0")
    cam = ((1100.0, 180.0, -40.0), (0.1, 0.0, 0.0), (0.0, 1.0, 0.0), 65.0)
    assert "@cam(1100,180,-40,0.1,0,0,0,1,0,65)|" in Case("cornell", "grid", "glsl", "8", camera=cam).key
    nudged = (cam[0], (0.1000001, 0.0, 0.0), *cam[2:])
    assert Case("cornell", "grid", "glsl", "8", camera=nudged).key != Case("cornell", "grid", "glsl", "8", camera=cam).key
    scen = tmp_path / "s.toml"
    scen.write_text('[[cases]]\nscenes = ["cornell"]\nstructures = ["svo-ls"]\nbackends = ["glsl"]\n'
                    'resolutions = [8, "8x8x8"]\nls_n = [0, 1]\n')
    assert [c.key for c in load_scenario(scen).cases] == ["cornell|primary@64x64|svo-ls|glsl|r8|n1|k0"]


def test_reuse_needs_identity_environment_and_ok():
    expected = {"scene_hash": "s", "rays_hash": "r", "commit": "c", "dirty": False, "diff_hash": None,
                "versions": {"numpy": "2"}, "planted_defect": None, "device": "d", "driver": "v",
                "backend_version": "b", "settings": {"repeats": 5}}
    old = dict(expected, key="k", status="ok", schema_version=record_module.SCHEMA_VERSION, heatmaps={})
    assert record_module.reuse_mismatch(old, expected, False, False) is None
    cases = [({"scene_hash": "t"}, "scene changed"), ({"rays_hash": "t"}, "rays changed"),
             ({"commit": "x"}, "code changed"), ({"diff_hash": "x"}, "uncommitted changes differ"),
             ({"device": "x"}, "device changed"), ({"planted_defect": "drop-reference"}, "planted defect changed"),
             ({"settings": {"repeats": 3}}, "settings changed (repeats)"), ({"status": "failed"}, "failed earlier"),
             ({"schema_version": None}, "record format")]
    for change, why in cases:
        assert why in record_module.reuse_mismatch(dict(old, **change), expected, False, False), change
    assert record_module.reuse_mismatch(dict(old, status="failed"), expected, False, True) is None
    assert record_module.reuse_mismatch(old, expected, True, False) == "heatmaps wanted"
