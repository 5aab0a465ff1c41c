"""Compare two commits: run one scenario at each revision in its own temporary git worktree (with
that revision's code on PYTHONPATH), then compare the two runs (lsbench/compare/verdicts.py)."""
from __future__ import annotations

import datetime as _dt
import os
import shutil
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


def compare_commits(rev_a: str, rev_b: str, scenario, factor: float = DEFAULT_FACTOR,
                    out_dir=None, repo_dir=None, alpha: float = DEFAULT_ALPHA,
                    extra_args=(), stream=None, only_common: bool = False,
                    scenes=None) -> CompareResult:
    """Run SCENARIO at two revisions, then compare (base = rev_a, head = rev_b).

    Both runs see the same inputs: the scenario file is resolved against the current directory
    when it exists there (else taken as relative to each worktree), and `$SCENES` is the scenes
    folder of the calling checkout (`scenes`, default lsbench.paths.scenes_dir()), passed to
    both runs as LSBENCH_SCENES: resolved inside a temporary worktree it would name a folder
    beside that worktree, which does not exist. Worktrees are removed afterwards, also on
    failure."""
    repo_dir = Path(repo_dir or _git(".", "rev-parse", "--show-toplevel").stdout.strip()).resolve()
    shas = []
    for rev in (rev_a, rev_b):
        r = _git(repo_dir, "rev-parse", "--verify", f"{rev}^{{commit}}", check=False)
        if r.returncode != 0:
            raise ValueError(f"unknown revision {rev!r}: {r.stderr.strip()}")
        shas.append(r.stdout.strip())
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    out_dir = Path(out_dir or repo_dir / "reports" /
                   f"compare-{slug(rev_a, empty='rev')}-{slug(rev_b, empty='rev')}-{stamp}")
    out_dir = out_dir.resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    scen = Path(scenario)
    scen_arg = str(scen.resolve()) if scen.exists() else str(scenario)
    scenes = Path(scenes if scenes is not None else scenes_dir()).resolve()

    run_dirs = []
    tmp_root = Path(tempfile.mkdtemp(prefix="lsbench-wt-"))
    try:
        for i, (rev, sha) in enumerate(zip((rev_a, rev_b), shas)):
            label = f"{'ab'[i]}-{slug(rev, empty='rev')}-{sha[:10]}"
            wt = tmp_root / label
            _git(repo_dir, "worktree", "add", "--detach", str(wt), sha)
            try:
                run_dir = out_dir / label
                env = dict(os.environ, LSBENCH_SCENES=str(scenes))
                env["PYTHONPATH"] = str(wt) + (os.pathsep + env["PYTHONPATH"]
                                               if env.get("PYTHONPATH") else "")
                cmd = [sys.executable, "-m", "lsbench", "run", scen_arg, "--out",
                       str(run_dir), *extra_args]
                print(f"[{rev} = {sha[:10]}] LSBENCH_SCENES={scenes} {' '.join(cmd)}",
                      file=stream or sys.stderr, flush=True)
                proc = subprocess.run(cmd, cwd=wt, env=env)
                # A run that exits non-zero (e.g. its accuracy gate failed) still leaves records
                # to compare; only a run that produced nothing is an error.
                if not (run_dir / "results.jsonl").exists():
                    raise RuntimeError(f"run at {rev} ({sha[:10]}) exited {proc.returncode} "
                                       f"and wrote no {run_dir / 'results.jsonl'}")
                run_dirs.append(run_dir)
            finally:
                _git(repo_dir, "worktree", "remove", "--force", str(wt), check=False)
    finally:
        _git(repo_dir, "worktree", "prune", check=False)
        shutil.rmtree(tmp_root, ignore_errors=True)
    return compare_runs(run_dirs[0], run_dirs[1], factor=factor, alpha=alpha,
                        only_common=only_common)
