"""A library batch's Ray plumbing: an embedded Ray or a cluster joined (`start_ray`), what one training task asks of
a node (`task_resources`), and tasks run to their ends with progress, retries of dead workers and cancel
(`run_tasks`)."""
from __future__ import annotations

import time
from typing import Callable

from ..protocol import events as wire
from ..protocol.events import EventSink

#: Ray retries a task whose worker died this many times (an exception inside a task is a result, not retried).
MAX_RETRIES = 2


def task_resources(triangles: int, cluster: dict) -> dict:
    """Ray resources of one training task: 1 CPU below 300k triangles, 2 above (at most what one node has), memory
    ~1 GB + 3 KB per triangle (the Embree scene, the labels, the model), a GPU when the cluster has one."""
    max_cpus = max(1, int(cluster.get("max_node_cpus", 1)))
    cpus = min(max_cpus, 1 if triangles < 300_000 else 2)
    memory = int(1e9 + 3e3 * triangles)
    memory = min(memory, int(cluster.get("max_node_memory", memory)))
    res = {"num_cpus": cpus, "memory": memory}
    if cluster.get("GPU", 0) >= 1:
        res["num_gpus"] = 1
    return res


def require_ray():
    """The ray module, or a clear ValueError naming the pinned version to install (exit code 2, not a crash)."""
    try:
        import ray
    except ImportError:
        raise ValueError("nbvh batch runs on Ray, which is not installed in this Python: "
                         "pip install ray==2.60.0 (or rerun the add-on's Install Dependencies)") from None
    return ray


def start_ray(address: str | None, num_cpus: int | None) -> bool:
    """Connect to `address` or start an embedded Ray; True when this call started it (and must shut it down)."""
    ray = require_ray()

    if ray.is_initialized():
        return False
    kw = dict(include_dashboard=False, log_to_driver=False, configure_logging=False)
    if address:
        ray.init(address=address, **kw)
    else:
        ray.init(num_cpus=num_cpus, **kw)
    return True


def cluster_info() -> dict:
    """The cluster's totals (CPU, GPU, memory) and the largest node's CPUs and memory (a task must fit one node)."""
    import ray

    total = ray.cluster_resources()
    nodes = [n for n in ray.nodes() if n.get("Alive")]
    res = [n.get("Resources", {}) for n in nodes]
    return {"CPU": total.get("CPU", 1), "GPU": total.get("GPU", 0), "nodes": len(nodes),
            "max_node_cpus": max((r.get("CPU", 0) for r in res), default=1),
            "max_node_memory": max((r.get("memory", 0) for r in res), default=0) or int(4e9)}


def run_tasks(remote, jobs: list[tuple[str, tuple, dict]], phase: str, on_result, events: EventSink,
               should_cancel: Callable[[], bool]) -> None:
    """Submit `jobs` [(row name, args, ray options)] in order; call on_result(name, result dict) as each ends (a
    task whose worker died more than MAX_RETRIES times ends as a failure); progress events with an ETA; raises
    process.Cancelled (after cancelling what is left) when should_cancel() turns true."""
    import ray

    from ..protocol.process import Cancelled

    pending = {remote.options(max_retries=MAX_RETRIES, **opts).remote(*args): name for name, args, opts in jobs}
    total, done, t0 = len(jobs), 0, time.perf_counter()
    while pending:
        if should_cancel():
            for ref in pending:
                ray.cancel(ref, force=True)
            raise Cancelled(f"cancelled in the {phase} phase with {total - done} of {total} assets left")
        ready, _ = ray.wait(list(pending), num_returns=1, timeout=0.5)
        for ref in ready:
            name = pending.pop(ref)
            try:
                result = ray.get(ref)
            except ray.exceptions.RayError as exc:  # the worker died on every try, or the task was lost
                result = {"name": name, "status": "failed", "error": f"{type(exc).__name__}: {str(exc)[:300]}"}
            done += 1
            on_result(name, result)
        elapsed = time.perf_counter() - t0
        eta = elapsed / done * (total - done) if done else None
        events(wire.progress(phase=phase, done=done, total=total, fraction=round(done / total, 4) if total else 1.0,
                             elapsed_s=round(elapsed, 1), eta_s=None if eta is None else round(eta, 1)))
