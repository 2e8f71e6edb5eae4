"""Outputs and inputs: save/load round trips of every format, sidecar, and image decoding."""

from __future__ import annotations

import json
import re
from pathlib import Path
from types import SimpleNamespace

import cv2
import m360
import numpy as np
import OpenEXR
import pytest
from m360 import io


def _result(height: int = 32, seed: int = 0) -> SimpleNamespace:
    """A result-like object with awkward values: NaN holes, negatives, a wide range."""
    rng = np.random.default_rng(seed)
    disparity = rng.uniform(-0.3, 4.0, (height, 2 * height)).astype(np.float32)
    disparity[0, :5] = np.nan
    disparity[height // 2, height] = np.float32(1e-7)
    with np.errstate(divide="ignore"):
        depth = np.where(disparity > 0, 1.0 / disparity, np.nan).astype(np.float32)
    return SimpleNamespace(
        disparity=disparity,
        depth=depth,
        units="relative",
        model={"name": "test", "sha256": "0" * 64},
        options={"align": "none", "blend": "mean"},
        timings={"network": 0.5, "blend": 0.25},
        layout=m360.Layout.icosahedron(2 * height),
    )


@pytest.mark.parametrize("fmt", ["npy", "pfm", "exr"])
def test_float_formats_round_trip_bit_exactly(tmp_path: Path, fmt: str) -> None:
    result = _result()
    written = m360.save(result, tmp_path / "pano", formats=(fmt,))
    assert set(written) == {f"disparity.{fmt}", f"depth.{fmt}", "preview", "sidecar"}
    back = m360.load(tmp_path / "pano")
    assert back.format == fmt
    for quantity in ("disparity", "depth"):
        got, want = getattr(back, quantity), getattr(result, quantity)
        assert got.dtype == np.float32 and got.shape == want.shape
        # Bit-exact, NaN where NaN.
        assert np.array_equal(got.view(np.uint32), want.view(np.uint32))


def test_png16_is_within_half_a_step(tmp_path: Path) -> None:
    """PNG16 quantisation: value = offset + (code - 1)·scale, scale = range / 65534, so the
    error is at most scale/2 (plus float32 rounding); 0 codes are exactly the NaN pixels."""
    result = _result(seed=3)
    m360.save(result, tmp_path / "pano", formats="png16", preview=False)
    back = m360.load(tmp_path / "pano")
    meta = back.metadata["png16"]
    for quantity in ("disparity", "depth"):
        want = getattr(result, quantity)
        got = getattr(back, quantity)
        finite = np.isfinite(want)
        assert np.array_equal(np.isfinite(got), finite)
        lo, hi = float(want[finite].min()), float(want[finite].max())
        scale = meta[quantity]["scale"]
        assert scale == pytest.approx((hi - lo) / 65534, rel=1e-12)
        err = np.abs(got[finite].astype(np.float64) - want[finite])
        bound = scale / 2 + np.abs(want[finite]) * 2.0**-23
        assert (err <= bound).all(), float((err - bound).max())
        codes = cv2.imread(str(tmp_path / f"pano.{quantity}.png"), cv2.IMREAD_UNCHANGED)
        assert codes.dtype == np.uint16 and (codes[~finite] == 0).all() and codes.max() == 65535


def test_sidecar_is_self_describing_and_written_last(tmp_path: Path) -> None:
    result = _result()
    written = m360.save(
        result, tmp_path / "sub" / "pano", formats=("npy", "png16"), extra={"input": "x.jpg"}
    )
    meta = json.loads((tmp_path / "sub" / "pano.json").read_text())
    assert meta["files"]["disparity"] == {
        "npy": "pano.disparity.npy",
        "png16": "pano.disparity.png",
    }
    assert meta["files"]["preview"] == "pano.preview.png"
    assert meta["quantities"]["depth"]["units"] == "relative"
    assert meta["layout"]["erp_shape"] == [32, 64] and meta["layout"]["cameras"] == 20
    assert meta["m360_version"] == m360.__version__ and meta["input"] == "x.jpg"
    assert meta["timings_s"] == {"network": 0.5, "blend": 0.25}
    assert "latitude" in meta["erp_convention"]
    mtimes = {role: p.stat().st_mtime_ns for role, p in written.items()}
    assert mtimes["sidecar"] == max(mtimes.values())
    assert not list((tmp_path / "sub").glob(".*"))  # no temporary files left


def test_a_failed_save_leaves_no_sidecar_and_no_partial_set(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    m360.save(_result(), tmp_path / "pano", formats=("npy",))
    assert (tmp_path / "pano.json").is_file()

    def broken(path: Path, values: np.ndarray) -> Path:
        raise OSError("disk full")

    monkeypatch.setattr(io.files, "_write_exr", broken)
    with pytest.raises(OSError, match="disk full"):
        m360.save(_result(seed=1), tmp_path / "pano", formats=("npy", "exr"))
    # The old sidecar went first (its set was being replaced) and the new arrays written before
    # the failure were removed again: what is left has no sidecar, so nothing claims to be done.
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pano.preview.png"]
    with pytest.raises(m360.ReadError, match="not a complete m360 output"):
        m360.load(tmp_path / "pano")


def test_load_accepts_any_file_of_the_set_and_a_format(tmp_path: Path) -> None:
    result = _result()
    m360.save(result, tmp_path / "pano", formats=("png16", "exr"))
    for name in ("pano.json", "pano.preview.png", "pano.depth.exr", "pano.disparity.png"):
        assert m360.load(tmp_path / name).stem == tmp_path / "pano"
    assert m360.load(tmp_path / "pano").format == "exr"  # float before png16
    assert m360.load(tmp_path / "pano", format="png16").format == "png16"
    with pytest.raises(m360.InputError, match="no 'npy' files"):
        m360.load(tmp_path / "pano", format="npy")


def test_read_map_reads_one_file_of_an_output_or_any_array(tmp_path: Path) -> None:
    result = _result()
    m360.save(result, tmp_path / "pano", formats=("png16", "exr"))
    png16 = m360.load(tmp_path / "pano", format="png16")
    for quantity in ("disparity", "depth"):
        # A 16-bit PNG of an output: its codes mapped back by the sidecar, as load does.
        got = io.read_map(tmp_path / f"pano.{quantity}.png")
        np.testing.assert_array_equal(got, getattr(png16, quantity))
        finite = np.isfinite(getattr(result, quantity))
        assert np.isfinite(got).tolist() == finite.tolist()
        # A float file of the output: its values, bit for bit.
        exr = io.read_map(tmp_path / f"pano.{quantity}.exr")
        assert np.array_equal(exr.view(np.uint32), getattr(result, quantity).view(np.uint32))
    # A 16-bit PNG another tool wrote (no sidecar): its codes minus one, 0 = unknown.
    codes = np.array([[0, 1, 1000, 65535], [7, 0, 2, 3]], np.uint16)
    assert cv2.imwrite(str(tmp_path / "lidar_mm.png"), codes)
    want = np.where(codes == 0, np.nan, codes.astype(np.float32) - 1)
    np.testing.assert_array_equal(io.read_map(tmp_path / "lidar_mm.png"), want)
    # An 8-bit image is refused, saying what is taken instead.
    assert cv2.imwrite(str(tmp_path / "preview8.png"), codes.astype(np.uint8))
    with pytest.raises(m360.ReadError, match=r"uint8 values; expected a float map .* 16-bit PNG"):
        io.read_map(tmp_path / "preview8.png")
    # A file named like an output's but without the sidecar is just an array.
    (tmp_path / "pano.json").unlink()
    codes_back = cv2.imread(str(tmp_path / "pano.depth.png"), cv2.IMREAD_UNCHANGED)
    want = np.where(codes_back == 0, np.nan, codes_back.astype(np.float32) - 1)
    np.testing.assert_array_equal(io.read_map(tmp_path / "pano.depth.png"), want)


def test_load_names_a_corrupt_or_missing_file(tmp_path: Path) -> None:
    m360.save(_result(), tmp_path / "pano", formats=("npy", "pfm"))
    (tmp_path / "pano.disparity.npy").write_bytes(b"\x93NUMPY garbage")
    with pytest.raises(m360.ReadError, match=r"pano\.disparity\.npy"):
        m360.load(tmp_path / "pano", format="npy")
    (tmp_path / "pano.depth.pfm").unlink()
    with pytest.raises(m360.ReadError, match=r"pano\.depth\.pfm does not exist"):
        m360.load(tmp_path / "pano", format="pfm")
    (tmp_path / "pano.json").write_text("{not json")
    with pytest.raises(m360.ReadError, match="sidecar"):
        m360.load(tmp_path / "pano")


def test_save_refuses_bad_formats_and_results(tmp_path: Path) -> None:
    with pytest.raises(m360.InputError, match="'tiff' is not supported"):
        m360.save(_result(), tmp_path / "p", formats=("npy", "tiff"))
    with pytest.raises(m360.InputError, match="formats is empty"):
        m360.save(_result(), tmp_path / "p", formats=())
    bad = SimpleNamespace(disparity=np.zeros((4, 8), np.int32), depth=np.zeros((4, 8)))
    with pytest.raises(m360.InputError, match=r"result\.disparity"):
        m360.save(bad, tmp_path / "p")
    assert not list(tmp_path.iterdir())


# --------------------------------------------------------------------------------------------
# Input images.


@pytest.fixture(scope="module")
def rgb() -> np.ndarray:
    rng = np.random.default_rng(7)
    return rng.integers(0, 256, (16, 32, 3), dtype=np.uint8)


def _write(path: Path, image: np.ndarray) -> Path:
    assert cv2.imwrite(str(path), image)
    return path


def test_reads_8_and_16_bit_grey_rgba_and_tiff(tmp_path: Path, rgb: np.ndarray) -> None:
    bgr = rgb[:, :, ::-1]
    assert np.array_equal(io.load_image(_write(tmp_path / "a.png", bgr)), rgb)
    assert np.array_equal(io.load_image(_write(tmp_path / "a.tif", bgr)), rgb)
    # 16 bit, off the exact multiples of 257 by 100 either way: rounds back to the 8-bit values.
    wide = (rgb.astype(np.int32) * 257 + np.where(rgb < 128, 100, -100)).astype(np.uint16)
    assert np.array_equal(io.load_image(_write(tmp_path / "b.png", wide[:, :, ::-1])), rgb)
    grey = rgb[:, :, 0]
    assert np.array_equal(io.load_image(_write(tmp_path / "g.png", grey)), np.dstack([grey] * 3))
    rgba = np.dstack([bgr, np.full(grey.shape, 9, np.uint8)])
    assert np.array_equal(io.load_image(_write(tmp_path / "c.png", rgba)), rgb)


def test_reads_an_exr_panorama_tone_mapped(tmp_path: Path) -> None:
    linear = np.linspace(0.0, 8.0, 16 * 32 * 3, dtype=np.float32).reshape(16, 32, 3)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {"RGB": linear}).write(str(tmp_path / "hdr.exr"))
    image = io.load_image(tmp_path / "hdr.exr")
    white = np.percentile(linear, 99.0)
    want = np.rint(np.clip(linear / white, 0, 1) ** (1 / 2.2) * 255).astype(np.uint8)
    assert image.dtype == np.uint8 and np.abs(image.astype(int) - want).max() <= 1


def test_bad_images_raise_specific_errors(tmp_path: Path, rgb: np.ndarray) -> None:
    _, jpeg = cv2.imencode(".jpg", rgb)
    (tmp_path / "cut.jpg").write_bytes(jpeg.tobytes()[: len(jpeg) * 2 // 3])
    with pytest.raises(m360.ReadError, match="truncated JPEG"):
        io.load_image(tmp_path / "cut.jpg")
    # A camera trailer after the end-of-image marker is fine.
    (tmp_path / "trailer.jpg").write_bytes(jpeg.tobytes() + b"\x00gyro\xff\xda\x00" * 10)
    assert io.load_image(tmp_path / "trailer.jpg").shape == (16, 32, 3)
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(m360.ReadError, match="empty"):
        io.load_image(tmp_path / "empty.png")
    (tmp_path / "text.png").write_text("not an image")
    with pytest.raises(m360.ReadError, match="cannot decode"):
        io.load_image(tmp_path / "text.png")
    with pytest.raises(m360.ReadError, match="does not exist"):
        io.load_image(tmp_path / "missing.png")


def test_aspect_ratio_is_refused_or_fixed_on_request(tmp_path: Path, rgb: np.ndarray) -> None:
    path = _write(tmp_path / "wide.png", np.ascontiguousarray(rgb[:, :24]))  # 24x16: 3:2
    with pytest.raises(m360.AspectRatioError, match=r"is 16x24 \(HxW\)") as info:
        io.load_image(path)
    assert "--fix-aspect" in str(info.value) and isinstance(info.value, m360.InputError)
    assert io.load_image(path, fix_aspect=True).shape == (12, 24, 3)


def test_stale_temporaries_of_one_set_only_are_removed(tmp_path: Path) -> None:
    """What a killed writer leaves: removed for its own set, never for a set with a longer stem."""
    with io.atomic_path(tmp_path / "pano.json") as tmp:  # the scheme the cleanup relies on
        assert re.fullmatch(r"\.pano\.json\.[a-z0-9_]{8}\.tmp", tmp.name), tmp.name
        tmp.write_text("{}")
    assert not tmp.exists() and (tmp_path / "pano.json").exists()
    mine = [tmp_path / ".pano.disparity.npy.a1b2c3d4.tmp", tmp_path / ".pano.json.zz_9x8y7.tmp"]
    other = [
        tmp_path / ".pano.v2.disparity.npy.a1b2c3d4.tmp",
        tmp_path / ".pano_b.json.q1w2e3r4.tmp",
    ]
    for path in [*mine, *other]:
        path.write_bytes(b"partial")
    assert sorted(io.remove_stale_temporaries(tmp_path / "pano")) == sorted(mine)
    assert all(p.exists() for p in other)


# --------------------------------------------------------------------------------------------
# Sizes from headers, refusals before decoding, NaN-only inputs (issue 23).


def _png_header_only(path: Path, width: int, height: int) -> Path:
    """A PNG that declares ``width`` x ``height`` (8-bit RGB) with one empty IDAT: its header
    is valid, its pixels are not there (nothing may decode it)."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    data = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b""))
    path.write_bytes(data + chunk(b"IEND", b""))
    return path


@pytest.fixture
def no_decoding(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*_: object, **__: object) -> None:
        raise AssertionError("the image was decoded")

    monkeypatch.setattr(cv2, "imdecode", refuse)


def test_headers_give_the_decoded_size_and_samples(tmp_path: Path, rgb: np.ndarray) -> None:
    from m360.io.decode import image_header

    bgr = np.ascontiguousarray(rgb[:, :, ::-1])
    wide = rgb.astype(np.uint16) * 257
    cases = {
        "a.png": (bgr, 3, 1),
        "g.png": (bgr[:, :, 0], 1, 1),
        "w.png": (wide, 3, 2),
        "a4.png": (np.dstack([bgr, bgr[:, :, :1]]), 4, 1),
        "a.jpg": (bgr, 3, 1),
        "g.jpg": (bgr[:, :, 0], 1, 1),
        "a.tif": (bgr, 3, 1),
        "w.tif": (wide, 3, 2),
        "a.hdr": (bgr.astype(np.float32) / 255, 3, 4),
    }
    for name, (image, channels, sample_bytes) in cases.items():
        _write(tmp_path / name, image)
        data = (tmp_path / name).read_bytes()
        header = image_header(data)
        decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        assert header is not None, name
        assert (header.height, header.width) == decoded.shape[:2] == (16, 32), name
        assert header.channels == (1 if decoded.ndim == 2 else decoded.shape[2]) == channels, name
        assert header.sample_bytes == decoded.dtype.itemsize == sample_bytes, name
    for channels in (
        {"RGB": np.ones((16, 32, 3), np.float32)},
        {"Y": np.ones((16, 32), np.float16)},
    ):
        exr = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
        OpenEXR.File(exr, channels).write(str(tmp_path / "a.exr"))
        header = image_header((tmp_path / "a.exr").read_bytes())
        assert header is not None and (header.height, header.width) == (16, 32)
        assert header.channels == (3 if "RGB" in channels else 1)
    assert image_header(b"not an image at all") is None
    assert image_header(b"\x89PNG\r\n\x1a\n\x00\x00") is None  # cut inside the header


def test_a_huge_image_of_the_wrong_aspect_is_refused_by_its_header(
    tmp_path: Path, no_decoding: None
) -> None:
    path = _png_header_only(tmp_path / "square.png", 30000, 30000)
    with pytest.raises(m360.AspectRatioError, match=r"is 30000x30000 \(HxW\)"):
        io.load_image(path)


def _tiny_model(tmp_path: Path) -> Path:
    import onnx_graphs as g

    return g.affine_of_mean(tmp_path / "m.onnx", 1.0, 0.1)  # type: ignore[no-any-return]


def _failures(out: Path) -> list[dict[str, str]]:
    return [json.loads(line) for line in (out / "failures.jsonl").read_text().splitlines()]


def test_a_run_refuses_by_header_a_wrong_aspect_and_an_image_too_large_for_the_memory(
    tmp_path: Path, no_decoding: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    from m360.cli import main

    inputs = tmp_path / "in"
    inputs.mkdir()
    _png_header_only(inputs / "square.png", 30000, 30000)
    _png_header_only(inputs / "huge.png", 60000, 30000)
    monkeypatch.setenv("M360_MEMORY_LIMIT", "8G")
    out = tmp_path / "out"
    args = ["run", str(inputs), "-o", str(out), "--model", str(_tiny_model(tmp_path))]
    assert main([*args, "--formats", "npy,glb", "--no-progress"]) == 1
    failures = {Path(f["input"]).name: f for f in _failures(out)}
    assert failures["square.png"]["error"] == "AspectRatioError"
    huge = failures["huge.png"]
    assert huge["error"] == "InputError", huge
    assert re.search(
        r"60000x30000.* needs about \d+\.\d GiB .* 8\.0 GiB is available", huge["message"]
    )
    assert "npy,glb" in huge["message"] and "--working-width" in huge["message"]


def test_the_run_estimate_grows_with_the_outputs_and_the_input_samples() -> None:
    from m360.io.decode import ImageHeader
    from m360.memory import estimate_memory

    width, work = 16384, 4096
    alone = estimate_memory(width, work, "consensus")
    run = estimate_memory(width, work, "consensus", formats=["npy"])
    assert run > alone  # the decoded panorama is held through the estimate
    more = estimate_memory(width, work, "consensus", formats=["npy", "pfm", "png16"], preview=True)
    assert more > run
    eight = ImageHeader(width, width // 2, 3, 1, "png")
    sixteen = ImageHeader(width, width // 2, 3, 2, "png")
    small = dict(formats=["npy"], file_bytes=0)
    low = estimate_memory(64, 64, "consensus", header=eight, **small)
    high = estimate_memory(64, 64, "consensus", header=sixteen, **small)
    # OpenCV's decoder holds two of its arrays at its peak: twice the wider samples
    assert high - low == pytest.approx(2 * (sixteen.decoded_bytes - eight.decoded_bytes), rel=0.01)
    # the mesh's vertex budget bounds the GLB's part: every pixel costs more than the default
    args = (width, work, "consensus")
    assert estimate_memory(*args, formats=["glb"], max_vertices=None) > estimate_memory(
        *args, formats=["glb"]
    )


def _nan_exr(path: Path) -> Path:
    values = np.full((16, 32, 3), np.nan, np.float32)
    values[3, 4] = np.inf
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {"RGB": values}).write(str(path))
    return path


def test_a_nan_only_exr_is_refused_through_the_api_and_the_cli(tmp_path: Path) -> None:
    from m360.cli import main

    path = _nan_exr(tmp_path / "nan.exr")
    with pytest.raises(m360.ReadError, match=r"nan\.exr has no finite pixel value"):
        io.load_image(path)
    # as m360.estimate refuses such an array
    with pytest.raises(m360.InputError, match="without NaN"):
        m360.estimate(np.full((16, 32, 3), np.nan, np.float32), "simulated")
    out = tmp_path / "out"
    args = ["run", str(path), "-o", str(out), "--model", str(_tiny_model(tmp_path))]
    assert main([*args, "--no-progress"]) == 1
    (failure,) = _failures(out)
    assert failure["error"] == "ReadError" and "no finite pixel value" in failure["message"]
    assert not list(out.glob("nan.*"))
