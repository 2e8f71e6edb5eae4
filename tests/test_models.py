"""m360.models: registry, cache, download and verification.

Downloads go to a local HTTP server on 127.0.0.1 (a thread that serves at most a few dozen
requests and shuts itself down after 30 s) serving a tiny ONNX file made in the test; no test
touches the internet. Real weights are only exercised when M360_MODEL_DIR points at them.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import re
from pathlib import Path

import m360
import numpy as np
import onnx_graphs as g
import pytest
from local_http import LocalServer
from m360 import models
from m360.errors import ModelError
from m360.estimators import OUTPUT_KINDS, OnnxEstimator, load_estimator


@pytest.fixture(autouse=True)
def isolated_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    home = tmp_path / "m360home"
    monkeypatch.setenv("M360_HOME", str(home))
    monkeypatch.setenv("NO_PROXY", "127.0.0.1,localhost")
    for var in ("M360_OFFLINE", "M360_MODEL_DIR", "M360_ALLOW_UNVERIFIED"):
        monkeypatch.delenv(var, raising=False)
    models._clear_verified()
    return home / "models"


@pytest.fixture
def tiny(tmp_path: Path) -> bytes:
    """Bytes of a tiny ONNX depth model (output = 2·mean(RGB) + 1)."""
    return g.affine_of_mean(tmp_path / "made" / "tiny.onnx", 2.0, 1.0).read_bytes()


def register(
    monkeypatch: pytest.MonkeyPatch, url: str, sha256: str | None, size: int
) -> models.ModelEntry:
    entry = dataclasses.replace(
        models.get("midas-v21-small"),
        name="tiny",
        filename="tiny.onnx",
        urls=(url,),
        sha256=sha256,
        sha256_source="made in the test",
        size_bytes=size,
        input_size=(16, 16),
        multiple_of=1,
    )
    monkeypatch.setitem(models.REGISTRY, "tiny", entry)
    return entry


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir()) if folder.exists() else []


# ------------------------------------------------------------------ happy path


def test_fetch_downloads_verifies_and_caches(
    server: LocalServer, tiny: bytes, monkeypatch: pytest.MonkeyPatch, isolated_cache: Path
) -> None:
    server.routes["/tiny.onnx"] = (200, tiny, "ok")
    register(monkeypatch, server.url("/tiny.onnx"), sha(tiny), len(tiny))
    assert not models.is_cached("tiny")
    path = models.fetch("tiny", progress=False)
    assert path == isolated_cache / "tiny.onnx" and path.read_bytes() == tiny
    assert leftovers(isolated_cache) == ["tiny.onnx"]  # no temporary files left behind
    assert models.is_cached("tiny")
    # Second use: no network, the hash check is remembered for this process.
    models.ensure("tiny")
    assert server.requests == ["/tiny.onnx"]
    est = load_estimator("tiny")
    assert isinstance(est, OnnxEstimator) and est.sha256 == sha(tiny)
    out = est.predict(np.full((1, 16, 16, 3), 255, np.uint8))
    # The graph does not normalise: m360 applies the entry's ImageNet normalisation.
    fed = (1.0 - np.array(models.IMAGENET_MEAN)) / np.array(models.IMAGENET_STD)
    assert est.normalization_source == "m360"
    np.testing.assert_allclose(out, 2 * fed.mean() + 1, rtol=1e-5)


def test_manual_copy_in_model_dir_is_found_and_verified(
    tmp_path: Path, tiny: bytes, monkeypatch: pytest.MonkeyPatch
) -> None:
    manual = tmp_path / "manual"
    manual.mkdir()
    (manual / "tiny.onnx").write_bytes(tiny)
    monkeypatch.setenv("M360_MODEL_DIR", str(manual))
    monkeypatch.setenv("M360_OFFLINE", "1")
    register(monkeypatch, "http://127.0.0.1:9/never", sha(tiny), len(tiny))
    assert models.ensure("tiny") == manual / "tiny.onnx"


def test_cache_dir_follows_m360_home_else_the_platform_cache(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    assert models.cache_dir() == tmp_path / "m360home" / "models"
    monkeypatch.delenv("M360_HOME")
    import platformdirs

    assert models.cache_dir() == Path(platformdirs.user_cache_dir("m360")) / "models"


# ------------------------------------------------------------------ failures, one message each


def test_hash_mismatch_on_download_saves_nothing(
    server: LocalServer, tiny: bytes, monkeypatch: pytest.MonkeyPatch, isolated_cache: Path
) -> None:
    server.routes["/tiny.onnx"] = (200, tiny + b"tampered", "ok")
    register(monkeypatch, server.url("/tiny.onnx"), sha(tiny), len(tiny))
    with pytest.raises(ModelError) as info:
        models.fetch("tiny", progress=False)
    msg = str(info.value)
    assert "fails its hash check" in msg and sha(tiny) in msg and "Nothing was saved" in msg
    assert str(isolated_cache / "tiny.onnx") in msg  # where to put a manual copy
    assert leftovers(isolated_cache) == []


def test_hash_mismatch_of_a_cached_file(
    tiny: bytes, monkeypatch: pytest.MonkeyPatch, isolated_cache: Path
) -> None:
    other = g.affine_of_mean(isolated_cache / "tiny.onnx", 5.0, 0.0).read_bytes()
    register(monkeypatch, "http://127.0.0.1:9/x", sha(tiny), len(other))
    with pytest.raises(ModelError) as info:
        models.ensure("tiny")
    msg = str(info.value)
    assert re.search(rf"tiny.onnx fails its hash check: expected sha256 {sha(tiny)}, got", msg)
    assert sha(other) in msg and "m360 models fetch tiny" in msg and "truncated" not in msg


def test_truncated_download_is_refused(
    server: LocalServer, tiny: bytes, monkeypatch: pytest.MonkeyPatch, isolated_cache: Path
) -> None:
    server.routes["/tiny.onnx"] = (200, tiny, "truncate")
    register(monkeypatch, server.url("/tiny.onnx"), sha(tiny), len(tiny))
    with pytest.raises(ModelError, match=r"could not download model 'tiny' \(expected sha256"):
        models.fetch("tiny", progress=False)
    assert leftovers(isolated_cache) == []


def test_truncated_cached_file_is_refused(
    tiny: bytes, monkeypatch: pytest.MonkeyPatch, isolated_cache: Path
) -> None:
    isolated_cache.mkdir(parents=True)
    (isolated_cache / "tiny.onnx").write_bytes(tiny[: len(tiny) // 2])
    register(monkeypatch, "http://127.0.0.1:9/x", sha(tiny), len(tiny))
    with pytest.raises(ModelError, match=r"fails its hash check \(it is \d+ bytes.*truncated\?\)"):
        models.ensure("tiny")


def test_html_error_page_saved_as_onnx(
    server: LocalServer, tiny: bytes, monkeypatch: pytest.MonkeyPatch, isolated_cache: Path
) -> None:
    page = b"<!DOCTYPE html><html><body>Rate limit exceeded</body></html>"
    server.routes["/tiny.onnx"] = (200, page, "ok")
    register(monkeypatch, server.url("/tiny.onnx"), sha(tiny), len(tiny))
    with pytest.raises(ModelError, match="fails its hash check"):
        models.fetch("tiny", progress=False)
    assert leftovers(isolated_cache) == []
    # The same page already in the cache (e.g. saved by a browser): named as HTML.
    isolated_cache.mkdir(parents=True, exist_ok=True)
    (isolated_cache / "tiny.onnx").write_bytes(page)
    with pytest.raises(ModelError, match=r"fails its hash check; it is an HTML/XML page"):
        models.ensure("tiny")


def test_offline_and_missing_never_touches_the_network(
    server: LocalServer, tiny: bytes, monkeypatch: pytest.MonkeyPatch, isolated_cache: Path
) -> None:
    server.routes["/tiny.onnx"] = (200, tiny, "ok")
    register(monkeypatch, server.url("/tiny.onnx"), sha(tiny), len(tiny))
    monkeypatch.setenv("M360_OFFLINE", "1")
    with pytest.raises(ModelError) as info:
        models.ensure("tiny")
    msg = str(info.value)
    assert "M360_OFFLINE=1 forbids downloading" in msg and sha(tiny) in msg
    assert str(isolated_cache / "tiny.onnx") in msg and server.url("/tiny.onnx") in msg
    assert server.requests == []


def test_no_network_names_the_url_and_where_to_put_the_file(
    tiny: bytes, monkeypatch: pytest.MonkeyPatch, isolated_cache: Path
) -> None:
    closed = LocalServer()  # bound, never started, then closed: connections are refused
    url = closed.url("/tiny.onnx")
    closed.httpd.server_close()
    register(monkeypatch, url, sha(tiny), len(tiny))
    with pytest.raises(ModelError) as info:
        models.fetch("tiny", progress=False)
    msg = str(info.value)
    assert "could not download model 'tiny'" in msg and url in msg
    assert f"put it at {isolated_cache / 'tiny.onnx'}" in msg


def test_unpublished_hash_is_refused_unless_allowed(
    tiny: bytes, monkeypatch: pytest.MonkeyPatch, isolated_cache: Path
) -> None:
    g.affine_of_mean(isolated_cache / "tiny.onnx", 2.0, 1.0)
    register(monkeypatch, "http://127.0.0.1:9/x", None, len(tiny))
    with pytest.raises(ModelError, match=rf"no published sha256.*actual sha256 is {sha(tiny)}"):
        models.ensure("tiny")
    monkeypatch.setenv("M360_ALLOW_UNVERIFIED", "1")
    with pytest.warns(UserWarning, match=rf"WITHOUT hash verification.*{sha(tiny)}"):
        assert models.ensure("tiny") == isolated_cache / "tiny.onnx"


def test_unknown_name() -> None:
    with pytest.raises(ModelError, match="unknown model 'midas': registered models are"):
        models.get("midas")


# ------------------------------------------------------------------ the registry itself


def test_registry_entries_are_complete() -> None:
    assert models.DEFAULT_MODEL in models.REGISTRY
    assert models.get(models.DEFAULT_MODEL).sha256 is not None
    required = {"midas-v21-small", "midas-v21-large", "dpt-hybrid", "dpt-large"}
    assert required | {"depth-anything-v2-small"} <= set(models.names())
    for entry in models.REGISTRY.values():
        assert entry.urls and all(u.startswith("https://") for u in entry.urls), entry.name
        assert entry.sha256 is None or re.fullmatch(r"[0-9a-f]{64}", entry.sha256), entry.name
        assert entry.sha256_source and entry.licence and entry.description
        assert entry.output_kind in OUTPUT_KINDS
        assert entry.resize in ("upper_bound", "lower_bound") and entry.multiple_of in (14, 32)
    da = models.get("depth-anything-v2-small")
    assert da.input_size == (518, 518) and da.multiple_of == 14 and "Apache-2.0" in da.licence
    assert "CC-BY-NC" in da.licence  # Base/Large are non-commercial
    assert models.get("midas-v21-small").input_size == (256, 256)
    assert all(models.get(n).input_size == (384, 384) for n in required - {"midas-v21-small"})


def test_list_models_reports_cached_state(
    tiny: bytes, monkeypatch: pytest.MonkeyPatch, isolated_cache: Path
) -> None:
    register(monkeypatch, "http://127.0.0.1:9/x", sha(tiny), len(tiny))
    g.affine_of_mean(isolated_cache / "tiny.onnx", 2.0, 1.0)
    rows = {r["name"]: r for r in models.list_models()}
    assert rows["tiny"]["cached"] is True and rows["midas-v21-small"]["cached"] is False
    assert rows["midas-v21-small"]["licence"] == "MIT"


# ------------------------------------------------------------------ real weights (opt-in)

#: Read before the autouse fixture clears M360_MODEL_DIR for the other tests.
REAL_MODEL_DIR = os.environ.get("M360_MODEL_DIR")


@pytest.mark.parametrize("name", list(models.REGISTRY))
def test_real_model_when_available(name: str, monkeypatch: pytest.MonkeyPatch) -> None:
    entry = models.get(name)
    if not REAL_MODEL_DIR or not (Path(REAL_MODEL_DIR) / entry.filename).is_file():
        pytest.skip(f"real weights: set M360_MODEL_DIR to a folder holding {entry.filename}")
    monkeypatch.setenv("M360_MODEL_DIR", REAL_MODEL_DIR)
    monkeypatch.setenv("M360_OFFLINE", "1")
    est = load_estimator(name, threads=2)
    rgb, depth = m360.synthetic.render(m360.synthetic.room(0), 512)
    res = m360.estimate(rgb, est, align="none", blend="mean")
    assert np.isfinite(res.disparity).mean() > 0.99
    # A real network ranks near and far correctly on a rendered room, even unaligned.
    valid = np.isfinite(res.disparity)
    corr = np.corrcoef(res.disparity[valid], 1.0 / depth[valid])[0, 1]
    assert corr > 0.5, corr


# ------------------------------------------------------------------ what is loaded is verified


def test_a_registry_default_size_is_not_a_request(
    monkeypatch: pytest.MonkeyPatch, isolated_cache: Path
) -> None:
    """The registry's input_size is a default: a file with its own fixed size runs at it, and
    only a size the user asks for is checked against the file."""
    data = g.affine_of_mean(isolated_cache / "tiny.onnx", input_shape=(1, 3, 24, 24)).read_bytes()
    register(monkeypatch, "http://127.0.0.1:9/x", sha(data), len(data))  # input_size (16, 16)
    est = load_estimator("tiny")
    assert est.network_size((40, 40)) == (24, 24)
    with pytest.raises(m360.InputError, match=r"takes a fixed 24x24 input; omit input_size"):
        load_estimator("tiny", input_size=(16, 16))


def _swap(path: Path, data: bytes) -> None:
    """Replace ``path``'s bytes, keeping its size and mtime (what a stat cache looks at)."""
    before = path.stat()
    assert len(data) == before.st_size
    path.write_bytes(data)
    os.utime(path, ns=(before.st_atime_ns, before.st_mtime_ns))


def test_a_model_swapped_between_the_check_and_the_load_is_refused(
    tiny: bytes, monkeypatch: pytest.MonkeyPatch, isolated_cache: Path
) -> None:
    """The file is replaced by another valid ONNX model right after models.ensure checked it:
    the bytes loaded are hashed, so the swap is a ModelError, never an unverified load."""
    path = isolated_cache / "tiny.onnx"
    path.parent.mkdir(parents=True)
    path.write_bytes(tiny)
    other = g.affine_of_mean(isolated_cache.parent / "other.onnx", 5.0, 0.0).read_bytes()
    register(monkeypatch, "http://127.0.0.1:9/x", sha(tiny), len(tiny))
    real_ensure = models.ensure

    def ensure_then_swap(name: str, **kwargs: object) -> Path:
        checked = real_ensure(name)
        _swap(checked, other)  # the window between the check and the load
        return checked

    monkeypatch.setattr(models, "ensure", ensure_then_swap)
    with pytest.raises(ModelError, match=rf"expected sha256 {sha(tiny)}, the bytes read have "
                       rf"{sha(other)} \(was the file replaced\?\)"):  # fmt: skip
        load_estimator("tiny")


def test_a_stat_cache_cannot_be_fooled_by_a_same_size_same_mtime_swap(
    tiny: bytes, monkeypatch: pytest.MonkeyPatch, isolated_cache: Path
) -> None:
    """After a first verified load, the file changes with its size and mtime kept: the next
    load hashes the bytes again and refuses them, and a session is never reused for them."""
    path = isolated_cache / "tiny.onnx"
    path.parent.mkdir(parents=True)
    path.write_bytes(tiny)
    register(monkeypatch, "http://127.0.0.1:9/x", sha(tiny), len(tiny))
    first = load_estimator("tiny")
    assert first.sha256 == sha(tiny)
    other = g.affine_of_mean(isolated_cache.parent / "other.onnx", 5.0, 0.0).read_bytes()
    _swap(path, other)
    with pytest.raises(ModelError, match="fails its hash check"):
        load_estimator("tiny")
    # A file given by path (no expected hash) reports the hash of the bytes it runs.
    assert OnnxEstimator(path).sha256 == sha(other)
    pred = OnnxEstimator(path, mean=(0, 0, 0), std=(1, 1, 1)).predict(
        np.full((1, 8, 8, 3), 51, np.uint8)
    )
    np.testing.assert_allclose(pred, 5.0 * 0.2, rtol=1e-6)  # the new graph ran, not a cached one


# ------------------------------------------------------------------ a user's own model


def test_a_run_time_size_failure_is_a_model_error_that_says_what_to_do(tmp_path: Path) -> None:
    from check_graphs import unet

    path = unet(tmp_path / "unet.onnx")
    tangents = np.full((1, 346, 400, 3), 128, np.uint8)  # 332x384 at the default 384 px
    est = load_estimator(path)
    with pytest.raises(ModelError) as caught:
        est.predict(tangents)
    text = str(caught.value)
    assert "ONNX Runtime failed on a 332x384 input (Add node: " in text
    assert text.endswith(
        "this model needs input sizes that are multiples of 32: pass --multiple-of 32 "
        "(or multiple_of=32)"
    )
    assert "onnxruntime_src" not in text  # no source paths of ONNX Runtime's build
    # With the option the message names, it runs.
    fixed = load_estimator(path, multiple_of=32)
    assert fixed.network_size((346, 400)) == (320, 384)
    assert np.isfinite(fixed.predict(tangents)).all()


def test_normalize_and_resize_reach_the_network_from_the_api_and_the_cli(
    tmp_path: Path,
) -> None:
    from m360._keywords import from_args
    from m360.cli import build_parser
    from m360.estimators import ModelKeywords, ModelOptions
    from m360.estimators.onnx_file import IMAGENET_MEAN, IMAGENET_STD

    path = g.channel(tmp_path / "c0.onnx", 0)  # output = what the network gets in channel 0
    grey = np.full((1, 8, 8, 3), 51, np.uint8)  # 0.2 in [0, 1]
    expected = {
        "imagenet": (0.2 - IMAGENET_MEAN[0]) / IMAGENET_STD[0],
        "unit": 0.2,
        "none": 51.0,
    }
    for name, value in expected.items():
        est = load_estimator(path, normalize=name, input_size=(8, 8))
        assert est.normalize == name and est.normalization.explicit
        assert est.predict(grey)[0, 0, 0] == pytest.approx(value, rel=1e-5)
    # exact: the input size as given; keep-aspect fits inside it; cover covers it.
    sizes = {"exact": (224, 224), "keep-aspect": (193, 224), "cover": (224, 259)}
    for policy, size in sizes.items():
        est = load_estimator(path, input_size=(224, 224), resize=policy)
        assert est.network_size((346, 400)) == size and est.resize_policy == policy
    assert load_estimator(path, input_size=(224, 224), resize="exact", multiple_of=32).network_size(
        (346, 400)
    ) == (224, 224)
    # The same from the flags of m360 run and m360 models check.
    sub = next(a for a in build_parser()._actions if hasattr(a, "choices") and a.choices).choices
    argv = ["--normalize", "unit", "--resize", "exact", "--multiple-of", "32"]
    for command, head in (("run", ["x.jpg", "-o", "o"]), ("models", ["check", "m.onnx"])):
        parser = sub[command]
        args = parser.parse_args([*head, *argv])
        got = from_args(args, ModelKeywords)
        assert got == {"normalize": "unit", "resize": "exact", "multiple_of": 32}
        assert ModelOptions(**got) == ModelOptions(normalize="unit", resize="exact", multiple_of=32)
    with pytest.raises(m360.InputError, match="not both"):
        ModelOptions(normalize="unit", std=(1, 1, 1))
    with pytest.raises(m360.InputError, match="normalize='unitt'"):
        ModelOptions(normalize="unitt")
    with pytest.raises(m360.InputError, match="resize='fit'"):
        ModelOptions(resize="fit")


def test_normalize_and_resize_are_in_the_sidecar_and_the_fingerprint(tmp_path: Path) -> None:
    from m360.batch.runner import fingerprint

    path = g.affine_of_mean(tmp_path / "dyn.onnx", 2.0, 1.0)
    rgb, _ = m360.synthetic.render(m360.synthetic.room(1), 128)
    options = m360.StitchOptions(align="none")
    prints = {}
    for name, keywords in {
        "default": {},
        "unit": {"normalize": "unit"},
        "exact": {"resize": "exact", "input_size": (64, 64)},
    }.items():
        est = load_estimator(path, **keywords)  # type: ignore[arg-type]
        prints[name] = fingerprint(est, options, ["npy"], preview=False, fix_aspect=False)
        model = m360.estimate(rgb, est, options=options).model
        assert model["normalize"] == keywords.get("normalize")
        assert model["resize"] == keywords.get("resize", "keep-aspect")
        assert model["multiple_of"] == 1
    assert prints["default"] != prints["unit"] != prints["exact"] != prints["default"]
    assert prints["unit"]["model"]["std"] == [1.0, 1.0, 1.0]
    assert prints["exact"]["model"]["resize"] == "exact"


def test_a_batch_whose_model_fails_on_the_first_image_stops_with_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import cv2
    from check_graphs import unet

    folder = tmp_path / "in"
    folder.mkdir()
    rgb, _ = m360.synthetic.render(m360.synthetic.room(2), 256)
    for k in range(4):
        cv2.imwrite(str(folder / f"p{k}.png"), rgb[..., ::-1])
    model = unet(tmp_path / "unet.onnx", levels=6)  # 64: fails at the default size here
    seen: list[m360.batch.ImageOutcome] = []
    report = m360.batch.run(
        folder, tmp_path / "out", model=str(model), progress=False, on_outcome=seen.append
    )
    assert len(seen) == 1 and len(report.outcomes) == 1  # one image tried, then it stopped
    assert report.exit_code == 2 and report.failed[0].error == "ModelError"
    assert report.model_error is not None and "multiples of 64" in report.model_error
    assert "stopped: the model failed on the first image" in report.summary()
    assert (tmp_path / "out" / "failures.jsonl").read_text().count("\n") == 1
    # The CLI says the same and exits 2; with the flag it asks for, every image is done.
    from m360.cli import main

    argv = ["run", str(folder), "-o", str(tmp_path / "cli"), "--model", str(model)]
    capsys.readouterr()
    assert main([*argv, "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("pass --multiple-of 64 (or multiple_of=64)") == 2  # the image, the summary
    assert "0 done, 0 already done, 1 failed" in err
    assert main([*argv, "--no-progress", "--multiple-of", "64", "--align", "none"]) == 0
    assert len(list((tmp_path / "cli").glob("p*.json"))) == 4


def test_a_model_error_after_a_success_fails_only_that_image(tmp_path: Path) -> None:
    import cv2

    folder = tmp_path / "in"
    folder.mkdir()
    rgb, _ = m360.synthetic.render(m360.synthetic.room(2), 256)
    for k in range(3):  # p1 is black: the estimator below fails on it only
        cv2.imwrite(str(folder / f"p{k}.png"), rgb[..., ::-1] * (k != 1))

    class FailsOnBlack:
        output_kind = "affine_disparity"

        def predict(self, tangents: np.ndarray) -> np.ndarray:
            if tangents.max() == 0:
                raise ModelError("black")
            return tangents.astype(np.float32).mean(axis=-1) / 255 + 1

    report = m360.batch.run(
        folder, tmp_path / "out", model=FailsOnBlack(), progress=False, align="none"
    )
    assert [o.status for o in report.outcomes] == ["done", "failed", "done"]
    assert report.exit_code == 1 and report.model_error is None


def test_a_pool_of_workers_stops_on_its_model_too(tmp_path: Path) -> None:
    import cv2
    from check_graphs import unet

    folder = tmp_path / "in"
    folder.mkdir()
    rgb, _ = m360.synthetic.render(m360.synthetic.room(2), 128)
    for k in range(6):
        cv2.imwrite(str(folder / f"p{k}.png"), rgb[..., ::-1])
    report = m360.batch.run(
        folder, tmp_path / "out", model=str(unet(tmp_path / "u.onnx")), progress=False, workers=2
    )
    assert report.exit_code == 2 and len(report.outcomes) == 1
    assert report.model_error is not None and "--multiple-of 32" in report.model_error
