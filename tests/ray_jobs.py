"""Ray runs the tests drive from outside, as separate processes: `python ray_jobs.py JOB ...`.

``driver PHOTOS OUT GATE``: a Ray run (the cluster in RAY_ADDRESS) with batch_helpers.Gated
(GATE's FIFOs); prints each outcome as a JSON line as it arrives, then the report's counts.

``cluster PHOTOS OUT FOLDER MODEL``: starts a simulated cluster (ray.cluster_utils.Cluster: a
head without CPUs and two worker nodes of 2 CPUs), runs the photos with ray_helpers.Faulty
(crashes and one pause), and while the network is paused at the PAUSE image removes the node
that runs it; prints the report's counts and the removed node.
"""

from __future__ import annotations

import json
import os
import sys
import threading
from pathlib import Path

import m360

HERE = Path(__file__).resolve().parent
os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(HERE), os.environ.get("PYTHONPATH")]))


def _counts(report: m360.batch.BatchReport) -> dict[str, object]:
    return {
        "done": len(report.done),
        "skipped": len(report.skipped),
        "busy": len(report.busy),
        "failed": len(report.failed),
        "exit_code": report.exit_code,
        "stages": report.stage_seconds(),
    }


def _print(line: dict[str, object]) -> None:
    print(json.dumps(line), flush=True)


def driver(photos: str, out: str, gate: str) -> None:
    import batch_helpers

    report = m360.batch.run(
        [photos],
        out,
        model=batch_helpers.Gated(gate),
        engine="ray",
        align="none",
        blend="frustum",
        progress=False,
        on_outcome=lambda o: _print({"outcome": o.status, "input": o.input}),
    )
    _print({"report": _counts(report)})


def cluster(photos: str, out: str, folder: str, model: str) -> None:
    import ray
    import ray_helpers
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 0})
    workers = [cluster.add_node(num_cpus=2) for _ in range(2)]
    ray.init(address=cluster.address, log_to_driver=False)
    removed: list[str] = []

    def remove_the_paused_node() -> None:
        with open(os.path.join(folder, "reached")) as reached:  # blocks until the pause
            node_id = reached.readline().strip()
        for node in workers:
            if node.node_id == node_id:
                cluster.remove_node(node)
                removed.append(node_id)
        with open(os.path.join(folder, "go"), "w") as go:
            go.write("g")

    os.mkfifo(os.path.join(folder, "reached"))
    os.mkfifo(os.path.join(folder, "go"))
    # Keep `go` open for reading too, so that writing it never blocks once the reader died
    # with its node.
    keep = os.open(os.path.join(folder, "go"), os.O_RDWR)
    watcher = threading.Thread(target=remove_the_paused_node, daemon=True)
    watcher.start()
    outcomes: dict[str, int] = {}

    def count(outcome: m360.batch.ImageOutcome) -> None:
        outcomes[outcome.input] = outcomes.get(outcome.input, 0) + 1

    report = m360.batch.run(
        [photos],
        out,
        model=ray_helpers.Faulty(model, folder, pause=True),
        engine="ray",
        on_outcome=count,
        **ray_helpers.OPTIONS,
    )
    if watcher.is_alive():  # never paused: let the watcher's open() return (it reads EOF)
        os.close(os.open(os.path.join(folder, "reached"), os.O_WRONLY))
    watcher.join()
    os.close(keep)
    _print(
        {
            "report": _counts(report),
            "removed": removed,
            "outcomes_per_input": sorted(set(outcomes.values())),
        }
    )
    ray.shutdown()
    cluster.shutdown()


if __name__ == "__main__":
    job, *arguments = sys.argv[1:]
    {"driver": driver, "cluster": cluster}[job](*arguments)
