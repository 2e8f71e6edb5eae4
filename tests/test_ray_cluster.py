"""The Ray engine on a simulated multi-node cluster (ray.cluster_utils.Cluster: a head and two
worker nodes on this machine), in a separate process under a watchdog: the node running the
network is removed mid-run (while it holds an image), a worker is killed by an image once and
another image kills it every time; the run still equals the local engine's bit for bit."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import m360
import onnx_graphs as g
import pytest
import ray_helpers as h

pytest.importorskip("ray")

HERE = Path(__file__).resolve().parent


def test_a_node_lost_mid_run_costs_only_its_images_which_are_redone(tmp_path: Path) -> None:
    # Offset 3: a positive affine disparity on the dark photos too (see test_ray.py's model).
    model = str(g.affine_of_mean(tmp_path / "tiny.onnx", 1.0, 3.0))
    photos = h.make_photos(tmp_path / "photos")
    reference = tmp_path / "reference"
    m360.batch.run([photos], reference, model=h.Faulty(model, crash=False), **h.OPTIONS)
    out, faults = tmp_path / "out", tmp_path / "faults"
    faults.mkdir()
    job = [sys.executable, str(HERE / "ray_jobs.py"), "cluster", str(photos), str(out)]
    done = subprocess.run(
        [*job, str(faults), model], capture_output=True, text=True, timeout=600, check=False
    )
    assert done.returncode == 0, done.stderr[-4000:]
    # Ray writes its own messages to stdout too.
    (line,) = [x for x in done.stdout.splitlines() if x.startswith('{"report"')]
    result = json.loads(line)
    assert len(result["removed"]) == 1  # the node running the network, while it held an image
    assert result["outcomes_per_input"] == [1]  # nothing lost, nothing twice
    report = result["report"]
    assert (report["done"], report["failed"], report["exit_code"]) == (36, 4, 1)
    assert h.failures(out) == h.BAD
    assert (faults / "crashed-once").exists() and (faults / "paused").exists()
    assert h.assert_same_outputs(reference, out, skip=frozenset({"z_black"})) == 36
    h.assert_clean(out)
