"""Sweeps beyond one machine (issue 19): the cases of a run are Ray tasks, scheduled by Ray on the
nodes of a cluster, each run on its node in the same isolated worker as a local case
(runner.run_case_isolated: time limit, crash -> failed record). Ray is the engine; lsbench only
says which nodes may run a case and hands the records to the run's one results store
(runner.run_scenario), so resume, the output lock, the reuse rules and --fresh are the local ones.

- A node offers every backend whose device it can open: when a run starts, a probe task on each
  node opens the backends there (environment.device_info). A case may run on the nodes that opened
  its backend (a Ray label selector on their node ids); where some of them open it on a GPU, only on
  those, asking for a GPU (`num_gpus=1`) when Ray counts one there. `--cluster-resource NAME=N`
  asks every case for a custom resource of the nodes (`ray start --resources`), which pins cases to
  the machines that carry it.
- A node runs the cases only if its lsbench is the submitter's, file for file (code_fingerprint):
  records name the submitter's commit, so a node with other code is left out, saying so.
- Scenes and rays travel by content through Ray's object store, made once on the submitter
  (runner.scenario_inputs, which also checks them before any case runs); workers need no shared
  file system. Embree's ground truth is one task per (scene, rays), its arrays shared by every case
  that traces those rays.
- Records come back as cases finish and are stored at once; each names the node that ran it and
  carries that node's package versions and device. A node that dies mid-case: Ray runs the case
  again on another node that may run it (`--cluster-retries`, Ray's max_retries); when no attempt
  is left, the case fails naming the lost node. A case is stored once, when its task ends.
"""
from __future__ import annotations

import hashlib
import os
import re
import socket
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from lsbench.inputs.scenario import Case, RunSettings, Scenario
from lsbench.results.record import result_settings
from lsbench.running.execute import case_inputs, failed_record
from lsbench.running.runner import CaseData, CasePlan, expected_fields, input_id, scenario_inputs

INSTALL_HINT = "pip install 'lsbench[cluster]'"
# What a case asks of its node besides a GPU: one CPU, Ray's default. The backends here use every
# core of their node, so for timings that compare, start a node with one slot per device
# (`ray start --num-cpus 1`, docs/cluster.md).
CASE_CPUS = 1
CONNECT_SECONDS = 10  # a head that does not accept a connection in this time is not there
PROBE_SECONDS = 300  # opening both backends takes a few seconds; a node silent longer is left out
NODE_ID_LABEL = "ray.io/node-id"  # the label Ray gives every node; a selector lists ids as "in(a,b)", no spaces (Ray 2.60 keeps them)


class ClusterError(RuntimeError):
    """The cluster cannot run this sweep (Ray missing, no connection): one-line message."""


def _ray():
    try:
        import ray
    except ImportError:
        raise ClusterError(f"lsbench run --cluster needs Ray: {INSTALL_HINT}") from None
    return ray


def code_fingerprint() -> str:
    """sha256 (16 hex digits) of the lsbench package's source and kernel files: equal on two
    machines when they run the same code, whether a checkout or an installed copy."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for path in sorted(root.rglob("*")):
        if path.is_file() and "__pycache__" not in path.parts and path.suffix != ".pyc":
            h.update(path.relative_to(root).as_posix().encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()[:16]


@dataclass
class Node:
    """One node of the cluster as the probe found it."""
    id: str  # Ray node id (hex)
    host: str
    ip: str
    resources: dict[str, float]
    devices: dict[str, dict] = field(default_factory=dict)  # per backend: environment.device_info()
    gpu: dict[str, bool] = field(default_factory=dict)  # per backend: its device is a GPU
    machine: dict = field(default_factory=dict)  # environment.machine_env() there
    unusable: str | None = None  # why no case runs there

    @property
    def name(self) -> dict:
        """What a record's `node` holds."""
        return {"host": self.host, "ip": self.ip, "id": self.id}

    def opens(self, backend: str) -> bool:
        return self.unusable is None and (self.devices.get(backend) or {}).get("device") is not None

    def describe(self) -> dict:
        return {**self.name, "resources": self.resources, "devices": self.devices, "gpu": self.gpu,
                "versions": self.machine.get("versions"), "unusable": self.unusable}


@dataclass(frozen=True)
class Placement:
    """Where the cases of one backend may run, and what their tasks ask for."""
    nodes: tuple[Node, ...]
    num_gpus: int
    none_because: str = ""  # when no node may run them: the case's failure reason

    def options(self, resources: dict[str, float], retries: int) -> dict:
        """Ray task options: the nodes by id (Ray's label selector), the resources, the retries."""
        ids = ",".join(n.id for n in self.nodes)
        return {"num_cpus": CASE_CPUS, "num_gpus": self.num_gpus, "resources": dict(resources),
                "label_selector": {NODE_ID_LABEL: f"in({ids})"}, "max_retries": retries,
                "retry_exceptions": False}


def place(backend: str, nodes: list[Node], resources: dict[str, float]) -> Placement:
    """The nodes that may run a case of `backend`: those that opened it and carry `resources`;
    of them, the ones that open it on a GPU when there are any (a real GPU is what a benchmark
    wants; pin cases elsewhere with resources). Their tasks ask for a GPU when Ray counts one on
    every such node (`ray start --num-gpus`), so one case at a time uses it."""
    carrying = [n for n in nodes if all(n.resources.get(k, 0) >= v for k, v in resources.items())]
    opened = [n for n in carrying if n.opens(backend)]
    if not opened:
        why = [f"{n.host} ({n.id[:12]}): " + (n.unusable or (n.devices.get(backend) or {}).get("error")
                                              or "does not open it")
               for n in carrying]
        if len(carrying) < len(nodes):
            why.append(f"{len(nodes) - len(carrying)} nodes lack the resources {resources}")
        return Placement((), 0, f"no node of the cluster opens backend {backend} ({'; '.join(why)})")
    on_gpu = [n for n in opened if n.gpu.get(backend)]
    if on_gpu:
        return Placement(tuple(on_gpu), 1 if all(n.resources.get("GPU", 0) >= 1 for n in on_gpu) else 0)
    return Placement(tuple(opened), 0)


# --- what runs on the nodes --------------------------------------------------------------------


def _this_node() -> tuple[str, str]:
    ray = _ray()
    return ray.get_runtime_context().get_node_id(), ray.util.get_node_ip_address()


def _probe(backend_names: list[str]) -> dict:
    """On one node: the backends it opens, whether each is on a GPU, its software and code."""
    from lsbench import backends
    from lsbench.running.environment import device_info, machine_env, on_gpu

    devices = device_info(backend_names)
    gpu = {name: on_gpu(name, backends.get_device(name).info()) for name in backend_names
           if devices[name].get("device") is not None}
    return {"host": socket.gethostname(), "devices": devices, "gpu": gpu, "machine": machine_env(),
            "fingerprint": code_fingerprint()}


def _ground_truth(scene, rays):
    """Embree's closest hits for one (scene, rays), once for every case that traces them."""
    from lsbench.oracle.embree import embree_closest

    return embree_closest(scene, rays)


def _run_case(case: Case, settings: RunSettings, env: dict, expected_by_node: dict[str, dict],
              heatmaps: bool, scene, rays, truth) -> tuple[dict, dict[str, bytes]]:
    """On the node Ray chose: the case in an isolated worker, as a local case runs. Returns the
    record (naming this node, with its package versions) and the heatmap files it wrote
    {path relative to the run folder: bytes}, which the submitter stores."""
    from lsbench.running.environment import machine_env
    from lsbench.running.runner import run_case_isolated

    node_id, ip = _this_node()
    env = dict(env, **machine_env())
    with tempfile.TemporaryDirectory(prefix="lsbench-case-") as tmp:
        heatmap_dir = str(Path(tmp) / "heatmaps") if heatmaps else None
        t0 = time.perf_counter()
        rec = run_case_isolated(case, settings, env, heatmap_dir, expected_by_node.get(node_id),
                                CaseData(scene, rays, truth))
        rec["wall_seconds"] = time.perf_counter() - t0
        files = {p.relative_to(tmp).as_posix(): p.read_bytes() for p in Path(tmp).rglob("*") if p.is_file()}
    rec["node"] = {"host": socket.gethostname(), "ip": ip, "id": node_id}
    return rec, files


# --- the submitting side -----------------------------------------------------------------------


class Cluster:
    """A connection to a Ray cluster for one run: `with Cluster(address) as cluster:` connects,
    probes the nodes, and offers what commands/run.py needs: uses_gpu, devices, describe, plan
    and run_cases (runner.run_scenario's `cases`). address as ray.init takes it: "auto",
    "HOST:PORT", "ray://HOST:PORT", or "local" (a throw-away Ray on this machine, for testing)."""

    def __init__(self, address: str, resources: dict[str, float] | None = None, retries: int = 2, log=print):
        self.address = address
        self.resources = dict(resources or {})
        self.retries = retries
        self.log = log
        self.nodes: list[Node] = []
        self._placements: dict[str, Placement] = {}
        self._data: dict[tuple, tuple] = {}  # input_id -> (scene ref, rays ref)
        self._truth: dict[tuple, object] = {}  # input_id -> ground-truth ref, made on first use

    def __enter__(self) -> "Cluster":
        _check_reachable(self.address)
        ray = _ray()
        # a throw-away local Ray runs one case at a time, as a local run does (docs/cluster.md)
        kwargs = {"include_dashboard": False, "num_cpus": CASE_CPUS} if self.address == "local" else {}
        try:
            ray.init(address=self.address, namespace="lsbench", log_to_driver=False, logging_level="warning",
                     **kwargs)
        except Exception as exc:  # Ray raises ConnectionError, ValueError, RuntimeError, ...
            hint = ""
            if not os.environ.get("RAY_AUTH_MODE") and _auth_token_at_hand():
                # `ray start --head` (2.60) asks for a token, which a driver given HOST:PORT sends
                # only in token mode; without it Ray retries for a minute and gives up like this.
                # Not set here: token mode against a cluster without authentication loses the
                # objects a node fetches from this driver (both seen on one machine).
                hint = "; if the cluster uses token authentication (ray start --head does), set RAY_AUTH_MODE=token"
            raise ClusterError(f"--cluster {self.address}: cannot connect to Ray "
                               f"({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}){hint}") from None
        try:
            self.nodes = self._probe_nodes()
        except BaseException:
            ray.shutdown()
            raise
        return self

    def __exit__(self, *exc) -> None:
        _ray().shutdown()

    # -- the nodes

    def _probe_nodes(self) -> list[Node]:
        from lsbench import backends
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        ray = _ray()
        mine = code_fingerprint()
        nodes = [Node(n["NodeID"], n.get("NodeManagerHostname") or n["NodeManagerAddress"], n["NodeManagerAddress"],
                      dict(n.get("Resources") or {})) for n in ray.nodes() if n.get("Alive")]
        probe = ray.remote(max_calls=1)(_probe)  # the worker exits after it: its device contexts go
        asked = {}
        for node in nodes:
            if node.resources.get("CPU", 0) < CASE_CPUS:
                node.unusable = "offers no CPU to run cases (it was started with --num-cpus 0)"
                continue
            asked[probe.options(num_cpus=0, max_retries=0,
                                scheduling_strategy=NodeAffinitySchedulingStrategy(node.id, soft=False)
                                ).remote(list(backends.BACKENDS))] = node
        ready, _ = ray.wait(list(asked), num_returns=len(asked), timeout=PROBE_SECONDS) if asked else ([], [])
        for ref, node in asked.items():
            if ref not in ready:
                node.unusable = f"did not answer the probe within {PROBE_SECONDS} s"
                ray.cancel(ref, force=True)
                continue
            try:
                found = ray.get(ref)
            except ray.exceptions.RayError as exc:
                node.unusable = f"probe failed ({_error_text(exc)})"
                continue
            node.host, node.devices, node.gpu, node.machine = (found["host"], found["devices"], found["gpu"],
                                                               found["machine"])
            if found["fingerprint"] != mine:
                node.unusable = (f"runs other lsbench code (files {found['fingerprint']}, "
                                 f"this run's {mine}): install the same version there")
        for node in nodes:
            opened = ", ".join(f"{b}={d.get('device')}" for b, d in sorted(node.devices.items()) if d.get("device"))
            self.log(f"cluster node {node.host} ({node.ip}, node {node.id[:12]}): "
                     + (f"not used: {node.unusable}" if node.unusable else opened or "opens no backend"))
        self._placements = {b: place(b, nodes, self.resources) for b in backends.BACKENDS}
        return nodes

    def uses_gpu(self, backend_names) -> bool:
        """True when any of the backends' cases run on GPUs (the scenario's gpu_width/height)."""
        return any(n.gpu.get(b) for b in backend_names for n in self._placements[b].nodes)

    def devices(self, backend_names) -> dict[str, dict]:
        """run.json's devices: per backend the device of the nodes that run its cases, or, when
        they differ, each of them (every record names its own)."""
        out = {}
        for b in sorted(set(backend_names)):
            p = self._placements[b]
            seen = [n.devices[b] for n in p.nodes]
            if not seen:
                out[b] = {"device": None, "error": p.none_because}
            elif all(d == seen[0] for d in seen):
                out[b] = dict(seen[0])
            else:
                out[b] = {"device": None, "several": [dict(d, node=n.id) for n, d in zip(p.nodes, seen)]}
        return out

    def describe(self) -> dict:
        return {"address": self.address, "resources": self.resources, "retries": self.retries,
                "nodes": [n.describe() for n in self.nodes]}

    # -- the cases

    def plan(self, scenario: Scenario, env: dict) -> list[CasePlan]:
        """runner.plan_cases for the cluster: the inputs are made here once (bad files fail the
        run now) and put into the object store; a case's expected fields are those of each node
        that may run it (its devices and package versions)."""
        ray = _ray()
        described, scene_refs = {}, {}
        for rid, scene, rays in scenario_inputs(scenario):
            described[rid] = case_inputs(scene, rays)
            if scene.content_hash not in scene_refs:  # one copy of each scene, however many ray sets
                scene_refs[scene.content_hash] = ray.put(scene)
            self._data[rid] = (scene_refs[scene.content_hash], ray.put(rays))
        settings = result_settings(scenario.settings)
        plans = []
        for c in scenario.cases:
            p = self._placements[c.backend]
            per_node = [expected_fields(described[input_id(c)], dict(env, **n.machine), settings, n.devices[c.backend])
                        for n in p.nodes] or [expected_fields(described[input_id(c)], env, settings, {})]
            plans.append(CasePlan(c, per_node[0], tuple(per_node[1:])))
        return plans

    def _expected_by_node(self, plan: CasePlan) -> dict[str, dict]:
        nodes = self._placements[plan.case.backend].nodes
        return {n.id: e for n, e in zip(nodes, (plan.expected, *plan.alternatives))}

    def run_cases(self, todo, total: int, settings: RunSettings, env: dict, heatmap_dir: str | None, log):
        """runner.run_scenario's `cases`: submit every case of `todo` as a Ray task, then yield
        (index, plan, record) as each finishes, in the order they finish. Heatmaps a node wrote
        are stored under the run folder here. Leaving early (Ctrl-C, an error) cancels the rest."""
        ray = _ray()
        run_case = ray.remote(_run_case)
        truth_task = ray.remote(_ground_truth)
        pending: dict = {}
        try:
            for i, plan, why in todo:
                case, placement = plan.case, self._placements[plan.case.backend]
                if not placement.nodes:
                    yield i, plan, failed_record(case, settings, placement.none_because, env, plan.expected)
                    continue
                rid = input_id(case)
                scene_ref, rays_ref = self._data[rid]
                if rid not in self._truth:
                    usable = ",".join(n.id for n in self.nodes if n.unusable is None)
                    self._truth[rid] = truth_task.options(
                        label_selector={NODE_ID_LABEL: f"in({usable})"}, max_retries=self.retries,
                        retry_exceptions=False).remote(scene_ref, rays_ref)
                ref = run_case.options(**placement.options(self.resources, self.retries)).remote(
                    case, settings, env, self._expected_by_node(plan), heatmap_dir is not None,
                    scene_ref, rays_ref, self._truth[rid])
                pending[ref] = (i, plan)
                log(f"[{i}/{total}] {case.key}: submitted" + ("" if why == "new" else f" ({why})"))
            while pending:
                [ref], _ = ray.wait(list(pending), num_returns=1)
                i, plan = pending.pop(ref)
                try:
                    rec, files = ray.get(ref)
                except ray.exceptions.RayError as exc:
                    rec = self._lost(plan, settings, env, exc)
                else:
                    for rel, data in files.items():
                        target = Path(heatmap_dir).parent / rel
                        target.parent.mkdir(parents=True, exist_ok=True)
                        target.write_bytes(data)
                yield i, plan, rec
        finally:
            for ref in pending:
                ray.cancel(ref, force=True)

    def _lost(self, plan: CasePlan, settings: RunSettings, env: dict, exc) -> dict:
        """The failed record of a case whose task ended without a record: its node died on the
        last attempt (named, from Ray's message or the one node that could run it), or the task
        or an input of it (the ground truth) raised."""
        ray = _ray()
        nodes = self._placements[plan.case.backend].nodes
        by_id = {n.id: n for n in nodes}
        if isinstance(exc, (ray.exceptions.NodeDiedError, ray.exceptions.TaskUnschedulableError,
                            ray.exceptions.WorkerCrashedError, ray.exceptions.ObjectLostError)):
            named = re.search(r"node ID: ([0-9a-f]+)", str(exc))
            node = by_id.get(named.group(1)) if named else (nodes[0] if len(nodes) == 1 else None)
            where = f"node {node.host} ({node.ip}, node {node.id[:12]})" if node else "its node"
            attempts = self.retries + 1
            reason = (f"lost with {where} while running ({type(exc).__name__}; "
                      f"{attempts} attempt{'s' if attempts > 1 else ''}"
                      + (", no other node opens its backend" if len(nodes) == 1 else "") + ")")
            expected = self._expected_by_node(plan).get(node.id, plan.expected) if node else plan.expected
            rec = failed_record(plan.case, settings, reason, env, expected)
            rec["node"] = node.name if node else None
            return rec
        return failed_record(plan.case, settings, _error_text(exc), env, plan.expected)


def _auth_token_at_hand() -> bool:
    """Whether Ray would find a cluster token here: RAY_AUTH_TOKEN, RAY_AUTH_TOKEN_PATH, or the
    file `ray start --head` (and `--cluster local`) writes."""
    return bool(os.environ.get("RAY_AUTH_TOKEN") or os.environ.get("RAY_AUTH_TOKEN_PATH")
                or (Path.home() / ".ray" / "auth_token").is_file())


def _check_reachable(address: str) -> None:
    """ClusterError at once when nothing listens at an explicit HOST:PORT: ray.init (2.60) would
    retry for many minutes, deaf to SIGTERM. `auto` and `local` Ray resolves on this machine."""
    if address in ("auto", "local"):
        return
    host, _, port = address.removeprefix("ray://").rpartition(":")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=CONNECT_SECONDS).close()
    except OSError as exc:
        raise ClusterError(f"--cluster {address}: nothing answers there ({exc.strerror or exc}); "
                           "start the head with `ray start --head` (docs/cluster.md)") from None


def _error_text(exc) -> str:
    """One line for a Ray error: the exception a task raised (as a local case would word it), or
    Ray's own."""
    cause = getattr(exc, "cause", None) or exc
    text = str(cause).strip().splitlines()
    return f"{type(cause).__name__}: {text[0] if text else ''}"[:500]
