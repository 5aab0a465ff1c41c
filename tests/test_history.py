"""The history database (lsbench/results/history.py), step detection (lsbench/compare/steps.py),
backfill through the worktree runner on a throw-away clone, `run --history`, and the history
page in headless Chromium."""
from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path
from urllib.parse import unquote, urlparse

import numpy as np
import pytest

from lsbench import cli
from lsbench.compare import steps
from lsbench.compare.history import analyse, summary_text
from lsbench.paths import source_checkout
from lsbench.results import history, store

CHROMIUM = "/usr/bin/chromium"
GL_DEV = "llvmpipe (LLVM 15.0.6, 256 bits)"


def _git(repo, *args) -> str:
    return subprocess.run(["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t", *args],
                          check=True, capture_output=True, text=True).stdout.strip()


def fake_record(key: str, rps: float, rng, noise=0.02, repeats=5, agreement=1.0, status="ok") -> dict:
    ray_count = 10000
    rec = {"key": key, "scene": "quad", "structure": key.split("|")[0], "backend": "glsl",
           "status": status, "reason": "" if status == "ok" else "worker timed out", "device": GL_DEV,
           "ray_count": ray_count}
    if status == "ok":
        times = [ray_count / rps * (1 + noise * rng.standard_normal()) for _ in range(repeats)]
        rec.update(trace_seconds_all=times, trace_seconds=float(np.median(times)),
                   rays_per_second=ray_count / float(np.median(times)), agreement=agreement)
    return rec


def fake_run(run_dir: Path, commit: str, records, date="2026-01-01T00:00:00", host="bench-host") -> Path:
    store.write_run_info(run_dir, {"commit": commit, "dirty": False, "date": date, "host": host,
                                   "scenario_name": "tiny", "platform": "Linux",
                                   "devices": {"glsl": {"device": GL_DEV, "driver": "Mesa"}}})
    for r in records:
        store.append_record(run_dir, r)
    return run_dir


@pytest.fixture
def linear_repo(tmp_path):
    """A git repository of 10 commits on one line: (repo, shas oldest first)."""
    repo = tmp_path / "repo"
    repo.mkdir()
    _git(tmp_path, "init", "-q", str(repo))
    shas = []
    for i in range(10):
        (repo / "f.txt").write_text(f"{i}\n")
        _git(repo, "add", "f.txt")
        _git(repo, "commit", "-q", "-m", f"commit {i}")
        shas.append(_git(repo, "rev-parse", "HEAD"))
    return repo, shas


def planted_history(tmp_path, repo, shas, slow_from=6, runs_per_commit=2) -> Path:
    """A database over shas: grid|64 loses 30 % at shas[slow_from], svo|64 stays; runs appended in
    shuffled order (the sequence must come from the commits, not the order of appending)."""
    db = tmp_path / "db"
    rng = np.random.default_rng(7)
    order = list(range(len(shas)))
    rng.shuffle(order)
    for i in order:
        for k in range(runs_per_commit):
            grid = 1e6 * (0.7 if i >= slow_from else 1.0) * (1 + 0.02 * rng.standard_normal())
            svo = 2e6 * (1 + 0.02 * rng.standard_normal())
            run = fake_run(tmp_path / "runs" / f"{i}-{k}", shas[i],
                           [fake_record("grid|64", grid, rng), fake_record("svo|64", svo, rng)],
                           date=f"2026-01-{i + 1:02d}T00:00:0{k}")
            history.append_run(db, run, repo_dir=repo)
    return db


# ---------------------------------------------------------------- the database layout

def test_layout_round_trips(tmp_path, linear_repo):
    repo, shas = linear_repo
    rng = np.random.default_rng(0)
    recs = [fake_record("grid|64", 1e6, rng), fake_record("svo|64", 2e6, rng, status="failed")]
    run = fake_run(tmp_path / "run", shas[3], recs)
    db = tmp_path / "db"
    stored = history.append_run(db, run, repo_dir=repo, source="test")
    assert json.loads((db / "history.json").read_text()) == {"format": 1}
    assert stored.parent == db / "bench-host" / shas[3][:12]
    machine = json.loads((db / "bench-host" / "machine.json").read_text())
    assert machine["host"] == "bench-host" and machine["devices"]["glsl"]["device"] == GL_DEV
    # the stored run is an ordinary run folder: store.read_run gives back the same records
    info, back = store.read_run(stored)
    assert back == recs
    assert info["history"]["order"] == 4 and info["history"]["subject"] == "commit 3"
    assert info["history"]["source"] == "test" and info["commit"] == shas[3]
    # appending the same run again replaces it: its repeats are not counted twice
    assert history.append_run(db, run, repo_dir=repo) == stored
    runs = history.read_history(db)
    assert len(runs) == 1 and runs[0].records == recs and runs[0].commit == shas[3]
    assert history.runs_at(db, "bench-host", shas[3], "tiny") == 1
    assert history.runs_at(db, "bench-host", shas[3], "other") == 0
    # a series point holds the ok figures and the failure's reason
    pts = history.series(runs)
    grid = pts[("bench-host", "grid|64", GL_DEV)][0]
    assert grid.repeats == pytest.approx(list(1e4 / np.asarray(recs[0]["trace_seconds_all"])))
    assert pts[("bench-host", "svo|64", GL_DEV)][0].failed == ["worker timed out"]
    # folders that are no database are refused with the reason
    with pytest.raises(history.HistoryError, match="no history database"):
        history.read_history(tmp_path / "run")
    with pytest.raises(history.HistoryError, match="not empty"):
        history.append_run(tmp_path / "run", run)
    (tmp_path / "empty").mkdir()
    with pytest.raises(history.HistoryError, match="no records"):
        history.append_run(db, tmp_path / "empty")


def test_runs_sort_by_commit_order_not_by_appending(tmp_path, linear_repo):
    repo, shas = linear_repo
    db = planted_history(tmp_path, repo, shas)
    runs = history.read_history(db)
    assert [r.commit for r in runs][::2] == shas  # two runs per commit, in commit order
    pts = history.series(runs)[("bench-host", "grid|64", GL_DEV)]
    assert [p.commit for p in pts] == shas and all(len(p.process_figures) == 2 for p in pts)


# ---------------------------------------------------------------- step detection

def test_segment_costs_match_the_direct_sum():
    rng = np.random.default_rng(11)
    for n in (1, 2, 5, 16):
        y = np.round(rng.standard_normal(n), 1)  # ties too
        cost = steps._segment_costs(y)
        for i in range(n):
            for j in range(i, n):
                seg = y[i:j + 1]
                assert cost[i, j] == pytest.approx(np.abs(seg - np.median(seg)).sum(), abs=1e-12)


def test_planted_step_is_found_at_its_commit():
    for seed in range(10):
        rng = np.random.default_rng(seed)
        v = 1e6 * np.exp(0.03 * rng.standard_normal(20))
        v[13:] *= 0.75
        fit = steps.fit_steps(v)
        assert len(fit.steps) == 1, seed
        s = fit.steps[0]
        assert (s.before, s.after) == (12, 13) and s.ratio == pytest.approx(0.75, rel=0.05)
    # two steps, one down and one back up
    rng = np.random.default_rng(3)
    v = np.exp(0.02 * rng.standard_normal(30))
    v[10:20] *= 0.6
    fit = steps.fit_steps(v)
    assert [(s.before, s.after) for s in fit.steps] == [(9, 10), (19, 20)]


def test_no_step_in_noise():
    for n in (8, 12, 30, 100):
        for seed in range(10):
            rng = np.random.default_rng(1000 + seed)
            assert steps.fit_steps(np.exp(0.05 * rng.standard_normal(n))).steps == [], (n, seed)
    # one wild commit (8 sigma) is an outlier of the L1 fit, not two steps; one far past twice
    # the penalty is two (a slowdown fixed at the next commit)
    v = np.exp(0.02 * np.random.default_rng(5).standard_normal(20))
    v[7] *= 0.85
    assert steps.fit_steps(v).steps == []
    v[7] *= 0.5
    assert [(s.before, s.after) for s in steps.fit_steps(v).steps] == [(6, 7), (7, 8)]
    assert steps.fit_steps([5.0]).steps == [] and steps.fit_steps([5.0] * 10).steps == []
    with pytest.raises(ValueError):
        steps.fit_steps([1.0, 0.0])


def test_history_names_the_commit_range_of_a_step(tmp_path, linear_repo):
    repo, shas = linear_repo
    cases = analyse(history.series(history.read_history(planted_history(tmp_path, repo, shas))))
    by = {c.key: c for c in cases}
    assert by["svo|64"].steps == []
    (step,) = by["grid|64"].steps
    assert step.kind == "slowdown" and step.ratio == pytest.approx(0.7, rel=0.05)
    assert step.commit_range == f"{shas[5][:10]}..{shas[6][:10]}"
    assert step.first_suspect.subject == "commit 6"
    text = summary_text(cases, 1.1)
    assert f"slowdown x0.70 @ {shas[5][:10]}..{shas[6][:10]}" in text and "1 slowdowns" in text


# ---------------------------------------------------------------- backfill and run --history, for real

TINY = """name = "tiny-history"
[run]
width = 16
height = 16
repeats = 2
warmup = 0
timeout_seconds = 300

[[cases]]
scenes = ["single-triangle"]
structures = ["grid"]
backends = ["glsl"]
resolutions = [4]
"""


@pytest.fixture
def clone(tmp_path):
    top = source_checkout()
    if top is None or not (top / ".git").exists():
        pytest.fail("the tests run from a git checkout of lsbench")
    dest = tmp_path / "clone"
    subprocess.run(["git", "clone", "-q", "--no-hardlinks", str(top), str(dest)], check=True)
    _git(dest, "checkout", "-q", _git(top, "rev-parse", "HEAD"))
    return dest


def test_backfill_over_real_commits_of_a_clone(tmp_path, clone, capsys):
    scenario = tmp_path / "tiny.toml"
    scenario.write_text(TINY)
    db = tmp_path / "db"
    shas = _git(clone, "rev-list", "--first-parent", "--reverse", "HEAD~2..HEAD").split()
    assert len(shas) == 2
    assert cli.main(["history", str(db), "--repo", str(clone), "--backfill", "HEAD~2..HEAD",
                     str(scenario)]) == 0
    out = capsys.readouterr().out
    assert "backfill HEAD~2..HEAD: 2 runs stored" in out and "1 cases over 2 commits" in out
    runs = history.read_history(db)
    assert [r.commit for r in runs] == shas
    for r in runs:
        assert r.info["history"]["source"] == "backfill" and r.records[0]["status"] == "ok"
        assert r.records[0]["commit"] == r.commit  # each ran that commit's own code
    assert [r.info["history"]["order"] for r in runs] == [
        int(_git(clone, "rev-list", "--count", s)) for s in shas]
    assert _git(clone, "worktree", "list").count("\n") == 0  # temporary worktrees are gone
    # a second backfill finds both commits stored and runs nothing
    assert cli.main(["history", str(db), "--repo", str(clone), "--backfill", "HEAD~2..HEAD",
                     str(scenario)]) == 0
    assert "backfill HEAD~2..HEAD: 0 runs stored" in capsys.readouterr().out
    assert cli.main(["history", str(db), "--repo", str(clone), "--backfill", "nope..HEAD",
                     str(scenario)]) == 2


def test_run_appends_to_the_history(tmp_path, capsys):
    scenario = tmp_path / "tiny.toml"
    scenario.write_text(TINY)
    db = tmp_path / "db"
    assert cli.main(["run", str(scenario), "--out", str(tmp_path / "run"), "--history", str(db)]) == 0
    assert "history: stored as" in capsys.readouterr().out
    (run,) = history.read_history(db)
    assert run.records == store.read_run(tmp_path / "run")[1]
    assert run.info["history"]["source"] == "run"
    # the history page is rewritten, and the run's report links it
    assert (db / "index.html").is_file()
    from lsbench.report import page
    index = page.write_report(tmp_path / "run")
    link = re.search(r"href='([^']+)'>history page</a>", index.read_text()).group(1)
    assert (index.parent / link).resolve() == (db / "index.html").resolve()


# ---------------------------------------------------------------- the page

def test_history_page_renders_in_headless_chromium(tmp_path, linear_repo, capsys):
    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} absent (apt-get install -y chromium)")
    repo, shas = linear_repo
    db = planted_history(tmp_path, repo, shas)
    assert cli.main(["history", str(db)]) == 0
    out = capsys.readouterr().out
    page = db / "index.html"
    assert f"wrote {page}" in out
    common = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
              "--disable-component-update", "--disable-sync", "--no-first-run",
              f"--user-data-dir={tmp_path / 'profile'}"]
    dom = subprocess.run(common + ["--dump-dom", page.resolve().as_uri()], capture_output=True,
                         text=True, timeout=120).stdout
    assert "<h1>lsbench history</h1>" in dom and "1 slowdowns" in dom
    assert f"{shas[5][:10]}..{shas[6][:10]}" in dom
    assert dom.count("<section") == 2 and dom.count("class=\"slowdown\"") == 1
    links = re.findall(r"(?:href|src)=\"([^\"]+)\"", dom)
    files = [u for u in links if not u.startswith("#")]
    anchors = [u[1:] for u in links if u.startswith("#")]
    assert len(files) >= 2 * 10 * 2 + 2  # every stored run of both cases, and both charts
    for u in files:
        target = (page.parent / unquote(urlparse(u).path)).resolve()
        assert target.is_file(), u
    for a in anchors:
        assert f"id=\"{a}\"" in dom, a
    svg = next(u for u in files if u.endswith(".svg"))
    assert "<svg" in (page.parent / unquote(svg)).read_text()[:2000]
    shot = tmp_path / "shot.png"
    subprocess.run(common + [f"--screenshot={shot}", "--window-size=1200,1600", page.resolve().as_uri()],
                   capture_output=True, timeout=120)
    import matplotlib.image
    img = matplotlib.image.imread(shot)[..., :3]
    assert img.shape[:2] == (1600, 1200) and img.std() > 0.05
    assert len(np.unique((img.reshape(-1, 3) * 255).astype(np.uint8), axis=0)) > 50


def test_history_bad_input_is_one_line_and_exit_2(tmp_path, capsys):
    assert cli.main(["history", str(tmp_path / "none")]) == 2
    assert "no history database here" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        cli.main(["history", str(tmp_path / "db"), "--processes", "0"])
    assert exc.value.code == 2 and "--processes" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        cli.main(["history", str(tmp_path / "db"), "--statistic", "mean"])
    assert exc.value.code == 2
