"""Partial panoramas: GPano XMP crop metadata, the full canvas and the masked rest."""

from __future__ import annotations

import functools
import json
import struct

import cv2
import m360
import m360.synthetic as syn
import numpy as np
import pytest
from m360 import masks

FULL_W, FULL_H = 540, 270
TOP, ROWS = 45, 180  # 120° of latitude: rows 45..224 (±60°)


def xmp_packet(**fields: object) -> bytes:
    attrs = " ".join(f'GPano:{k}="{v}"' for k, v in fields.items())
    return (
        '<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF '
        'xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
        '<rdf:Description rdf:about="" xmlns:GPano="http://ns.google.com/photos/1.0/panorama/" '
        f"{attrs}/></rdf:RDF></x:xmpmeta>"
    ).encode()


def jpeg_with_xmp(rgb: np.ndarray, packet: bytes) -> bytes:
    """A JPEG (quality 100) with an XMP APP1 segment right after SOI."""
    ok, encoded = cv2.imencode(".jpg", rgb[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 100])
    assert ok
    payload = b"http://ns.adobe.com/xap/1.0/\x00" + packet
    segment = b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload
    data = bytes(encoded)
    return data[:2] + segment + data[2:]


def crop_fields(**over: object) -> dict[str, object]:
    fields: dict[str, object] = {
        "ProjectionType": "equirectangular",
        "FullPanoWidthPixels": FULL_W,
        "FullPanoHeightPixels": FULL_H,
        "CroppedAreaImageWidthPixels": FULL_W,
        "CroppedAreaImageHeightPixels": ROWS,
        "CroppedAreaLeftPixels": 0,
        "CroppedAreaTopPixels": TOP,
    }
    fields.update(over)
    return fields


@functools.cache
def full_scene() -> tuple[syn.Scene, np.ndarray, np.ndarray]:
    scene = syn.room(4)
    rgb, depth = syn.render(scene, FULL_W)
    return scene, rgb, depth


def exact_estimator(scene: syn.Scene) -> m360.estimators.SimulatedEstimator:
    return m360.estimators.SimulatedEstimator(
        scene, m360.geometry.default_layout(FULL_W), scale=(1.0, 1.0), shift=0.0
    )


def write_crop(tmp_path, **over: object):
    _, rgb, _ = full_scene()
    path = tmp_path / "crop.jpg"
    path.write_bytes(jpeg_with_xmp(rgb[TOP : TOP + ROWS], xmp_packet(**crop_fields(**over))))
    return path


def test_crop_estimate_equals_full_sphere_on_captured_rows(tmp_path):
    scene, rgb, _ = full_scene()
    partial = masks.partial_panorama(write_crop(tmp_path))
    assert partial is not None and partial.rgb.shape == (FULL_H, FULL_W, 3)
    assert partial.mask[TOP : TOP + ROWS].all() and partial.mask.sum() == ROWS * FULL_W
    est = exact_estimator(scene)
    crop = m360.estimate(partial.rgb, est, mask=partial.mask, align="none", blend="mean")
    full = m360.estimate(rgb, est, align="none", blend="mean")
    inner = slice(TOP + 4, TOP + ROWS - 4)  # the mask edge loses a few rows to bilinear footprints
    np.testing.assert_allclose(crop.disparity[inner], full.disparity[inner], rtol=1e-5)
    assert np.isnan(crop.disparity[:TOP]).all() and np.isnan(crop.disparity[TOP + ROWS :]).all()


def test_batch_places_the_crop_and_records_it(tmp_path):
    scene, _, _ = full_scene()
    path = write_crop(tmp_path, CroppedAreaLeftPixels=500)  # crosses the seam: wraps
    report = m360.batch.run([path], tmp_path / "out", model=exact_estimator(scene), progress=False)
    assert report.exit_code == 0, report.outcomes
    meta = json.loads((tmp_path / "out" / "crop.json").read_text())
    assert meta["crop"]["top"] == TOP and meta["crop"]["left"] == 500
    assert meta["crop"]["full_width"] == FULL_W
    saved = m360.load(tmp_path / "out" / "crop")
    assert saved.depth.shape == (FULL_H, FULL_W)
    assert np.isnan(saved.depth[:TOP]).all() and np.isnan(saved.depth[TOP + ROWS :]).all()
    assert np.isfinite(saved.depth[TOP + 2 : TOP + ROWS - 2]).mean() > 0.99


@pytest.mark.parametrize(
    ("over", "message"),
    [
        ({"CroppedAreaImageHeightPixels": 150}, "the image is 540x180 pixels"),
        ({"CroppedAreaImageWidthPixels": 500}, "the image is 540x180 pixels"),
        ({"FullPanoHeightPixels": 300}, "not an ERP canvas"),
        ({"CroppedAreaTopPixels": 100}, "outside the full"),
        ({"CroppedAreaLeftPixels": 9999}, "outside 0"),
        ({"ProjectionType": "cylindrical"}, "not equirectangular"),
        ({"CroppedAreaTopPixels": "4.5"}, "not an integer"),
    ],
)
def test_contradicting_metadata_is_a_read_error(tmp_path, over, message):
    path = write_crop(tmp_path, **over)
    with pytest.raises(m360.ReadError, match=message):
        masks.partial_panorama(path)
    report = m360.batch.run(
        [path], tmp_path / "out", model=exact_estimator(full_scene()[0]), progress=False
    )
    assert report.exit_code != 0 and report.outcomes[0].error == "ReadError"


def test_missing_fields_and_element_form(tmp_path):
    _, rgb, _ = full_scene()
    fields = crop_fields()
    del fields["CroppedAreaTopPixels"]
    path = tmp_path / "a.jpg"
    path.write_bytes(jpeg_with_xmp(rgb[TOP : TOP + ROWS], xmp_packet(**fields)))
    with pytest.raises(m360.ReadError, match="lacks CroppedAreaTopPixels"):
        masks.partial_panorama(path)
    # the same fields as child elements instead of attributes
    elements = "".join(f"<GPano:{k}>{v}</GPano:{k}>" for k, v in crop_fields().items())
    packet = (
        '<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF '
        'xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#"><rdf:Description '
        'xmlns:GPano="http://ns.google.com/photos/1.0/panorama/">'
        f"{elements}</rdf:Description></rdf:RDF></x:xmpmeta>"
    ).encode()
    path.write_bytes(jpeg_with_xmp(rgb[TOP : TOP + ROWS], packet))
    partial = masks.partial_panorama(path)
    assert partial is not None and partial.crop["top"] == TOP


def test_without_metadata_a_crop_is_refused_as_before(tmp_path):
    _, rgb, _ = full_scene()
    path = tmp_path / "plain.jpg"
    _, data = cv2.imencode(".jpg", rgb[TOP : TOP + ROWS])
    path.write_bytes(bytes(data))
    assert masks.partial_panorama(path) is None
    report = m360.batch.run(
        [path], tmp_path / "out", model=exact_estimator(full_scene()[0]), progress=False
    )
    assert report.outcomes[0].error == "AspectRatioError"
