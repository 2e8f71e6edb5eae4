"""Estimators, inputs and checks for the Ray engine tests; importable by Ray workers (the tests
put tests/ on their PYTHONPATH)."""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import m360
import numpy as np

#: A panorama whose brightest value is this kills its worker the first time it is seen.
CRASH_ONCE = 77
#: A panorama whose brightest value is this pauses the network once (see Faulty).
PAUSE = 99
#: The options of the Ray tests: the method's default stitching.
# A padding other than the default, so that the engines' equality covers how each stage of
# the Ray engine makes its layout.
OPTIONS: dict[str, Any] = {"progress": False, "padding": 0.5}
BAD = {
    "z_black.png": "WorkerCrashed",
    "truncated.jpg": "ReadError",
    "zero.jpg": "ReadError",
    "three_two.png": "AspectRatioError",
}


class Faulty:
    """The tiny ONNX model (loaded in the worker on first use), with faults keyed on the image.

    The key is the brightest value of the tangents. With ``crash``: an all-black panorama kills
    the worker process every time; a ``CRASH_ONCE`` one kills it the first time only
    (``folder/crashed-once`` records it). With ``pause``: the first time the network sees a
    ``PAUSE`` panorama it writes its
    Ray node id and a newline into the FIFO ``folder/reached`` and waits for a byte from the
    FIFO ``folder/go``. The name does not depend on the faults, so a faulty run and a clean one
    share their fingerprint.
    """

    output_kind = "affine_disparity"
    name = "faulty-tiny"

    def __init__(
        self, model: str, folder: str | None = None, *, crash: bool = True, pause: bool = False
    ) -> None:
        self.model, self.folder, self.crash, self.pause = model, folder, crash, pause
        self._estimator: Any = None

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_estimator": None}

    def _first_time(self, marker: str) -> bool:
        assert self.folder is not None
        try:
            os.close(os.open(os.path.join(self.folder, marker), os.O_CREAT | os.O_EXCL))
        except FileExistsError:
            return False
        return True

    def predict(self, tangents: np.ndarray) -> np.ndarray:
        brightest = int(tangents.max())
        if self.crash and brightest == 0:
            os._exit(3)
        if self.crash and brightest == CRASH_ONCE and self._first_time("crashed-once"):
            os._exit(3)
        if self.pause and brightest == PAUSE and self._first_time("paused"):
            import ray

            assert self.folder is not None
            reached = os.open(os.path.join(self.folder, "reached"), os.O_WRONLY)
            node = ray.get_runtime_context().get_node_id()
            os.write(reached, (node + "\n").encode())
            os.close(reached)
            go = os.open(os.path.join(self.folder, "go"), os.O_RDONLY)
            os.read(go, 1)
            os.close(go)
        if self._estimator is None:
            self._estimator = m360.estimators.load_estimator(
                self.model, threads=1, input_size=(64, 96)
            )
        result: np.ndarray = self._estimator.predict(tangents)
        return result


def make_photos(folder: Path, good: int = 34) -> Path:
    """``good`` rolled synthetic rooms (128x64), the room clipped at CRASH_ONCE and at PAUSE
    (also good) and the four bad inputs of BAD."""
    folder.mkdir(parents=True, exist_ok=True)
    rgb, _ = m360.synthetic.render(m360.synthetic.room(3), 128)
    assert rgb.max() > PAUSE
    for k in range(good):
        image = np.roll(rgb, 3 * k, axis=1)[:, :, ::-1]
        assert cv2.imwrite(str(folder / f"pano_{k:02d}.{'jpg' if k % 2 else 'png'}"), image)
    # Sorted, the paused image comes first and the crashing ones late: when a test removes a
    # node at the pause, no image that has already lost a worker is in flight.
    for value, name in ((PAUSE, "a_clipped_99.png"), (CRASH_ONCE, "z_clipped_77.png")):
        assert cv2.imwrite(str(folder / name), np.minimum(rgb, value)[:, :, ::-1])
    assert cv2.imwrite(str(folder / "z_black.png"), np.zeros((64, 128, 3), np.uint8))
    _, jpeg = cv2.imencode(".jpg", rgb)
    (folder / "truncated.jpg").write_bytes(jpeg.tobytes()[: len(jpeg) // 2])
    (folder / "zero.jpg").write_bytes(b"")
    assert cv2.imwrite(str(folder / "three_two.png"), rgb[:, :96])
    return folder


def failures(out: Path) -> dict[str, str]:
    """Input file name → error type, from OUT/failures.jsonl (each input at most once)."""
    lines = (out / "failures.jsonl").read_text().splitlines()
    records = [json.loads(line) for line in lines]
    names = [Path(r["input"]).name for r in records]
    assert len(names) == len(set(names)), names
    return {Path(r["input"]).name: r["error"] for r in records}


def sidecar_without_run_details(path: Path) -> dict[str, Any]:
    """A sidecar less what differs between any two runs: times and the run id."""
    meta = json.loads(path.read_text())
    meta.pop("timings_s", None)
    meta.pop("created", None)
    meta["batch"].pop("run", None)
    return dict(meta)


def assert_same_outputs(reference: Path, out: Path, skip: frozenset[str] = frozenset()) -> int:
    """Every array and preview of ``reference`` is byte-identical in ``out``, and the sidecars
    agree but for timings and run id; returns the number of images compared."""
    stems = sorted(
        p.name[: -len(".json")] for p in reference.glob("*.json") if p.name[:-5] not in skip
    )
    assert stems
    for stem in stems:
        for file in reference.glob(f"{stem}.*"):
            other = out / file.name
            if file.suffix == ".json":
                assert sidecar_without_run_details(file) == sidecar_without_run_details(other)
            else:
                assert file.read_bytes() == other.read_bytes(), file.name
    return len(stems)


def assert_clean(out: Path) -> None:
    """No temporary or lock file is left."""
    leftovers = [p.name for p in out.rglob(".*")]
    assert not leftovers, leftovers


@contextlib.contextmanager
def local_ray(num_cpus: int = 2) -> Iterator[str]:
    """A local Ray of ``num_cpus`` CPUs whose workers can import the test helpers; its address.

    "local": always a new Ray, never one a stale /tmp/ray/ray_current_cluster points at.
    """
    import ray

    saved = os.environ.get("PYTHONPATH")
    here = str(Path(__file__).resolve().parent)
    os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [here, saved]))
    ray.init(address="local", num_cpus=num_cpus, include_dashboard=False, log_to_driver=False)
    try:
        yield ray.get_runtime_context().gcs_address
    finally:
        ray.shutdown()
        if saved is None:
            os.environ.pop("PYTHONPATH", None)
        else:
            os.environ["PYTHONPATH"] = saved
