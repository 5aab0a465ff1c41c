"""Runs at past commits: one scenario at each revision in its own temporary git worktree (with
that revision's code on PYTHONPATH). compare_commits runs two and compares them
(lsbench/compare/verdicts.py); backfill runs a range of them into the history database
(lsbench/results/history.py)."""
from __future__ import annotations

import datetime as _dt
import os
import shutil
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

from lsbench.compare.verdicts import DEFAULT_ALPHA, DEFAULT_FACTOR, CompareResult, compare_runs
from lsbench.paths import scenes_dir
from lsbench.report.format import slug


def _git(repo, *args, check=True):
    return subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True,
                          check=check)


def repo_root(repo_dir=None) -> Path:
    return Path(repo_dir or _git(".", "rev-parse", "--show-toplevel").stdout.strip()).resolve()


def resolve_revision(repo_dir: Path, rev: str) -> str:
    r = _git(repo_dir, "rev-parse", "--verify", f"{rev}^{{commit}}", check=False)
    if r.returncode != 0:
        raise ValueError(f"unknown revision {rev!r}: {r.stderr.strip()}")
    return r.stdout.strip()


def revision_range(repo_dir: Path, rev_range: str) -> list[str]:
    """The commits of a git range (`A..B`, or one revision for itself alone), oldest first,
    along first parents: one line of history, the sequence a step model needs."""
    if ".." not in rev_range:
        return [resolve_revision(repo_dir, rev_range)]
    r = _git(repo_dir, "rev-list", "--reverse", "--first-parent", rev_range, check=False)
    if r.returncode != 0:
        raise ValueError(f"bad revision range {rev_range!r}: {r.stderr.strip()}")
    shas = r.stdout.split()
    if not shas:
        raise ValueError(f"revision range {rev_range!r} holds no commits")
    return shas


class WorktreeRunner:
    """`lsbench run SCENARIO --out DIR` at given commits, each in a temporary detached worktree of
    repo_dir (made on first use, all removed on close, also on failure). Every run sees the same
    inputs: the scenario file is resolved against the current directory when it exists there
    (else taken as relative to each worktree), and `$SCENES` is the scenes folder of the calling
    checkout (`scenes`, default lsbench.paths.scenes_dir()), passed as LSBENCH_SCENES: resolved
    inside a temporary worktree it would name a folder beside that worktree, which does not
    exist."""

    def __init__(self, repo_dir: Path, scenario, scenes=None, extra_args=(), stream=None):
        self.repo_dir = repo_dir
        scen = Path(scenario)
        self.scenario = str(scen.resolve()) if scen.exists() else str(scenario)
        self.scenes = Path(scenes if scenes is not None else scenes_dir()).resolve()
        self.extra_args = list(extra_args)
        self.stream = stream or sys.stderr
        self.tmp_root = Path(tempfile.mkdtemp(prefix="lsbench-wt-"))
        self.worktrees: dict[str, Path] = {}

    def __enter__(self) -> "WorktreeRunner":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        for wt in self.worktrees.values():
            _git(self.repo_dir, "worktree", "remove", "--force", str(wt), check=False)
        self.worktrees.clear()
        _git(self.repo_dir, "worktree", "prune", check=False)
        shutil.rmtree(self.tmp_root, ignore_errors=True)

    def worktree(self, sha: str) -> Path:
        if sha not in self.worktrees:
            wt = self.tmp_root / sha[:12]
            _git(self.repo_dir, "worktree", "add", "--detach", str(wt), sha)
            self.worktrees[sha] = wt
        return self.worktrees[sha]

    def run(self, sha: str, run_dir: Path, rev: str | None = None) -> Path:
        """Run the scenario at sha into run_dir; RuntimeError when it left no records. A run that
        exits non-zero (e.g. a case failed) still leaves records, which count."""
        wt = self.worktree(sha)
        env = dict(os.environ, LSBENCH_SCENES=str(self.scenes))
        env["PYTHONPATH"] = str(wt) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        cmd = [sys.executable, "-m", "lsbench", "run", self.scenario, "--out", str(run_dir), *self.extra_args]
        print(f"[{rev or sha[:10]} = {sha[:10]}] LSBENCH_SCENES={self.scenes} {' '.join(cmd)}",
              file=self.stream, flush=True)
        proc = subprocess.run(cmd, cwd=wt, env=env)
        if not (run_dir / "results.jsonl").exists():
            raise RuntimeError(f"run at {rev or sha} ({sha[:10]}) exited {proc.returncode} "
                               f"and wrote no {run_dir / 'results.jsonl'}")
        return run_dir


def _stamp() -> str:
    return _dt.datetime.now().strftime("%Y%m%d-%H%M%S")


def processes_needed(scenario, alpha: float = DEFAULT_ALPHA) -> tuple[int, int]:
    """(runs per revision, cases) for `compare-commits --processes auto`: the fewest runs K such
    that K against K per-run samples can reach Holm's first level alpha / cases (the exact U
    test's smallest p is 1 / C(2K, K)), so that a lone slowdown can be flagged at all."""
    from lsbench.compare.stats import samples_needed
    from lsbench.inputs.scenario import load_scenario

    cases = max(1, len(load_scenario(str(scenario)).cases))
    return max(2, samples_needed(alpha / cases) or 2), cases


def compare_commits(rev_a: str, rev_b: str, scenario, factor: float = DEFAULT_FACTOR,
                    out_dir=None, repo_dir=None, alpha: float = DEFAULT_ALPHA,
                    extra_args=(), stream=None, only_common: bool = False,
                    scenes=None, processes: int = 1) -> CompareResult:
    """Run SCENARIO at two revisions, then compare (base = rev_a, head = rev_b).

    processes > 1 runs the scenario that many times at each revision, alternating a, b, a, b so
    that a drift of the machine's load falls on both alike; each run is a new process per case
    (and a new build), and the comparison then takes each run's median as one sample: the spread
    across processes is the larger one (`lsbench stability`)."""
    repo_dir = repo_root(repo_dir)
    shas = [resolve_revision(repo_dir, rev) for rev in (rev_a, rev_b)]
    out_dir = Path(out_dir or repo_dir / "reports" /
                   f"compare-{slug(rev_a, empty='rev')}-{slug(rev_b, empty='rev')}-{_stamp()}").resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    dirs: list[list[Path]] = [[], []]
    with WorktreeRunner(repo_dir, scenario, scenes, extra_args, stream) as runner:
        for k in range(processes):
            for i, (rev, sha) in enumerate(zip((rev_a, rev_b), shas)):
                label = f"{'ab'[i]}-{slug(rev, empty='rev')}-{sha[:10]}" + (f"-p{k + 1}" if k else "")
                dirs[i].append(runner.run(sha, out_dir / label, rev))
    result = compare_runs(dirs[0], dirs[1], factor=factor, alpha=alpha, only_common=only_common)
    result.folder = str(out_dir)  # both sides' runs are in it: so is their comparison
    return result


def scenario_name(scenario) -> str | None:
    """The `name` a scenario file declares (what run.json calls it), None when unreadable."""
    import tomllib

    from lsbench.paths import shipped_scenario

    path = Path(scenario)
    if not path.exists():
        path = shipped_scenario(str(scenario)) or path
    try:
        return tomllib.loads(path.read_text()).get("name") or path.stem
    except (OSError, tomllib.TOMLDecodeError):
        return None


def backfill(history_dir, rev_range: str, scenario, processes: int = 1, repo_dir=None, out_dir=None,
             extra_args=(), stream=None, scenes=None) -> list[Path]:
    """Run SCENARIO `processes` times at every commit of rev_range and append each run to the
    history database; commits that already hold `processes` runs of this scenario on this machine
    get only the runs they lack (an interrupted backfill resumes). The runs go in rounds, one run
    per commit each, oldest to newest and back again: a drift of the machine's load over the
    backfill then falls on old and new commits alike instead of reading as a step. Returns the
    stored runs' folders. The run folders themselves go to out_dir (default: a temporary folder,
    removed)."""
    from lsbench.results import history

    stream = stream or sys.stderr
    repo_dir = repo_root(repo_dir)
    shas = revision_range(repo_dir, rev_range)
    hist = history.open_history(history_dir, create=True)
    name = scenario_name(scenario)
    machine = slug(socket.gethostname())
    have = {sha: history.runs_at(hist, machine, sha, name) for sha in shas}
    for n, sha in enumerate(shas, 1):
        if have[sha] >= processes:
            print(f"backfill {n}/{len(shas)} {sha[:10]}: {have[sha]} runs of {name} stored, skipped",
                  file=stream, flush=True)
    keep = out_dir is not None
    work = Path(out_dir).resolve() if keep else Path(tempfile.mkdtemp(prefix="lsbench-backfill-"))
    stored = []
    try:
        with WorktreeRunner(repo_dir, scenario, scenes, extra_args, stream) as runner:
            for k in range(processes):
                order = list(enumerate(shas, 1))
                for n, sha in (order if k % 2 == 0 else order[::-1]):
                    if have[sha] > k:
                        continue
                    run_dir = runner.run(sha, work / f"{n:03d}-{sha[:12]}-p{k + 1}")
                    stored.append(history.append_run(hist, run_dir, repo_dir, source="backfill"))
                    print(f"backfill round {k + 1}/{processes}, commit {n}/{len(shas)} {sha[:10]}: stored",
                          file=stream, flush=True)
    finally:
        if not keep:
            shutil.rmtree(work, ignore_errors=True)
    return stored
