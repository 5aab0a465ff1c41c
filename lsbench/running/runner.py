"""Run a scenario: every case in its own worker process with a time limit, so a driver crash,
hang or out-of-memory ends that case only, and the worker dies with the run (PR_SET_PDEATHSIG).
Records go to the run folder through lsbench.results.store as cases finish; a rerun into the same
folder reuses a record only where it still stands for the case (record.reuse_mismatch) and says
why it redoes the rest."""
from __future__ import annotations

import multiprocessing as mp
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from lsbench.inputs.scenario import Case, RunSettings, Scenario
from lsbench.results.record import reuse_mismatch, result_settings
from lsbench.report.format import eta_text
from lsbench.results.store import RunResults
from lsbench.running.execute import case_inputs, execute, failed_record


class Interrupted(KeyboardInterrupt):
    """Ctrl-C during a run; the message says where the finished cases are."""


def budget_text(settings: RunSettings) -> str:
    return f"host memory budget of {settings.memory_budget_mb:g} MiB (--memory-budget, RLIMIT_AS)"


def _test_fault(case: Case) -> None:
    """Test-only fault injection, like LSBENCH_PLANT_DEFECT: env LSBENCH_FAULT=crash|hang, or
    crash:TEXT / hang:TEXT to hit only cases whose key contains TEXT. `crash` kills the worker
    with SIGKILL (as a driver crash or the OOM killer would), `hang` sleeps past any timeout.
    tests/test_limits.py uses it to show that the run records the case and goes on."""
    fault = os.environ.get("LSBENCH_FAULT", "")
    if not fault:
        return
    kind, _, where = fault.partition(":")
    if where and where not in case.key:
        return
    if kind == "crash":
        os.kill(os.getpid(), signal.SIGKILL)
    elif kind == "hang":
        time.sleep(10**6)


def _die_with_parent(parent_pid: int) -> None:
    """Make this worker end when the run that started it ends, however it ends (kill -9
    included): Linux sends SIGKILL on the parent's death (prctl(2) PR_SET_PDEATHSIG); elsewhere
    a thread watches for the parent to go. A worker hung in a driver call dies either way."""
    if sys.platform.startswith("linux"):
        import ctypes

        PR_SET_PDEATHSIG = 1  # <linux/prctl.h>
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    else:
        def watch():
            while os.getppid() == parent_pid:
                time.sleep(0.5)
            os._exit(1)

        threading.Thread(target=watch, daemon=True).start()
    if os.getppid() != parent_pid:  # the parent died before the request took effect
        os._exit(1)


def _worker(conn, parent_pid: int, case: Case, settings: RunSettings, env: dict, heatmap_dir: str | None,
            inputs: dict | None, given: CaseData | None) -> None:
    _die_with_parent(parent_pid)
    # The parent handles Ctrl-C; a worker just dies with it.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _test_fault(case)
    if settings.memory_budget_mb:
        import resource

        limit = int(settings.memory_budget_mb * 2**20)
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    try:
        data = given or CaseData()
        rec = execute(case, settings, env, heatmap_dir=heatmap_dir, scene=data.scene, rays=data.rays,
                      truth=data.truth)
    except MemoryError:
        rec = failed_record(case, settings, f"{budget_text(settings)} exceeded (MemoryError)", env, inputs)
    except Exception as exc:  # bad scene or rays: the case fails with the one-line reason
        rec = failed_record(case, settings, f"{type(exc).__name__}: {exc}".splitlines()[0], env, inputs)
    # Under RLIMIT_AS drivers fail in many ways that do not say "memory" (a kernel build, a
    # context): every failure under a budget says the budget was in force.
    if settings.memory_budget_mb and rec.get("status") != "ok" \
            and "memory budget" not in str(rec.get("reason")):
        rec["reason"] = f"{rec['reason']} (under the {budget_text(settings)})"
    conn.send(rec)
    conn.close()


@dataclass
class CaseData:
    """A case's inputs already in memory (a cluster node gets them by content, not by path):
    the Scene, the RaySet and Embree's (prim_ids, t) for them; None = load or compute it."""
    scene: object = None
    rays: object = None
    truth: tuple | None = None


def run_case_isolated(case: Case, settings: RunSettings, env: dict, heatmap_dir: str | None = None,
                      inputs: dict | None = None, given: CaseData | None = None) -> dict:
    """The record of `case` run in a fresh worker process. `inputs` (what plan_cases expects:
    scene and ray hashes, device) fill the record of a worker that crashed or timed out; `given`
    hands it the scene, rays and ground truth instead of their paths. Call it from the main
    thread: the worker's death signal follows the thread that started it."""
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_worker, args=(child, os.getpid(), case, settings, env, heatmap_dir, inputs, given),
                       daemon=True)
    proc.start()
    child.close()
    try:
        return _wait_for_record(proc, parent, case, settings, env, inputs)
    finally:  # Ctrl-C or an error here: the worker goes too
        if proc.is_alive():
            proc.kill()
            proc.join(5)


def _wait_for_record(proc, parent, case, settings, env, inputs) -> dict:
    rec = None
    deadline = time.monotonic() + settings.timeout_seconds
    while time.monotonic() < deadline:
        if parent.poll(0.2):
            try:
                rec = parent.recv()
            except EOFError:
                rec = None
            break
        if not proc.is_alive() and not parent.poll(0):
            break
    if rec is None:
        if proc.is_alive() and time.monotonic() < deadline:
            # the pipe closed before the deadline: the worker is dying (abort, core dump), give
            # it a moment so a crash is not reported as a timeout
            proc.join(min(10.0, max(0.0, deadline - time.monotonic())))
        if proc.is_alive():
            proc.kill()
            proc.join(5)
            return failed_record(case, settings, f"timed out after {settings.timeout_seconds:g} s (worker killed)",
                                 env, inputs)
        proc.join(5)
        code = proc.exitcode
        what = f"signal {signal.Signals(-code).name}" if code is not None and code < 0 else f"exit code {code}"
        reason = f"worker crashed ({what}) before reporting"
        if settings.memory_budget_mb:
            # drivers abort() or segfault when malloc fails under RLIMIT_AS instead of reporting it
            reason += f"; the {budget_text(settings)} was in force: likely exceeded"
        return failed_record(case, settings, reason, env, inputs)
    proc.join(10)
    return rec


@dataclass
class CasePlan:
    case: Case
    expected: dict  # the identity and environment fields this run would record for the case
    # On a cluster, what the case would record on each other node that may run it: an earlier
    # record is reused when it matches any one of them (lsbench/running/cluster.py).
    alternatives: tuple[dict, ...] = ()

    def reuse_mismatch(self, old: dict, heatmaps_wanted: bool, keep_failed: bool) -> str | None:
        """Why `old` cannot stand for this case (the reason against `expected`), or None."""
        why = reuse_mismatch(old, self.expected, heatmaps_wanted, keep_failed)
        if why is not None and any(reuse_mismatch(old, other, heatmaps_wanted, keep_failed) is None
                                   for other in self.alternatives):
            return None
        return why


def input_id(case: Case) -> tuple:
    """What makes a case's scene and rays: cases with one input_id trace the same rays."""
    return (case.scene, case.rays, case.ray_params, case.width, case.height, case.camera)


def scenario_inputs(scenario: Scenario):
    """(input_id, Scene, RaySet) for every distinct scene and ray set of the scenario, made one
    after another (a missing or corrupt file raises SceneError or RayError here)."""
    from lsbench.inputs.rays import make_rays
    from lsbench.inputs.scenes import load_scene

    made = set()
    for spec in dict.fromkeys(c.scene for c in scenario.cases):
        scene = load_scene(spec)
        for c in scenario.cases:
            if c.scene == spec and input_id(c) not in made:
                made.add(input_id(c))
                yield input_id(c), scene, make_rays(c.rays, scene, c.width, c.height, c.camera_object(),
                                                    c.ray_params)


def expected_fields(case_inputs: dict, env: dict, settings: dict, device: dict) -> dict:
    """What a record of a case would hold about its inputs and environment (reuse_mismatch)."""
    return dict(case_inputs, **env, settings=settings,
                **{f: device.get(f) for f in ("device", "driver", "backend_version")})


def plan_cases(scenario: Scenario, env: dict, devices: dict[str, dict]) -> list[CasePlan]:
    """What each case would record about its inputs and environment, before any case runs:
    every scene and ray set is made here once (a missing or corrupt file is a SceneError or
    RayError now, not a run of failed cases) and known by its content hash. devices: per
    backend, environment.device_info(). (A cluster plans its own: cluster.Cluster.plan.)"""
    described = {rid: case_inputs(scene, rays) for rid, scene, rays in scenario_inputs(scenario)}
    settings = result_settings(scenario.settings)
    return [CasePlan(c, expected_fields(described[input_id(c)], env, settings, devices.get(c.backend) or {}))
            for c in scenario.cases]


def run_locally(todo, total: int, settings: RunSettings, env: dict, heatmap_dir: str | None, log):
    """Run each (index, CasePlan, why) of `todo` in turn in an isolated worker on this machine;
    yield (index, plan, record) as each finishes."""
    for i, plan, why in todo:
        log(f"[{i}/{total}] {plan.case.key}: running" + ("" if why == "new" else f" ({why})"))
        t0 = time.perf_counter()
        rec = run_case_isolated(plan.case, settings, env, heatmap_dir, plan.expected)
        rec["wall_seconds"] = time.perf_counter() - t0
        yield i, plan, rec


def run_scenario(scenario: Scenario, plans: list[CasePlan], out_dir: Path, env: dict, fresh: bool = False,
                 heatmaps: bool | None = None, keep_failed: bool = False, log=print, cases=run_locally) -> list[dict]:
    """Run the planned cases of `scenario` into out_dir (whose store.RunLock the caller holds) and
    return the records, reused ones included. fresh: reuse nothing and supersede results.jsonl
    only once every case is done; keep_failed: reuse failed records too instead of retrying them.
    cases: what runs the cases that are not reused (run_locally, or a cluster's) and yields their
    records as they finish; it draws them from its `todo` iterator as it goes."""
    results = RunResults(out_dir, fresh, warn=lambda m: log(f"warning: {m}"))
    if results.stale_fresh:
        log(f"warning: {results.side} holds an unfinished --fresh run; this run leaves it alone "
            "(the next --fresh run starts it anew)")
    want_heatmaps = scenario.settings.heatmaps if heatmaps is None else heatmaps
    decisions = []
    for plan in plans:
        old = results.earlier.get(plan.case.key)
        why = "new" if old is None else plan.reuse_mismatch(old, want_heatmaps, keep_failed)
        decisions.append((plan, old, why))
    log(resume_text(decisions, fresh))
    total = len(plans)
    records: list[dict | None] = [None] * total

    def todo():  # reused records are told in order, as the runner draws the next case to run
        for i, (plan, old, why) in enumerate(decisions, 1):
            if why is None:
                log(f"[{i}/{total}] {plan.case.key}: done earlier ({old.get('status')}), reused")
                records[i - 1] = old
            else:
                yield i, plan, why

    heatmap_dir = str(out_dir / "heatmaps") if want_heatmaps else None
    finished = cases(todo(), total, scenario.settings, env, heatmap_dir, log)
    to_run = sum(1 for _, _, why in decisions if why is not None)
    walls: list[float] = []
    try:
        for i, plan, rec in finished:
            results.append(rec)
            records[i - 1] = rec
            if rec.get("wall_seconds") is not None:
                walls.append(rec["wall_seconds"])
            log(f"[{i}/{total}] {plan.case.key}: " + progress_text(rec)
                + eta_text(walls, to_run - len(walls)))
    except KeyboardInterrupt:
        finished.close()  # a cluster cancels what it still runs
        raise Interrupted(results.finish(complete=False)) from None
    except BaseException:
        finished.close()
        try:  # an error is on its way out: tidy what can be tidied, without hiding it
            results.finish(complete=False)
        except OSError:
            pass
        raise
    done = results.finish(complete=True)
    if done:
        log(done)
    return [r for r in records if r is not None]


def resume_text(decisions, fresh: bool) -> str:
    """One line: how many records are reused and why the other cases run."""
    total = len(decisions)
    if fresh:
        return f"--fresh: running all {total} cases (earlier records are superseded when the run finishes)"
    reused = sum(1 for _, _, why in decisions if why is None)
    reasons: dict[str, int] = {}
    for _, _, why in decisions:
        if why is not None:
            reasons[why] = reasons.get(why, 0) + 1
    text = f"reusing {reused} of {total} earlier records"
    if reasons:
        text += f"; running {total - reused}: " + ", ".join(f"{n} {why}" for why, n in reasons.items())
    return text


def progress_text(rec: dict) -> str:
    where = f" on {node_text(rec['node'])}" if rec.get("node") else ""
    if rec.get("status") != "ok":
        took = f"{rec['wall_seconds']:.1f} s" if rec.get("wall_seconds") is not None else "no record came back"
        return f"FAILED ({took}{where}): {rec.get('reason')}"
    return (f"ok ({rec.get('wall_seconds') or 0:.1f} s{where}): agreement {rec['agreement']:.6f} "
            f"({rec.get('unexplained')} unexplained), "
            f"{rec['rays_per_second'] / 1e6:.2f} Mrays/s, {rec['memory_bytes'] / 2**20:.1f} MiB, "
            f"build {rec['build_seconds']:.2f} s{auto_text(rec)}")


def auto_text(rec: dict) -> str:
    """For an ok "auto" case: what the cost model chose, its prediction, and whether it ranked with
    the default constants (lsbench/report/auto.py shows the whole choice)."""
    from lsbench.model.check import setting_text
    from lsbench.report.auto import used_default_constants

    if not rec.get("auto") or rec.get("status") != "ok":
        return ""
    predicted = (rec.get("predicted") or {}).get("rays_per_second")
    text = f"; auto chose {setting_text(rec)}" + (f" (predicted {predicted / 1e6:.2f} Mrays/s)" if predicted else "")
    if used_default_constants(rec):
        text += ", ranked with the default constants: run `lsbench fit` for this device's own"
    return text


def node_text(node: dict) -> str:
    """A record's `node` (the cluster node that ran it) in a few words."""
    return f"{node.get('host')} ({node.get('ip')}, node {str(node.get('id'))[:12]})"


def _setting_columns(rec: dict) -> tuple[str, str]:
    """The summary's res and N: as the case asked, and for an ok "auto" case what was built."""
    from lsbench.model.check import setting_of

    res, n = str(rec.get("resolution")), str(rec.get("ls_n") or "-")
    if rec.get("auto") and rec.get("status") == "ok" and rec.get("resolution_x") is not None:
        built = setting_of((rec["resolution_x"], rec["resolution_y"], rec["resolution_z"]))
        res = built if res == built else f"{res}: {built}"
        if rec.get("ls_n"):
            n = f"{rec['ls_n']} K={rec.get('ls_min_candidates') or 0}"
    return res, n


def summary_table(records: list[dict]) -> str:
    from lsbench.report.format import text_table
    from lsbench.report.records import label_scenes, scene_name

    records = [dict(r) for r in records]
    label_scenes(records)  # two files of one name in different folders are two scenes
    head = ["scene", "rays", "structure", "backend", "res", "N", "status", "agreement", "Mrays/s",
            "FPS", "MiB", "build s"]
    rows = []
    for r in records:
        ok = r.get("status") == "ok"
        rows.append([
            scene_name(r), f"{r.get('rays')}@{r.get('width')}x{r.get('height')}", r.get("structure"),
            r.get("backend"), *_setting_columns(r),
            "ok" if ok else "FAILED",
            f"{r['agreement']:.6f}" if ok else "-",
            f"{r['rays_per_second'] / 1e6:.3f}" if ok else "-",
            f"{r['fps']:.1f}" if ok and r.get("fps") else "-",
            f"{r['memory_bytes'] / 2**20:.2f}" if ok else "-",
            f"{r['build_seconds']:.3f}" if ok else "-",
        ])
    out = text_table(head, rows)
    for r in records:
        if r.get("status") != "ok":
            out.append(f"FAILED {r.get('key')}: {r.get('reason')}")
    return "\n".join(out)
