"""Issue 12 §5, real weights on first contact: every known URL of a file, and normalisation read
from the graph (not from a model card).

Downloads go to the bounded local HTTP server (local_http.py); graphs are tiny ONNX files built
with the onnx package (norm_graphs.py), each one a preprocessing chain (or none) then
"output = channel c": so the output is exactly the value the network core receives there.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Sequence
from pathlib import Path

import m360
import numpy as np
import onnx
import onnx_graphs as g
import pytest
from local_http import LocalServer
from m360 import models
from m360.errors import InputError, ModelError
from m360.estimators import OnnxEstimator, _onnxgraph, load_estimator
from norm_graphs import MEAN, STD, VARIANTS, chain_then_channel, per_channel
from onnx import TensorProto, helper, numpy_helper

COLOUR = (200, 100, 30)  # one uniform RGB colour: every pixel of a channel gets one value


@pytest.fixture(autouse=True)
def isolated_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    home = tmp_path / "m360home"
    monkeypatch.setenv("M360_HOME", str(home))
    monkeypatch.setenv("NO_PROXY", "127.0.0.1,localhost")
    for var in ("M360_OFFLINE", "M360_MODEL_DIR", "M360_ALLOW_UNVERIFIED"):
        monkeypatch.delenv(var, raising=False)
    models._clear_verified()
    return home / "models"


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def tangents(shape: tuple[int, int] = (8, 8)) -> np.ndarray:
    return np.broadcast_to(np.array(COLOUR, np.uint8), (1, *shape, 3)).copy()


def imagenet(c: int) -> float:
    return float((COLOUR[c] / 255.0 - MEAN[c]) / STD[c])


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_the_network_receives_imagenet_normalised_rgb_once(tmp_path: Path, variant: str) -> None:
    steps, shape, source, input_range = VARIANTS[variant]
    for c in range(3):
        path = chain_then_channel(tmp_path / f"{variant}_{c}.onnx", c, steps, shape)
        est = OnnxEstimator(path)
        assert est.normalization_source == source
        assert est.normalization.input_range == input_range
        got = est.predict(tangents())
        # Normalised once: in the graph, or by m360 when the graph does not.
        np.testing.assert_allclose(got, imagenet(c), rtol=1e-4, atol=1e-4)
    if source == "graph":
        np.testing.assert_allclose(est.normalization.mean, MEAN, rtol=1e-5)
        np.testing.assert_allclose(est.normalization.std, STD, rtol=1e-5)
        assert est.normalization.found is not None and est.normalization.found["matched"]
    else:
        assert est.normalization.found is None


def test_a_per_channel_map_that_is_no_known_normalisation_is_not_taken_for_one(
    tmp_path: Path,
) -> None:
    odd_mean, odd_std = np.array([0.3, 0.2, 0.1]), np.array([0.6, 0.7, 0.8])
    steps = [("Sub", per_channel(odd_mean), "init"), ("Div", per_channel(odd_std), "init")]
    path = chain_then_channel(tmp_path / "odd.onnx", 0, steps)
    est = OnnxEstimator(path)
    assert est.normalization_source == "m360"
    found = est.normalization.found
    assert found is not None and not found["matched"] and found["ops"] == ["Sub", "Div"]
    np.testing.assert_allclose(found["mean"], odd_mean, rtol=1e-5)
    # m360 normalises, then the graph's own map: the network receives both.
    np.testing.assert_allclose(est.predict(tangents()), (imagenet(0) - 0.3) / 0.6, rtol=1e-4)


def test_imagenet_constants_along_the_width_are_not_per_channel(tmp_path: Path) -> None:
    # A (3,) constant broadcasts along the last axis (W of NCHW): not a per-channel map.
    steps = [("Sub", MEAN, "init"), ("Div", STD, "init")]
    path = chain_then_channel(tmp_path / "w.onnx", 0, steps, input_shape=(1, 3, 8, 3))
    norm = models.input_normalization(path)
    assert norm.source == "m360" and norm.found is None


def test_an_input_used_twice_is_not_a_preprocessing_chain(tmp_path: Path) -> None:
    # x - mean, but x also feeds an Add: the Sub is part of the network, not preprocessing.
    nodes = [
        helper.make_node("Sub", ["x", "m"], ["a"]),
        helper.make_node("Add", ["a", "x"], ["y"]),
    ]
    graph = helper.make_graph(
        nodes,
        "twice",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, 4, 4])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 3, 4, 4])],
        initializer=[numpy_helper.from_array(per_channel(MEAN), "m")],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", g.OPSET)])
    onnx.save(model, str(tmp_path / "twice.onnx"))
    assert models.input_normalization(tmp_path / "twice.onnx").found is None


def test_an_explicit_normalisation_wins_over_the_graph(tmp_path: Path) -> None:
    steps, shape, _, _ = VARIANTS["sub_div"]
    path = chain_then_channel(tmp_path / "in.onnx", 2, steps, shape)
    est = OnnxEstimator(path, mean=(0.0, 0.0, 0.0), std=(1.0, 1.0, 1.0))
    assert est.normalization_source == "m360" and est.normalization.explicit
    assert est.normalization.found is not None and est.normalization.found["matched"]
    # Only the graph's own normalisation reached the network.
    np.testing.assert_allclose(est.predict(tangents()), imagenet(2), rtol=1e-4)
    # The same through load_estimator: given mean/std win, std defaults to the expected one.
    est = load_estimator(str(path), mean=(0.0, 0.0, 0.0))
    assert est.normalization_source == "m360"  # type: ignore[attr-defined]
    assert est.normalization.std == models.IMAGENET_STD  # type: ignore[attr-defined]


def test_the_entrys_own_normalisation_is_recognised_in_the_graph(tmp_path: Path) -> None:
    # DPT's mean 0.5 / std 0.5 inside the graph: found because the entry expects it.
    half = np.full(3, 0.5)
    steps = [("Sub", per_channel(half), "init"), ("Div", per_channel(half), "init")]
    path = chain_then_channel(tmp_path / "half.onnx", 1, steps)
    est = OnnxEstimator(path, expected_normalization=((0.5,) * 3, (0.5,) * 3))
    assert est.normalization_source == "graph"
    np.testing.assert_allclose(est.predict(tangents()), (COLOUR[1] / 255 - 0.5) / 0.5, rtol=1e-4)
    # Without that expectation the same map is no known normalisation: m360 applies ImageNet.
    assert OnnxEstimator(path).normalization_source == "m360"


def test_a_registry_model_normalising_in_its_graph(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, isolated_cache: Path
) -> None:
    steps, shape, _, _ = VARIANTS["sub_div"]
    path = chain_then_channel(isolated_cache / "inside.onnx", 0, steps, shape)
    entry = dataclasses.replace(
        models.get(models.DEFAULT_MODEL),
        name="inside",
        filename="inside.onnx",
        urls=("http://127.0.0.1:9/never",),
        sha256=sha(path.read_bytes()),
        size_bytes=path.stat().st_size,
    )
    monkeypatch.setitem(models.REGISTRY, "inside", entry)
    est = load_estimator("inside")
    assert est.normalization_source == "graph"  # type: ignore[attr-defined]
    np.testing.assert_allclose(est.predict(tangents()), imagenet(0), rtol=1e-4)


def test_the_sidecar_records_who_normalised(tmp_path: Path) -> None:
    steps = VARIANTS["sub_div"][0]
    rgb, _ = m360.synthetic.render(m360.synthetic.room(0), 256)
    saved = {}
    for name, chain in (("inside", steps), ("outside", [])):
        path = chain_then_channel(tmp_path / f"{name}.onnx", 1, chain, (1, 3, "H", "W"))
        result = m360.estimate(rgb, OnnxEstimator(path), align="none", blend="mean")
        written = m360.save(result, tmp_path / name)
        saved[name] = json.loads(written["sidecar"].read_text())["model"]["normalization"]
    assert saved["inside"]["source"] == "graph" and saved["outside"]["source"] == "m360"
    np.testing.assert_allclose(saved["inside"]["mean"], MEAN, rtol=1e-5)
    np.testing.assert_allclose(saved["outside"]["std"], STD, rtol=1e-12)
    assert saved["inside"]["found_in_graph"]["ops"] == ["Sub", "Div"]


def test_a_graph_m360_cannot_read_is_assumed_not_to_normalise(tmp_path: Path) -> None:
    path = tmp_path / "junk.onnx"
    path.write_bytes(b"\x08\x07\x3a\xff\xff\xff\x0f")  # graph field claims more bytes than exist
    norm = models.input_normalization(path)
    assert norm.source == "m360" and "not readable" in norm.detail


# ------------------------------------------------------------------ every known URL


def register(monkeypatch: pytest.MonkeyPatch, urls: Sequence[str], data: bytes) -> None:
    entry = dataclasses.replace(
        models.get(models.DEFAULT_MODEL),
        name="tiny",
        filename="tiny.onnx",
        urls=tuple(urls),
        sha256=sha(data),
        sha256_source="made in the test",
        size_bytes=len(data),
        input_size=(16, 16),
        multiple_of=1,
    )
    monkeypatch.setitem(models.REGISTRY, "tiny", entry)


@pytest.fixture
def tiny(tmp_path: Path) -> bytes:
    return g.affine_of_mean(tmp_path / "made" / "tiny.onnx", 2.0, 1.0).read_bytes()


def test_404_then_wrong_bytes_then_the_right_file(
    server: LocalServer, tiny: bytes, monkeypatch: pytest.MonkeyPatch, isolated_cache: Path
) -> None:
    other = g.affine_of_mean(isolated_cache.parent / "other.onnx", 5.0, 0.0).read_bytes()
    server.routes["/b/tiny.onnx"] = (200, other, "ok")
    server.routes["/c/tiny.onnx"] = (200, tiny, "ok")
    urls = [server.url(p) for p in ("/a/tiny.onnx", "/b/tiny.onnx", "/c/tiny.onnx")]
    register(monkeypatch, urls, tiny)
    path = models.fetch("tiny", progress=False)
    assert path.read_bytes() == tiny
    assert server.requests == ["/a/tiny.onnx", "/b/tiny.onnx", "/c/tiny.onnx"]
    assert sorted(p.name for p in isolated_cache.iterdir()) == ["tiny.onnx"]


def test_every_url_failing_is_reported_url_by_url(
    server: LocalServer, tiny: bytes, monkeypatch: pytest.MonkeyPatch, isolated_cache: Path
) -> None:
    wrong = tiny + b"tampered"
    server.routes["/b/tiny.onnx"] = (200, wrong, "ok")
    server.routes["/c/tiny.onnx"] = (200, tiny, "truncate")
    urls = [server.url(p) for p in ("/a/tiny.onnx", "/b/tiny.onnx", "/c/tiny.onnx")]
    register(monkeypatch, urls, tiny)
    with pytest.raises(ModelError) as info:
        models.fetch("tiny", progress=False)
    msg = str(info.value)
    assert f"could not download model 'tiny' (expected sha256 {sha(tiny)}); tried 3 URLs" in msg
    assert f"1. {urls[0]}: HTTP 404" in msg
    assert f"2. {urls[1]}: fails its hash check (got sha256 {sha(wrong)})" in msg
    third = msg.split(f"3. {urls[2]}: ")[1]
    assert "Connection broken" in third.split("; ")[0]  # the truncated transfer
    assert f"put it at {isolated_cache / 'tiny.onnx'}" in msg
    assert server.requests == ["/a/tiny.onnx", "/b/tiny.onnx", "/c/tiny.onnx"]
    assert not isolated_cache.exists() or list(isolated_cache.iterdir()) == []


def test_a_hash_mismatch_is_never_accepted(
    server: LocalServer, tiny: bytes, monkeypatch: pytest.MonkeyPatch, isolated_cache: Path
) -> None:
    server.routes["/a/tiny.onnx"] = (200, tiny[:-1] + b"\x00", "ok")
    register(monkeypatch, [server.url("/a/tiny.onnx")], tiny)
    with pytest.raises(ModelError, match="fails its hash check"):
        models.fetch("tiny", progress=False)
    with pytest.raises(ModelError, match="M360_OFFLINE=1 forbids"):
        monkeypatch.setenv("M360_OFFLINE", "1")
        models.ensure("tiny")  # nothing was cached by the failed attempt


def test_offline_names_every_url_and_where_to_put_the_file(
    server: LocalServer, tiny: bytes, monkeypatch: pytest.MonkeyPatch, isolated_cache: Path
) -> None:
    server.routes["/c/tiny.onnx"] = (200, tiny, "ok")
    urls = [server.url(p) for p in ("/a/tiny.onnx", "/b/tiny.onnx", "/c/tiny.onnx")]
    register(monkeypatch, urls, tiny)
    monkeypatch.setenv("M360_OFFLINE", "1")
    with pytest.raises(ModelError) as info:
        models.ensure("tiny")
    msg = str(info.value)
    assert "M360_OFFLINE=1 forbids downloading" in msg
    assert f"put it at {isolated_cache / 'tiny.onnx'}" in msg and "M360_MODEL_DIR" in msg
    assert all(u in msg for u in urls)
    assert server.requests == []


def test_registry_urls_are_pinned_and_the_hf_copies_are_all_listed() -> None:
    for entry in models.REGISTRY.values():
        assert len(set(entry.urls)) == len(entry.urls), entry.name
        for url in entry.urls:
            assert url.startswith("https://"), url
            if "huggingface.co" in url:
                # a 40-hex revision, never a branch such as main
                rev = url.split("/resolve/")[1].split("/")[0]
                assert len(rev) == 40 and int(rev, 16) >= 0, url
    for name in ("midas-v21-small", "midas-v21-large", "dpt-large"):
        entry = models.get(name)
        root, sub = entry.urls[:2]
        assert root.endswith(f"/{entry.filename}") and sub.endswith(f"/onnx/{entry.filename}")
        assert root.rsplit("/", 1)[0] + "/onnx" == sub.rsplit("/", 1)[0]
    isl = models.get("midas-v21-small-isl")
    assert isl.urls[0] == "https://github.com/isl-org/MiDaS/releases/download/v2_1/model-small.onnx"


def test_in_memory_bytes_are_read_instead_of_the_file(tmp_path: Path) -> None:
    inside = chain_then_channel(tmp_path / "in.onnx", 0, VARIANTS["sub_div"][0])
    plain = chain_then_channel(tmp_path / "plain.onnx", 0, [])
    assert models.input_normalization(plain).source == "m360"
    assert models.input_normalization(plain, data=inside.read_bytes()).source == "graph"


def test_the_graph_reader_only_ever_says_unreadable(tmp_path: Path) -> None:
    # Every truncation and many one-byte corruptions of a normalising graph: the reader
    # answers or raises ModelError, never another exception (the file comes from anywhere).
    data = chain_then_channel(
        tmp_path / "in.onnx", 0, VARIANTS["constant_nodes_after_cast_and_resize"][0]
    ).read_bytes()
    assert _onnxgraph.inspect(data).affine is not None
    rng = np.random.default_rng(0)
    variants = [data[:n] for n in range(len(data))]
    for _ in range(400):
        mutated = bytearray(data)
        mutated[rng.integers(len(data))] = rng.integers(256)
        variants.append(bytes(mutated))
    for blob in variants:
        try:
            _onnxgraph.inspect(blob)
        except ModelError:
            pass


def test_a_malformed_expected_normalisation_is_an_input_error(tmp_path: Path) -> None:
    path = chain_then_channel(tmp_path / "plain.onnx", 0, [])
    with pytest.raises(InputError, match=r"expected_normalization must be \(mean, std\)"):
        OnnxEstimator(path, expected_normalization=(0.5, 0.5, 0.5))  # type: ignore[arg-type]
    with pytest.raises(InputError, match="mean must be 3 finite numbers"):
        OnnxEstimator(path, expected_normalization=((0.5, float("nan"), 0.5), (1, 1, 1)))


def test_an_unverified_entry_skips_an_error_page_for_the_next_url(
    server: LocalServer, tiny: bytes, monkeypatch: pytest.MonkeyPatch, isolated_cache: Path
) -> None:
    # No hash to reject it: the page is recognised as not ONNX, removed, and the next URL tried.
    server.routes["/a/tiny.onnx"] = (200, b"<!DOCTYPE html><html>Sign in</html>", "ok")
    server.routes["/b/tiny.onnx"] = (200, tiny, "ok")
    register(monkeypatch, [server.url("/a/tiny.onnx"), server.url("/b/tiny.onnx")], tiny)
    monkeypatch.setitem(
        models.REGISTRY, "tiny", dataclasses.replace(models.get("tiny"), sha256=None)
    )
    monkeypatch.setenv("M360_ALLOW_UNVERIFIED", "1")
    with pytest.warns(UserWarning, match="WITHOUT hash verification"):
        assert models.fetch("tiny", progress=False).read_bytes() == tiny
    assert server.requests == ["/a/tiny.onnx", "/b/tiny.onnx"]
