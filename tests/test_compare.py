"""Regression comparison on hand-written run directories (no GPU), and compare-commits on a
throw-away git repository whose fake `python -m lsbench run` writes records."""
from __future__ import annotations

import json
import re
import math
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from lsbench import cli, paths
from lsbench.compare import commits, stats
from lsbench.compare import verdicts as compare
from lsbench.results import store

GL_DEV = "llvmpipe (LLVM 15.0.6, 256 bits)"


def record(key, trace=0.010, noise=0.01, repeats=5, agreement=1.0, status="ok", memory=1 << 20,
           device=GL_DEV, seed=0, ray_count=10000, scene_hash="5ce7e0", rays_hash="4a75"):
    rng = np.random.default_rng(seed)
    rec = {"key": key, "scene": "quad", "structure": key.split("|")[0], "backend": "glsl",
           "resolution": "64", "ls_n": 0, "rays": "primary", "ray_count": ray_count,
           "status": status, "reason": "" if status == "ok" else "worker timed out after 900 s",
           "device": device, "driver": "Mesa 22.3.6"}
    if status == "ok":
        times = [trace * (1 + noise * rng.standard_normal()) for _ in range(repeats)]
        med = float(np.median(times))
        rec.update(agreement=agreement, trace_seconds=med, trace_seconds_all=times,
                   trace_seconds_min=min(times), trace_seconds_max=max(times),
                   rays_per_second=ray_count / med, fps=1 / med, memory_bytes=memory,
                   scene_hash=scene_hash, rays_hash=rays_hash)  # a failed record has none
    else:
        rec.update(agreement=None, trace_seconds=None, trace_seconds_all=[],
                   rays_per_second=None, memory_bytes=None)
    return rec


def write(run_dir: Path, records, device=GL_DEV, commit="a" * 40):
    store.write_run_info(run_dir, {"commit": commit, "dirty": False, "date": "2026-01-01T00:00:00",
                                   "devices": {"glsl": {"device": device, "driver": "Mesa 22.3.6"}}})
    for r in records:
        store.append_record(run_dir, r)
    return run_dir


KEYS = ["grid|64", "svo|64", "esvo|64"]


def base_run(tmp_path, seed=0):
    return write(tmp_path / "base", [record(k, seed=seed + i) for i, k in enumerate(KEYS)])


# ---------------------------------------------------------------- the U test

def test_mann_whitney_exact_and_normal():
    x, y = [1, 2, 3, 4, 5], [6, 7, 8, 9, 10]
    u, p = stats.mann_whitney_less(x, y)
    assert u == 0 and p == pytest.approx(1 / math.comb(10, 5))
    u, p = stats.mann_whitney_less(y, x)
    assert u == 25 and p == pytest.approx(1.0)
    # one overlapping pair: 2 orderings out of 252 are at least as extreme
    u, p = stats.mann_whitney_less([1, 2, 3, 4, 6.5], [6, 7, 8, 9, 10])
    assert u == 1 and p == pytest.approx(2 / 252)
    # counts of the exact distribution add up to C(m+n, m) and are symmetric
    c = stats._u_counts(4, 6)
    assert sum(c) == math.comb(10, 4) and c == c[::-1]
    # ties: normal approximation, still says clearly apart samples differ
    u, p = stats.mann_whitney_less([1, 1, 2, 2, 3] * 4, [5, 5, 6, 6, 7] * 4)
    assert u == 0 and p < 1e-6
    _, p = stats.mann_whitney_less([1, 2, 3], [1, 2, 3])
    assert p > 0.3


# ---------------------------------------------------------------- compare_runs

def test_planted_slowdown_is_a_regression(tmp_path):
    base = base_run(tmp_path)
    head = write(tmp_path / "head", [record("grid|64", trace=0.013, seed=10),  # 30% slower
                                     record("svo|64", seed=11), record("esvo|64", seed=12)])
    res = compare.compare_runs(base, head)
    assert res.verdicts_given and not res.warnings
    by = {c.key: c for c in res.cases}
    grid = by["grid|64"]
    assert grid.verdicts == ["speed"] and grid.ranges_disjoint
    assert grid.speed_ratio == pytest.approx(1 / 1.3, rel=0.03)
    assert not by["svo|64"].regression and not by["esvo|64"].regression
    assert res.exit_code == 1
    text = res.to_text()
    assert "REGRESSION speed" in text and "1 regressions" in text


def test_noise_within_factor_passes(tmp_path):
    base = base_run(tmp_path)
    # 4% slower on average plus noise: under the 1.1 factor
    head = write(tmp_path / "head", [record(k, trace=0.0104, noise=0.03, seed=20 + i)
                                     for i, k in enumerate(KEYS)])
    res = compare.compare_runs(base, head)
    assert not res.has_regression and res.exit_code == 0
    assert all(c.speed_ratio > 1 / 1.1 for c in res.cases)


def test_slowdown_inside_the_noise_is_not_a_regression(tmp_path):
    # median 15% slower but repeats spread over a factor 2: the U test cannot tell
    base = write(tmp_path / "base", [dict(record("grid|64"), trace_seconds_all=[0.006, 0.008, 0.010, 0.012, 0.016],
                                          trace_seconds=0.010, rays_per_second=1e6)])
    head = write(tmp_path / "head", [dict(record("grid|64"), trace_seconds_all=[0.007, 0.009, 0.0115, 0.013, 0.015],
                                          trace_seconds=0.0115, rays_per_second=1e4 / 0.0115)])
    res = compare.compare_runs(base, head)
    c = res.cases[0]
    assert c.speed_ratio < 1 / 1.1 and not c.ranges_disjoint and c.p_value > 0.05
    assert not c.regression and "within noise" in " ".join(c.notes)


def test_accuracy_drop_failure_and_memory_are_regressions(tmp_path):
    base = base_run(tmp_path)
    head = write(tmp_path / "head", [
        record("grid|64", agreement=1 - 1 / 10000, seed=30),   # one ray more disagrees
        record("svo|64", status="failed"),
        record("esvo|64", memory=int(1.25 * (1 << 20)), seed=32),
    ])
    res = compare.compare_runs(base, head)
    by = {c.key: c for c in res.cases}
    assert by["grid|64"].verdicts == ["accuracy"]
    assert by["grid|64"].agreement_delta == pytest.approx(-1e-4)
    assert by["svo|64"].verdicts == ["failure"] and by["svo|64"].status == "ok->failed"
    assert "timed out" in " ".join(by["svo|64"].notes)
    assert by["esvo|64"].verdicts == ["memory"] and by["esvo|64"].bytes_ratio == pytest.approx(1.25)
    assert res.exit_code == 1


def test_improvements_and_added_cases_are_not_regressions(tmp_path):
    base = write(tmp_path / "base", [record("grid|64", agreement=0.99), record("svo|64", status="failed"),
                                     record("old|64")])
    head = write(tmp_path / "head", [record("grid|64", trace=0.005, agreement=1.0, seed=5),
                                     record("svo|64", seed=6), record("new|64", seed=7)])
    res = compare.compare_runs(base, head, only_common=True)
    assert not res.has_regression and res.exit_code == 0
    by = {c.key: c for c in res.cases}
    assert "faster" in by["grid|64"].notes and "fixed (failed in base)" in by["svo|64"].notes
    assert res.only_base == ["old|64"] and res.only_head == ["new|64"]


def test_different_devices_warn_and_give_no_verdict(tmp_path):
    base = base_run(tmp_path)
    head = write(tmp_path / "head", [record("grid|64", trace=0.02, device="NVIDIA H100", seed=40),
                                     record("svo|64", device="NVIDIA H100", seed=41),
                                     record("esvo|64", device="NVIDIA H100", seed=42)],
                 device="NVIDIA H100")
    res = compare.compare_runs(base, head)
    assert not res.verdicts_given and res.exit_code == 0
    assert any("different devices" in w for w in res.warnings)
    grid = next(c for c in res.cases if c.key == "grid|64")
    assert grid.verdicts == [] and "would be: speed" in " ".join(grid.notes)
    text = res.to_text()
    assert "WARNING: different devices" in text and "no verdict" in text


def test_truncated_head_is_read(tmp_path):
    base = base_run(tmp_path)
    head = write(tmp_path / "head", [record(k, seed=50 + i) for i, k in enumerate(KEYS[:2])])
    with open(head / "results.jsonl", "a") as f:
        f.write(json.dumps(record("esvo|64"))[:40])
    with pytest.warns(UserWarning, match="truncated"):
        res = compare.compare_runs(base, head)
    assert res.only_base == ["esvo|64"] and not res.has_regression
    assert res.exit_code == 1  # the case lost with the truncated line is missing from head


def test_cli_compare_exit_code_and_html(tmp_path, capsys):
    base = base_run(tmp_path)
    head = write(tmp_path / "head", [record("grid|64", trace=0.013, seed=60),
                                     record("svo|64", seed=61), record("esvo|64", seed=62)])
    assert cli.main(["compare", str(base), str(head), "--report"]) == 1
    out = capsys.readouterr().out
    assert "REGRESSION speed" in out and "compare.html" in out
    page = (head / "compare.html").read_text()
    assert "class='reg'" in page and "grid|64" in page
    assert cli.main(["compare", str(base), str(head), "--factor", "1.5"]) == 0


# ---------------------------------------------------------------- a comparison that can't lie

def test_nothing_in_common_fails(tmp_path, capsys):
    base = base_run(tmp_path)
    head = write(tmp_path / "head", [record("grid|128", seed=70), record("svo|128", seed=71)])
    res = compare.compare_runs(base, head, only_common=True)
    assert not res.has_regression and res.exit_code == 1
    assert res.problems[0].startswith("nothing matched: no case key is in both runs (base has 3 cases, head 2)")
    assert cli.main(["compare", str(base), str(head), "--only-common"]) == 1
    out = capsys.readouterr().out
    assert "0 cases compared, 0 regressions" in out and "compare failed: nothing matched" in out
    empty = tmp_path / "empty"
    empty.mkdir()
    assert compare.compare_runs(empty, empty).exit_code == 1  # two empty runs match nothing either


def test_head_lacking_base_cases_fails_unless_only_common(tmp_path, capsys):
    base = base_run(tmp_path)
    head = write(tmp_path / "head", [record("grid|64", seed=80)])
    res = compare.compare_runs(base, head)
    assert not res.has_regression and res.only_base == ["svo|64", "esvo|64"]
    assert res.exit_code == 1
    assert res.problems == ["head lacks 2 of base's cases (first: svo|64); --only-common compares "
                            "the common ones only"]
    assert cli.main(["compare", str(base), str(head)]) == 1
    out = capsys.readouterr().out
    assert "compare failed: head lacks 2 of base's cases" in out and out.count("MISSING") == 2
    assert cli.main(["compare", str(base), str(head), "--only-common"]) == 0
    # cases new in head that ran are fine
    head2 = write(tmp_path / "head2", [record(k, seed=90 + i) for i, k in enumerate(KEYS + ["bvh|64"])])
    assert compare.compare_runs(base, head2).exit_code == 0


def test_case_new_in_head_that_failed_is_a_failure(tmp_path, capsys):
    base = base_run(tmp_path)
    head = write(tmp_path / "head", [record(k, seed=100 + i) for i, k in enumerate(KEYS)]
                 + [record("grid-ls|64", status="failed")])
    res = compare.compare_runs(base, head)
    new = next(c for c in res.cases if c.key == "grid-ls|64")
    assert new.verdicts == ["failure"] and new.status == "none->failed"
    assert "new and failed: worker timed out" in "; ".join(new.notes)
    assert res.exit_code == 1 and res.problems == ["1 regressions"]
    assert cli.main(["compare", str(base), str(head)]) == 1
    assert "REGRESSION failure" in capsys.readouterr().out


@pytest.mark.parametrize("changed, what", [({"scene_hash": "0dd5ce"}, "scene differs (scene_hash 5ce7e0 in base, 0dd5ce in head)"),
                                           ({"rays_hash": "0dd4a7"}, "ray set differs (rays_hash 4a75 in base, 0dd4a7 in head)")])
def test_same_key_on_different_inputs_is_refused(tmp_path, capsys, changed, what):
    base = base_run(tmp_path)
    # identical figures: only the inputs differ, so nothing but the refusal can fail this
    same = [record(k, seed=i) for i, k in enumerate(KEYS)]
    head = write(tmp_path / "head", [dict(same[0], **changed)] + same[1:])
    res = compare.compare_runs(base, head)
    grid = next(c for c in res.cases if c.key == "grid|64")
    assert grid.refused == what and not grid.comparable and grid.speed_ratio is None
    assert [c.key for c in res.refused] == ["grid|64"] and not res.has_regression
    assert res.exit_code == 1 and res.problems == ["1 cases refused: same key, different inputs"]
    assert cli.main(["compare", str(base), str(head), "--report"]) == 1
    out = capsys.readouterr().out
    assert "REFUSED" in out and what in out and "2 cases compared, 0 regressions, 1 refused" in out
    assert what in (head / "compare.html").read_text()
    # a failed record carries no hashes: that alone is no refusal
    head_failed = write(tmp_path / "head-failed", [record("grid|64", status="failed")] + same[1:])
    assert not compare.compare_runs(base, head_failed).refused


# ---------------------------------------------------------------- compare-commits

FAKE_CLI = '''
"""Fake `python -m lsbench`: `run SCENARIO --out DIR` writes one record whose speed is SPEED."""
import json, os, sys
from pathlib import Path
from lsbench.speed import SPEED
args = sys.argv[1:]
assert args[0] == "run" and args[2] == "--out", args
out = Path(args[3]); out.mkdir(parents=True, exist_ok=True)
scenario = Path(args[1]).read_text()
times = [0.01 / SPEED * (1 + 0.001 * i) for i in range(5)]
rec = {"key": "grid|64", "status": "ok", "backend": "glsl", "device": "fake", "ray_count": 1000,
       "trace_seconds": times[2], "trace_seconds_all": times, "rays_per_second": 1000 / times[2],
       "agreement": 1.0, "memory_bytes": 100, "scenario_text": scenario,
       "scenes": os.environ.get("LSBENCH_SCENES"),
       "code_dir": os.path.dirname(os.path.dirname(os.path.abspath(__file__)))}
(out / "run.json").write_text(json.dumps({"commit": "x", "devices": {"glsl": {"device": "fake"}}}))
(out / "results.jsonl").write_text(json.dumps(rec) + "\\n")
'''


def _git(repo, *args):
    return subprocess.run(["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t",
                           *args], check=True, capture_output=True, text=True).stdout.strip()


@pytest.mark.skipif(subprocess.run(["git", "--version"], capture_output=True).returncode != 0,
                    reason="git not installed")
def fake_repo(tmp_path):
    """A git repository whose fake lsbench runs 30 % slower at HEAD than at HEAD~1: (repo, scenario)."""
    repo = tmp_path / "repo"
    (repo / "lsbench").mkdir(parents=True)
    _git(tmp_path, "init", "-q", str(repo))
    (repo / "lsbench" / "__init__.py").write_text("")
    (repo / "lsbench" / "__main__.py").write_text(textwrap.dedent(FAKE_CLI))
    (repo / "lsbench" / "speed.py").write_text("SPEED = 1.0\n")
    _git(repo, "add", "-A")
    _git(repo, "commit", "-q", "-m", "fast")
    (repo / "lsbench" / "speed.py").write_text("SPEED = 0.7\n")  # 30 % fewer rays/s
    _git(repo, "commit", "-q", "-am", "slow")
    # uncommitted change in the main work tree must not leak into either revision
    (repo / "lsbench" / "speed.py").write_text("SPEED = 100.0\n")
    scenario = tmp_path / "s.toml"
    scenario.write_text('name = "tiny"\n')
    return repo, scenario


@pytest.mark.skipif(subprocess.run(["git", "--version"], capture_output=True).returncode != 0,
                    reason="git not installed")
def test_compare_commits_runs_each_revision_in_its_own_worktree(tmp_path, monkeypatch):
    repo, scenario = fake_repo(tmp_path)

    # $SCENES is the calling checkout's scenes folder, also when LSBENCH_SCENES is not exported
    monkeypatch.delenv("LSBENCH_SCENES", raising=False)
    res = commits.compare_commits("HEAD~1", "HEAD", scenario, out_dir=tmp_path / "cmp",
                                  repo_dir=repo, stream=sys.stderr)
    c = res.cases[0]
    assert c.verdicts == ["speed"] and c.speed_ratio == pytest.approx(0.7)
    assert res.exit_code == 1
    dirs = sorted(p.name for p in (tmp_path / "cmp").iterdir())
    assert len(dirs) == 2 and dirs[0].startswith("a-HEAD_1-") and dirs[1].startswith("b-HEAD-")
    _, recs = store.read_run(tmp_path / "cmp" / dirs[0])
    assert recs[0]["scenario_text"] == 'name = "tiny"\n'
    assert not recs[0]["code_dir"].startswith(str(repo))  # ran the worktree's code
    for d in dirs:
        assert store.read_run(tmp_path / "cmp" / d)[1][0]["scenes"] == str(paths.scenes_dir().resolve())
    # worktrees are gone
    assert _git(repo, "worktree", "list").count("\n") == 0
    assert not Path(recs[0]["code_dir"]).exists()

    with pytest.raises(ValueError, match="unknown revision"):
        commits.compare_commits("nope", "HEAD", scenario, repo_dir=repo, out_dir=tmp_path / "x")


# ---------------------------------------------------------------- stated power

def _same_slowdown_run(path, keys, trace, repeats, seed0):
    return write(path, [record(k, trace=trace, repeats=repeats, seed=seed0 + i) for i, k in enumerate(keys)])


def test_compare_states_its_power_and_a_run_wide_false_alarm_rate(tmp_path, capsys):
    # the CI scenario's shape: 60 cases, 3 repeats, a uniform 30 % slowdown
    keys = [f"case{i}|32" for i in range(60)]
    base = _same_slowdown_run(tmp_path / "base3", keys, 0.010, 3, 0)
    head = _same_slowdown_run(tmp_path / "head3", keys, 0.013, 3, 100)
    res = compare.compare_runs(base, head)
    # 3 against 3 repeats: the smallest p is 1/20, above Holm's first level 0.05/60, so no speed
    # verdict can fire, and the output says so instead of calling the run clean by omission
    assert not any("speed" in c.verdicts for c in res.cases)
    assert all(c.p_value == pytest.approx(0.05) and c.holm_level for c in res.cases)
    assert cli.main(["compare", str(base), str(head)]) == 0
    out = capsys.readouterr().out
    assert "false alarms: at most 0.05 per run (family-wise, Holm over the 60 cases" in out
    assert ("3 vs 3 repeats per case: smallest possible p 0.05, Holm's strictest level 0.05/60 = "
            "0.000833: NO speed regression can be flagged; 7 repeats per side are needed") in out
    # every compared row carries the interval of its ratio: 3 v 3 = the 9 pairwise ratios, 90 %
    rows = [line for line in out.splitlines() if line.startswith("case")][1:]
    assert len(rows) == 60 and all(re.search(r"0\.\d{3}-0\.\d{3} \(90%\)", r) for r in rows)
    c = res.cases[0]
    lo, hi = c.ratio_ci[1:3]
    sb, sh = c.samples
    assert lo == pytest.approx((sh / sb[:, None]).min()) and hi == pytest.approx((sh / sb[:, None]).max())
    assert lo <= c.speed_ratio <= hi

    # 8 repeats over the same 60 cases: Holm's first level is reachable, the slowdown is found in
    # every case, and the smallest detectable change is printed for the repeats given
    base = _same_slowdown_run(tmp_path / "base8", keys, 0.010, 8, 0)
    head = _same_slowdown_run(tmp_path / "head8", keys, 0.013, 8, 100)
    res = compare.compare_runs(base, head)
    assert all(c.verdicts == ["speed"] for c in res.cases)
    text = res.to_text()
    assert "8 vs 8 repeats per case: smallest possible p 7.77e-05" in text and "can be flagged" in text
    assert "smallest detectable change (mdc" in text
    # 1 % noise, 8 v 8: a few per cent is detectable; the factor 1.1 then decides
    assert all(0.9 < c.detectable < 1.0 for c in res.cases)


def test_holm_corrects_across_cases(tmp_path):
    # 10 cases, 5 v 5 repeats: Holm's levels are 0.05/10, 0.05/9, ...
    keys = [f"case{i}|32" for i in range(10)]
    base_recs = [dict(record(k), trace_seconds_all=[0.0100, 0.0101, 0.0102, 0.0103, 0.0104]) for k in keys]
    head_recs = [dict(record(k), trace_seconds_all=[0.0100, 0.0101, 0.0102, 0.0103, 0.0104]) for k in keys]
    # case0: all five repeats slower than all of base (p = 1/252); case1: one pair overlaps (2/252)
    head_recs[0].update(trace_seconds_all=[0.0130, 0.0131, 0.0132, 0.0133, 0.0134], trace_seconds=0.0132,
                        rays_per_second=1e4 / 0.0132)
    head_recs[1].update(trace_seconds_all=[0.01035, 0.0131, 0.0132, 0.0133, 0.0134], trace_seconds=0.0132,
                        rays_per_second=1e4 / 0.0132)
    res = compare.compare_runs(write(tmp_path / "base", base_recs), write(tmp_path / "head", head_recs))
    by = {c.key: c for c in res.cases}
    assert by["case0|32"].p_value == pytest.approx(1 / 252) and by["case0|32"].verdicts == ["speed"]
    # at 0.05 per case it would be flagged too; after Holm (0.0079 > 0.05/9) it is not
    c1 = by["case1|32"]
    assert c1.p_value == pytest.approx(2 / 252) and c1.p_value < 0.05 and c1.verdicts == []
    assert "within noise (p 0.00794 > Holm level 0.00556)" in " ".join(c1.notes)


def test_runs_of_one_commit_give_one_sample_per_process(tmp_path, capsys):
    # the repeats inside one process agree closely, the processes do not: three runs per side
    def run(name, trace, seed):
        return write(tmp_path / name, [record("grid|64", trace=trace, noise=0.001, seed=seed)])
    bases = [run(f"b{i}", t, i) for i, t in enumerate((0.010, 0.012, 0.009))]
    heads = [run(f"h{i}", t, 10 + i) for i, t in enumerate((0.011, 0.0095, 0.0125))]
    pooled = compare.compare_runs(bases[0], heads[0])  # one process each: 5 v 5 repeats
    assert pooled.cases[0].units == "repeats" and pooled.cases[0].n_base == 5
    assert pooled.cases[0].p_value < 0.01  # the repeats of one process claim a difference
    res = compare.compare_runs(bases, heads)
    c = res.cases[0]
    assert c.units == "processes" and (c.n_base, c.n_head) == (3, 3)
    assert c.p_value > 0.3 and not c.regression
    medians = [float(np.median(1e4 / np.asarray(store.read_run(d)[1][0]["trace_seconds_all"]))) for d in heads]
    assert sorted(c.samples[1]) == pytest.approx(sorted(medians))
    assert cli.main(["compare", str(bases[0]), str(heads[0]), "--base-also", str(bases[1]),
                     "--base-also", str(bases[2]), "--head-also", str(heads[1]), "--head-also",
                     str(heads[2])]) == 0
    out = capsys.readouterr().out
    assert "3 vs 3 processes per case" in out and "3v3p" in out and "(+2 more runs)" in out


def test_compare_commits_repeats_across_processes(tmp_path, capsys, monkeypatch):
    repo, scenario = fake_repo(tmp_path)
    res = commits.compare_commits("HEAD~1", "HEAD", scenario, out_dir=tmp_path / "cmp", repo_dir=repo,
                                  processes=2, stream=sys.stderr)
    dirs = sorted(p.name for p in (tmp_path / "cmp").iterdir())
    assert len(dirs) == 4 and sum(d.endswith("-p2") for d in dirs) == 2
    c = res.cases[0]
    assert c.units == "processes" and (c.n_base, c.n_head) == (2, 2)
    assert c.speed_ratio == pytest.approx(0.7)
    # two processes per side can never pass 0.05 (smallest p 1/6): said, and no verdict claimed
    assert c.verdicts == [] and "within noise" in " ".join(c.notes)
    text = res.to_text()
    assert "2 vs 2 processes per case: smallest possible p 0.167" in text
    assert "NO speed regression can be flagged; 3 processes per side are needed" in text
    # the command: its comparison page goes beside both sides' runs (it crashed on a display name)
    monkeypatch.chdir(repo)
    assert cli.main(["compare-commits", "HEAD~1", "HEAD", str(scenario), "--processes", "2",
                     "--out", str(tmp_path / "cli")]) == 0
    assert (tmp_path / "cli" / "compare.html").is_file()
    assert f"wrote {tmp_path / 'cli' / 'compare.html'}" in capsys.readouterr().out


def test_tied_small_samples_get_the_exact_permutation_p():
    # 2 v 2 with ties: no ordering gives p below 1/6; the normal approximation said 0.097
    _, p = stats.mann_whitney_less([1.0, 1.0], [2.0, 2.0])
    assert p == pytest.approx(1 / 6)
    _, p = stats.mann_whitney_less([1.0, 2.0, 2.0], [2.0, 3.0, 3.0])
    assert stats.min_p_value(3, 3) <= p < 0.5
    assert stats.samples_needed(0.05) == 3 and stats.samples_needed(0.05 / 60) == 7
    est, lo, hi, cov = stats.ratio_interval([7.0, 7.1, 6.9], [10.0, 10.2, 9.8])
    assert lo < est < hi and est == pytest.approx(0.7, rel=0.02) and cov == pytest.approx(0.9)


def test_processes_auto_is_what_a_lone_slowdown_needs(tmp_path):
    scenario = tmp_path / "two.toml"
    scenario.write_text('name = "two"\n[[cases]]\nscenes = ["cornell"]\nstructures = ["grid"]\n'
                        'backends = ["glsl", "opencl"]\nresolutions = [8]\n')
    # 2 cases: Holm's first level 0.05/2; 3 v 3 reach only 1/20, 4 v 4 reach 1/70
    assert commits.processes_needed(scenario, 0.05) == (4, 2)
    assert commits.processes_needed(scenario, 0.2) == (3, 2)
    assert commits.processes_needed("ci", 0.05)[0] >= 7  # the CI gate's many cases
    for bad in ("0", "many"):
        with pytest.raises(SystemExit) as exc:
            cli.main(["compare-commits", "HEAD", "HEAD", str(scenario), "--processes", bad])
        assert exc.value.code == 2
