"""Registry of depth models: where to get them, how to check them, how to feed them.

Each :class:`ModelEntry` names an ONNX file, the URL(s) it is published at, its sha256, its
licence, the input size and normalisation the network expects and what it outputs. Files are
cached under ``$M360_HOME/models`` (default: the platform's user cache folder, via platformdirs),
downloaded atomically with a progress bar, and their sha256 is checked before the first use in a
process. ``M360_OFFLINE=1`` never touches the network.

Download, hash check and atomic rename are pooch's (``pooch.retrieve`` writes to a temporary file
in the cache folder, checks the hash, then moves it into place): it is the ecosystem's maintained
tool for exactly this (docs/architecture.md) and brings tqdm progress bars. m360 adds what
pooch does not know: the offline switch, a check that the file is an ONNX graph and not an HTML
error page, and :class:`~m360.errors.ModelError` messages that say where to put a manually
downloaded copy.

Each entry lists every known location of the same file (``urls``), tried in order: a failed
request or a hash mismatch moves on to the next one (a mismatching file is never kept), and the
error lists what happened at every URL.

The normalisation an entry names (``mean``/``std``) is what the *network* needs; whether m360
applies it or the exported graph already does is found by reading the graph when a model is
first loaded (:func:`input_normalization`), not taken from a model card.

Where the publisher's sha256 could not be confirmed, the entry stores ``sha256=None`` and says so
in ``sha256_source``; such a file is refused unless ``M360_ALLOW_UNVERIFIED=1`` is set (then it is
used with a warning that prints the file's actual hash).
"""

from __future__ import annotations

import math
import os
import re
import threading
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .._home import home_dir
from ..errors import InputError, ModelError
from ..geometry.layout import Layout, pixel_degrees
from .onnx import OnnxEstimator, PanoramicOnnxEstimator, is_file
from .onnx_file import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    NO_NORMALISATION,
    NORMALIZE_PRESETS,
    Normalization,
    input_normalization,
    sha256_of,
    sniff_onnx,
)
from .options import ModelKeywords, ModelOptions

if TYPE_CHECKING:
    from typing_extensions import Unpack

__all__ = [
    "DEFAULT_MODEL",
    "IMAGENET_MEAN",
    "IMAGENET_STD",
    "NO_NORMALISATION",
    "REGISTRY",
    "ModelEntry",
    "Normalization",
    "cache_dir",
    "check",
    "ensure",
    "fetch",
    "get",
    "home_dir",
    "input_normalization",
    "is_cached",
    "list_models",
    "names",
    "sha256_of",
    "sniff_onnx",
    "verify",
]

#: The model :func:`m360.estimate` uses when none is named.
DEFAULT_MODEL = "midas-v21-small"

_DOWNLOAD_TIMEOUT_S = 60.0


@dataclass(frozen=True)
class ModelEntry:
    """One registered model.

    Attributes
    ----------
    name : str
        Registry name, e.g. ``"midas-v21-small"``.
    filename : str
        File name in the cache folder.
    urls : tuple of str
        Every known location of this very file (same sha256), pinned to a revision, tried in
        order; a 404 or a hash mismatch moves on to the next.
    sha256 : str or None
        Expected sha256 (lower-case hex) of the file; None when no published hash could be
        confirmed (see ``sha256_source``).
    sha256_source : str
        Where the hash comes from, or why there is none.
    size_bytes : int or None
        Approximate size, for ``m360 models`` (exact when known).
    licence : str
        Licence of the weights.
    input_size : (int, int)
        Network input (height, width) the model was trained at; the file's own fixed input
        size, when it has one, takes precedence.
    mean, std : (float, float, float)
        Per-channel normalisation of RGB in [0, 1] the network was trained with:
        ``(rgb - mean) / std``. m360 applies it unless the exported graph is found to apply it
        itself (:func:`input_normalization`).
    multiple_of : int
        Network sizes are rounded to a multiple of this (32 for CNN/DPT, 14 for DINOv2 ViTs).
    resize : str
        ``"upper_bound"`` (fit inside ``input_size``, keep aspect) or ``"lower_bound"`` (cover
        ``input_size``, keep aspect); only used when the file's input size is dynamic.
    output_kind : str
        ``"affine_disparity"``, ``"metric_depth"`` or ``"distance"`` (docs/architecture.md).
    description : str
        One line for ``m360 models``.
    notes : str
        Provenance and caveats.
    kind : str
        ``"tangent"`` (perspective tiles in; every entry so far) or ``"panoramic"`` (the whole
        ERP in and out; ``output_kind`` then one of
        :data:`m360.estimators.kinds.PANORAMIC_OUTPUT_KINDS`).
    """

    name: str
    filename: str
    urls: tuple[str, ...]
    sha256: str | None
    sha256_source: str
    size_bytes: int | None
    licence: str
    input_size: tuple[int, int]
    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    multiple_of: int
    resize: str
    output_kind: str
    description: str
    notes: str = ""
    kind: str = "tangent"


_SENTIS = (
    "https://huggingface.co/julienkay/sentis-MiDaS/resolve/49661c6dbe7e7e1a57290e30aae95b649fd33d54"
)


def _sentis(filename: str) -> tuple[str, ...]:
    # The repository's root copy (the registry's original URL), then the same file in its onnx/
    # sub-folder, from which public projects also fetch it (…/resolve/main/onnx/<file>). Both
    # are checked against the same sha256: a missing path (404) or other bytes move on.
    # The authors' isl-org release assets (model-small.onnx, model-f6b98070.onnx) are their own
    # exports, other bytes (another size): not copies of this file, so not listed here.
    return (f"{_SENTIS}/{filename}", f"{_SENTIS}/onnx/{filename}")


_SENTIS_NOTE = (
    "ONNX export of the official isl-org MiDaS weights by julienkay (Hugging Face "
    "julienkay/sentis-MiDaS, revision 49661c6); static input size. Its model card says the "
    "input normalisation is baked into the graph, while public code using the same file "
    "applies it outside: m360 reads the graph and applies it only if the graph does not."
)
_SENTIS_HASH = (
    "Hugging Face Git LFS pointer of this file at revision 49661c6 (published by the host)"
)
#: MiDaS v3 DPT models are trained with mean 0.5 / std 0.5 (isl-org/MiDaS run.py).
_HALF = (0.5, 0.5, 0.5)

REGISTRY: dict[str, ModelEntry] = {
    e.name: e
    for e in (
        ModelEntry(
            name="midas-v21-small",
            filename="midas_v21_small_256.onnx",
            urls=_sentis("midas_v21_small_256.onnx"),
            sha256="b0a5b3f12625137e626805167907fe0410665bec671685d59daaa2daab19f977",
            sha256_source=_SENTIS_HASH,
            size_bytes=66_400_000,
            licence="MIT",
            input_size=(256, 256),
            mean=IMAGENET_MEAN,
            std=IMAGENET_STD,
            multiple_of=32,
            resize="upper_bound",
            output_kind="affine_disparity",
            description="MiDaS v2.1 small (EfficientNet-Lite3), 256 px, fast CPU default",
            notes=_SENTIS_NOTE,
        ),
        ModelEntry(
            name="midas-v21-small-isl",
            filename="midas_v21_small_isl.onnx",
            urls=(
                # The authors' v2_1 release asset; the repository was intel-isl/MiDaS when it
                # was published and GitHub redirects that older address to the same asset.
                "https://github.com/isl-org/MiDaS/releases/download/v2_1/model-small.onnx",
                "https://github.com/intel-isl/MiDaS/releases/download/v2_1/model-small.onnx",
            ),
            sha256=None,
            sha256_source=(
                "none published: the isl-org v2_1 release lists no checksum for model-small.onnx; "
                "refused unless M360_ALLOW_UNVERIFIED=1"
            ),
            size_bytes=66_845_081,
            licence="MIT",
            input_size=(256, 256),
            mean=IMAGENET_MEAN,
            std=IMAGENET_STD,
            multiple_of=32,
            resize="upper_bound",
            output_kind="affine_disparity",
            description="MiDaS v2.1 small, the authors' own ONNX export (unverified hash)",
            notes=(
                "Official isl-org file; the authors' export script (tf/make_onnx_model.py) bakes "
                "the ImageNet normalisation into the graph (m360 checks the graph on load)."
            ),
        ),
        ModelEntry(
            name="midas-v21-large",
            filename="midas_v21_384.onnx",
            urls=_sentis("midas_v21_384.onnx"),
            sha256="49c200fda47b9fe88f778acee05c1c773d555265122bcaa784e03298326c3b04",
            sha256_source=_SENTIS_HASH,
            size_bytes=416_000_000,
            licence="MIT",
            input_size=(384, 384),
            mean=IMAGENET_MEAN,
            std=IMAGENET_STD,
            multiple_of=32,
            resize="upper_bound",
            output_kind="affine_disparity",
            description="MiDaS v2.1 large (ResNeXt-101), 384 px",
            notes=_SENTIS_NOTE,
        ),
        ModelEntry(
            name="dpt-hybrid",
            filename="dpt_hybrid_midas.onnx",
            # Transformers.js repositories keep their exports in onnx/ only (no root copy); the
            # authors publish no ONNX of DPT-Hybrid.
            urls=(
                "https://huggingface.co/Xenova/dpt-hybrid-midas/resolve/"
                "c9ab952ed178a2f0c085a4602d0a9da35bc54bca/onnx/model.onnx",
            ),
            sha256="2eca68239006c64af94bdfa68464f34d7627c3dca7bb02932636e616c55a39ff",
            sha256_source=(
                "Hugging Face Git LFS pointer of onnx/model.onnx at revision c9ab952 "
                "(published by the host)"
            ),
            size_bytes=533_000_000,
            licence="MIT (MiDaS v3 weights, isl-org)",
            input_size=(384, 384),
            mean=(0.5, 0.5, 0.5),
            std=(0.5, 0.5, 0.5),
            multiple_of=32,
            resize="upper_bound",
            output_kind="affine_disparity",
            description="MiDaS v3 DPT-Hybrid (ViT-B + ResNet-50), 384 px",
            notes=(
                "Transformers.js export (Xenova/dpt-hybrid-midas) of Intel/dpt-hybrid-midas; "
                "dynamic input size, normalisation mean 0.5 / std 0.5 as DPT's preprocessor."
            ),
        ),
        ModelEntry(
            name="dpt-large",
            filename="dpt_large_384.onnx",
            urls=_sentis("dpt_large_384.onnx"),
            sha256="42b2e08dada8bd0e4612ac268f5f92c065389484c7e4cfab4ca8f3c32a13090f",
            sha256_source=_SENTIS_HASH,
            size_bytes=1_370_000_000,
            licence="MIT",
            input_size=(384, 384),
            mean=_HALF,
            std=_HALF,
            multiple_of=32,
            resize="upper_bound",
            output_kind="affine_disparity",
            description="MiDaS v3 DPT-Large (ViT-L/16), 384 px",
            notes=_SENTIS_NOTE,
        ),
        ModelEntry(
            name="depth-anything-v2-small",
            filename="depth_anything_v2_vits.onnx",
            # Only the repository root holds this export; the authors (DepthAnything/
            # Depth-Anything-V2) publish PyTorch weights only.
            urls=(
                "https://huggingface.co/yuvraj108c/Depth-Anything-2-Onnx/resolve/"
                "10c37c92fed4668c65c063f3acd7d04aad2c33a8/depth_anything_v2_vits.onnx",
            ),
            sha256="b47f3b67a5fadc18dec8cfae9954544182b79b57e8beedf6051a27cd73001c77",
            sha256_source=(
                "Hugging Face Git LFS pointer of this file at revision 10c37c9 (published by "
                "the host, size 101472019 bytes)"
            ),
            size_bytes=101_472_019,
            licence="Apache-2.0 (Small only: Depth-Anything-V2 Base/Large are CC-BY-NC-4.0)",
            input_size=(518, 518),
            mean=IMAGENET_MEAN,
            std=IMAGENET_STD,
            multiple_of=14,
            resize="lower_bound",
            output_kind="affine_disparity",
            description="Depth Anything V2 Small (ViT-S/14, relative), 518 px",
            notes=(
                "Community ONNX export (yuvraj108c/Depth-Anything-2-Onnx) of the official "
                "depth-anything/Depth-Anything-V2-Small weights; ImageNet normalisation outside "
                "the graph. Base and Large weights are non-commercial (CC-BY-NC-4.0) and are "
                "deliberately not registered."
            ),
        ),
    )
}

_verified: set[tuple[str, int, int]] = set()
_lock = threading.Lock()


def names() -> list[str]:
    """List the registered model names."""
    return list(REGISTRY)


def get(name: str) -> ModelEntry:
    """Look up the registry entry ``name`` (ModelError listing the known names if unknown)."""
    entry = REGISTRY.get(name) if isinstance(name, str) else None
    if entry is None:
        known = ", ".join(REGISTRY)
        raise ModelError(
            f"unknown model {name!r}: registered models are {known}; or pass a path to an "
            ".onnx file, or an object with predict(tiles) and output_kind"
        )
    return entry


def cache_dir() -> Path:
    """Folder of cached model files: ``$M360_HOME/models``, default the user cache dir."""
    return home_dir() / "models"


def _offline() -> bool:
    return os.environ.get("M360_OFFLINE", "").strip().lower() in {"1", "true", "yes", "on"}


def _allow_unverified() -> bool:
    value = os.environ.get("M360_ALLOW_UNVERIFIED", "").strip().lower()
    return value in {"1", "true", "yes", "on"}


def _candidates(entry: ModelEntry) -> Iterator[Path]:
    """Where a file may be: ``$M360_MODEL_DIR`` (manual copies) first, then the cache."""
    manual = os.environ.get("M360_MODEL_DIR")
    if manual:
        yield Path(manual).expanduser() / entry.filename
    yield cache_dir() / entry.filename


def local_path(entry: ModelEntry) -> Path | None:
    """Find an existing local copy of ``entry`` (not verified), or None."""
    for path in _candidates(entry):
        if path.is_file():
            return path
    return None


def is_cached(name: str) -> bool:
    """Whether a local copy of model ``name`` exists (its hash is checked on first use)."""
    return local_path(get(name)) is not None


def _where_to_put(entry: ModelEntry) -> str:
    target = cache_dir() / entry.filename
    where = entry.urls[0] if len(entry.urls) == 1 else "one of " + ", ".join(entry.urls)
    return (
        f"download it yourself from {where} and put it at {target} "
        f"(or in the folder named by M360_MODEL_DIR, or set M360_HOME)"
    )


def verify(entry: ModelEntry, path: str | os.PathLike[str]) -> Path:
    """Check a local file against ``entry``; returns the path or raises ModelError.

    The sha256 is computed once per process for a given (path, size, mtime); an entry without
    a published hash is refused unless ``M360_ALLOW_UNVERIFIED=1`` (then a warning prints the
    file's actual hash).
    """
    if not isinstance(entry, ModelEntry):
        raise InputError(f"entry must be a ModelEntry (models.get(name)), got {entry!r}")
    if not isinstance(path, (str, os.PathLike)):
        raise InputError(f"path must be a str or os.PathLike, got {type(path).__name__}")
    p = Path(path)
    try:
        stat = p.stat()
        regular = p.is_file()
    except (OSError, ValueError) as exc:  # missing, unreadable, a NUL in the name
        raise ModelError(f"model file {p} cannot be read ({exc}); {_where_to_put(entry)}") from exc
    if not regular:
        raise ModelError(f"model file {p} is not a regular file; {_where_to_put(entry)}")
    key = (str(p.resolve()), stat.st_size, stat.st_mtime_ns)
    with _lock:
        if key in _verified:
            return p
    problem = sniff_onnx(p)
    actual = sha256_of(p)
    if entry.sha256 is None:
        if not _allow_unverified():
            raise ModelError(
                f"model {entry.name!r}: no published sha256 could be confirmed for {p.name} "
                f"({entry.sha256_source}), so m360 will not load it. Its actual sha256 is "
                f"{actual}; if you trust the file, set M360_ALLOW_UNVERIFIED=1, or use a model "
                "with a verified hash (m360 models)"
            )
        warnings.warn(
            f"model {entry.name!r} loaded WITHOUT hash verification (M360_ALLOW_UNVERIFIED=1): "
            f"{p} has sha256 {actual}",
            UserWarning,
            stacklevel=3,
        )
    elif actual != entry.sha256:
        why = f"; {problem}" if problem else ""
        truncated = (
            f" (it is {stat.st_size} bytes, expected about {entry.size_bytes}: truncated?)"
            if entry.size_bytes and stat.st_size < 0.98 * entry.size_bytes
            else ""
        )
        raise ModelError(
            f"model file {p} fails its hash check{why}{truncated}: expected sha256 "
            f"{entry.sha256}, got {actual}. Delete it and run `m360 models fetch {entry.name}`, "
            f"or {_where_to_put(entry)}"
        )
    if problem:
        raise ModelError(f"model file {p} is not an ONNX model: {problem}; {_where_to_put(entry)}")
    with _lock:
        _verified.add(key)
    return p


def ensure(name: str, *, progress: bool = True) -> Path:
    """Get a verified local path of model ``name``, downloading it if needed (unless offline)."""
    entry = get(name)
    path = local_path(entry)
    if path is not None:
        return verify(entry, path)
    return fetch(name, progress=progress)


def fetch(name: str, *, progress: bool = True, force: bool = False) -> Path:
    """Download model ``name`` into the cache (atomic, with a progress bar) and verify it.

    Raises ModelError when offline (``M360_OFFLINE=1``), when every URL fails, or when the
    downloaded bytes do not match the expected sha256 (nothing is left in the cache then).
    """
    entry = get(name)
    target = cache_dir() / entry.filename
    if target.is_file() and not force:
        return verify(entry, target)
    if _offline():
        raise ModelError(
            f"model {entry.name!r} is not cached and M360_OFFLINE=1 forbids downloading it "
            f"(expected sha256 {entry.sha256 or 'unpublished'}): {_where_to_put(entry)}"
        )
    if entry.sha256 is None and not _allow_unverified():
        raise ModelError(
            f"model {entry.name!r} has no confirmed sha256 ({entry.sha256_source}); m360 will "
            "not download an unverifiable file unless M360_ALLOW_UNVERIFIED=1 is set"
        )
    target.parent.mkdir(parents=True, exist_ok=True)
    if force:
        target.unlink(missing_ok=True)
    tried: list[str] = []
    for url in entry.urls:
        why = _download(url, entry, target, progress)
        if why is None and entry.sha256 is None:  # no hash to catch an error page: sniff it
            problem = sniff_onnx(target)
            if problem:
                target.unlink(missing_ok=True)
                why = f"not an ONNX model: {problem}"
        if why is None:
            return verify(entry, target)
        tried.append(f"{len(tried) + 1}. {url}: {why}")
    plural = "s" if len(tried) > 1 else ""
    raise ModelError(
        f"could not download model {entry.name!r} (expected sha256 "
        f"{entry.sha256 or 'unpublished'}); tried {len(tried)} URL{plural}: "
        + "; ".join(tried)
        + f". Nothing was saved; {_where_to_put(entry)}"
    )


def _download(url: str, entry: ModelEntry, target: Path, progress: bool) -> str | None:
    """Download ``url`` to ``target`` checking the hash; None, or what went wrong."""
    import pooch
    import requests

    known_hash = f"sha256:{entry.sha256}" if entry.sha256 else None
    downloader = pooch.HTTPDownloader(progressbar=progress, timeout=_DOWNLOAD_TIMEOUT_S)
    logger = pooch.get_logger()
    level = logger.level
    logger.setLevel("WARNING")
    try:
        pooch.retrieve(
            url,
            known_hash=known_hash,
            fname=target.name,
            path=target.parent,
            downloader=downloader,
        )
    except ValueError as exc:  # pooch's hash mismatch: it removed the file
        got = re.search(r"but got ([0-9a-f]{64})", str(exc))
        return f"fails its hash check (got sha256 {got.group(1) if got else 'unknown'})"
    except requests.HTTPError as exc:
        status = exc.response.status_code if exc.response is not None else "?"
        reason = exc.response.reason if exc.response is not None else str(exc)
        return f"HTTP {status} {reason}".strip()
    except Exception as exc:  # network errors come in many types (requests, OSError, ...)
        return f"{type(exc).__name__}: {str(exc)[:200]}"
    finally:
        logger.setLevel(level)
    return None


#: ERP width whose default layout ``check`` reports the network size for.
CHECK_ERP_WIDTH = 2048
#: Smallest height of the probe views (tangents of a small ERP are enlarged to it).
_PROBE_MIN_HEIGHT = 240


def check(
    path: str | os.PathLike[str],
    *,
    erp_width: int = CHECK_ERP_WIDTH,
    model_options: ModelOptions | None = None,
    **keywords: Unpack[ModelKeywords],
) -> dict[str, Any]:
    """Say what m360 does with the ONNX file at ``path`` and what it needs (``m360 models check``).

    The file is loaded as :func:`m360.estimators.load_estimator` would (with a registry entry's
    settings when its sha256 matches one, then the options given), and probed:

    - sizes: one run at the network size m360 uses for the tangents of
      ``Layout.icosahedron(erp_width)`` (a panoramic model, ``kind="panoramic"``: for the
      ERP of that width); for a dynamic input size, runs near it at odd multiples
      of 1, 2, 4 … 128 (then 14, 28) give the multiple the size must be
      (:meth:`OnnxEstimator.size_rule`);
    - normalisation: what the graph holds (:func:`input_normalization`) and, when the graph does
      not normalise, which named normalisation (``imagenet``, ``unit``, ``none``) makes the
      output follow the depth of a synthetic corridor best;
    - output: its shape for the network size, its value range on the corridor and a guess of its
      kind (:func:`m360.estimators._probe.guess_kind`) with how sure it is. A panoramic model
      sees the corridor as one ERP panorama and its output is compared with the true radial
      distance (kinds ``affine_disparity``, ``disparity``, ``affine_depth``, ``distance``).

    Nothing here raises for a network that merely fails at run time: ``usable`` is False and
    ``problem`` says why.

    Parameters
    ----------
    path : str or PathLike
        The .onnx file.
    erp_width : int
        ERP width of the default layout (``Layout.icosahedron(erp_width)``) whose network size
        is probed.
    model_options : ModelOptions, optional
        The model options to check the file with (then give none as a keyword).
    **keywords
        The model options (:class:`ModelKeywords`), e.g. ``output_kind`` (what the model
        outputs, if known: wins over the registry's), ``multiple_of``, ``normalize``.

    Returns
    -------
    dict
        ``path``, ``size_bytes``, ``sha256``, ``registry`` (matching entry name or None),
        ``kind`` (``"tangent"`` or ``"panoramic"``), ``input`` (name, shape, layout, static,
        size), ``erp_width``, ``tangent_shape`` (a panoramic model: the ERP's shape),
        ``network_size`` (what m360 uses with the options given), ``network_size_runs`` (None
        or ONNX Runtime's reason), ``size_rule`` (the multiple a dynamic size needs; None for a
        fixed size or when no size runs), ``working_size`` (the size probed further),
        ``normalization`` (:meth:`Normalization.as_dict`), ``normalize_scores`` (rank
        correlation with depth per named normalisation), ``normalize_guess`` (a name or None),
        ``output_shape``, ``output_scale`` (output / input size), ``output_range`` (min,
        median, max on the corridor), ``output_finite``, ``output_kind`` and
        ``output_kind_source`` (``"user"``, ``"registry"`` or None), ``kind_guess``
        (:meth:`KindGuess.as_dict`), ``flags`` (the ``m360 run`` flags the file needs),
        ``options`` (the same as :class:`m360.ModelOptions` keywords), ``usable`` and
        ``problem``.

    Raises
    ------
    m360.ModelError
        When the file is missing, not ONNX, corrupt, or not a model m360 can feed.
    m360.InputError
        For unusable options.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise InputError(f"path must be a str or os.PathLike, got {type(path).__name__}")
    given = ModelOptions.build(model_options, **keywords).keywords()
    p = Path(path)
    if not is_file(p):
        raise ModelError(f"{p} does not exist (or is not a file)")
    problem = sniff_onnx(p)
    if problem:
        raise ModelError(f"{p} is not an ONNX model: {problem}")
    digest = sha256_of(p)
    entry = next((e for e in REGISTRY.values() if e.sha256 == digest), None)
    kind = given.get("output_kind")
    role = given.get("kind") or (entry.kind if entry is not None else "tangent")
    settings: dict[str, Any] = {}
    if entry is not None:
        settings = {
            "expected_normalization": (entry.mean, entry.std),
            "multiple_of": entry.multiple_of,
            "resize": entry.resize,
            "name": entry.name,
        }
    settings.update({k: v for k, v in given.items() if k not in ("output_kind", "kind")})
    onnx_class = PanoramicOnnxEstimator if role == "panoramic" else OnnxEstimator
    est = onnx_class(
        p,
        output_kind=kind or (entry.output_kind if entry else "affine_disparity"),
        sha256=digest,
        **settings,
    )
    if entry is not None and "input_size" not in given:
        # The registry's size is a default (a file's fixed size wins), as in load_estimator:
        # not a request that a fixed-size file would have to refuse.
        est.input_size = entry.input_size
    first = est.session.get_inputs()[0]
    layout = None if role == "panoramic" else Layout.icosahedron(erp_width)
    # A panoramic network's image is the whole ERP.
    tangent = (erp_width // 2, erp_width) if layout is None else layout.tangent_shape
    size = est.network_size(tangent)
    info: dict[str, Any] = {
        "path": str(p),
        "size_bytes": p.stat().st_size,
        "sha256": digest,
        "registry": entry.name if entry else None,
        "kind": role,
        "input": {
            "name": first.name,
            "shape": [d if isinstance(d, int) else str(d) for d in first.shape],
            "layout": est._input.layout,
            "static": est.fixed_size is not None,
            "size": None if est.fixed_size is None else list(est.fixed_size),
        },
        "erp_width": erp_width,
        "tangent_shape": list(tangent),
        "network_size": list(size),
        "degrees_per_pixel": round(pixel_degrees(layout, size[1]), 4),
        "network_size_runs": est.runs_at(size),
        "size_rule": est.size_rule(size),
        "normalization": est.normalization.as_dict(),
        "output_kind": kind or (entry.output_kind if entry else None),
        "output_kind_source": "user" if kind else "registry" if entry else None,
        "usable": True,
        "problem": None,
    }
    flags: dict[str, Any] = {}
    rule = info["size_rule"]
    if info["network_size_runs"] is not None:
        if rule is None or rule == 1:
            info["usable"] = False
            near = f"any size tried near {size[0]}x{size[1]}"
            where = "its fixed size" if est.fixed_size else near
            info["problem"] = (
                f"ONNX Runtime fails at {where} ({info['network_size_runs']}); m360 cannot run it"
            )
            return _finish(info, flags, given)
        est.multiple_of = math.lcm(est.multiple_of, rule)
        flags["multiple_of"] = est.multiple_of
    working = est.network_size(tangent)
    info["working_size"] = list(working)
    try:
        grey = est._run(est.network_input(np.full((1, *working, 3), 0.5, np.float32)))
    except ModelError as exc:  # an output that is not one map per image
        info.update(usable=False, problem=str(exc))
        return _finish(info, flags, given)
    info["output_shape"] = list(grey.shape)
    info["output_scale"] = [grey.shape[1] / working[0], grey.shape[2] / working[1]]
    _probe_scene(est, tangent, info, flags, given)
    return _finish(info, flags, given)


def _probe_scene(
    est: OnnxEstimator,
    tangent: tuple[int, int],
    info: dict[str, Any],
    flags: dict[str, Any],
    given: dict[str, Any],
) -> None:
    """Run the corridor views: the normalisation and output kind guesses, the value range."""
    from . import _probe

    h, w = tangent
    panoramic = est.kind == "panoramic"
    if panoramic:  # the corridor as one ERP at the network's size (its true radial distance)
        views = _probe.erp_views(est.network_size(tangent))
    else:
        grow = max(1.0, _PROBE_MIN_HEIGHT / h)
        views = _probe.views((round(h * grow), round(w * grow)))
    rgb = np.stack([v[0] for v in views])
    depths = [v[1] for v in views]
    current = (tuple(float(v) for v in est.mean), tuple(float(v) for v in est.std))
    candidates: dict[str, tuple[Any, Any]] = {"as given": current}
    if est.normalization.source != "graph" or est.normalization.explicit:
        candidates.update(NORMALIZE_PRESETS)
        same = [k for k, (m, s) in NORMALIZE_PRESETS.items() if (tuple(m), tuple(s)) == current]
        if same:  # no need to run twice
            del candidates["as given"]
    outputs: dict[str, list[np.ndarray] | str] = {}
    for name, (mean, std) in candidates.items():
        est.mean, est.std = np.asarray(mean, np.float64), np.asarray(std, np.float64)
        try:  # one view per run: a file may fix its batch at 1
            outputs[name] = [est._run(est.preprocess(view[None]))[0] for view in rgb]
        except ModelError as exc:
            outputs[name] = str(exc)
    est.mean, est.std = (np.asarray(v, np.float64) for v in current)
    if "as given" not in outputs:
        preset = next(
            k for k, (m, s) in NORMALIZE_PRESETS.items() if (tuple(m), tuple(s)) == current
        )
        outputs["as given"] = outputs[preset]
    scores = {
        name: _probe.guess_kind(out, depths, panoramic=panoramic).correlation
        for name, out in outputs.items()
        if not isinstance(out, str)
    }
    named = {k: v for k, v in scores.items() if k != "as given"}
    info["normalize_scores"] = {k: round(v, 3) for k, v in named.items()}
    # A declared kind says which way the output must follow depth (the shared FastDepth as a
    # panoramic depth falls with depth on raw 0-255 input, -0.77, and was told to take it).
    declared = given.get("output_kind") is not None or info["registry"] is not None
    direction = _probe.DEPTH_DIRECTION.get(est.output_kind, 0) if declared else 0
    guess = _probe.best_normalisation(named, direction)
    info["normalize_guess"] = guess
    chosen = "as given"
    # A registry entry knows its normalisation, and the user's explicit one wins: a hint only.
    if guess is not None and not est.normalization.explicit and info["registry"] is None:
        if tuple(NORMALIZE_PRESETS[guess][0]) != current[0] or tuple(
            NORMALIZE_PRESETS[guess][1]
        ) != tuple(current[1]):
            flags["normalize"] = guess
        chosen = guess
    elif est.normalization.explicit and given.get("normalize") in named:
        chosen = given["normalize"]
    out = outputs.get(chosen)
    if isinstance(out, str) or out is None:
        info.update(usable=False, problem=out or "the network did not run on the probe views")
        return
    values = np.concatenate([o.ravel() for o in out])
    finite = values[np.isfinite(values)]
    info["output_finite"] = bool(finite.size == values.size)
    info["output_range"] = (
        None
        if finite.size == 0
        else [float(finite.min()), float(np.median(finite)), float(finite.max())]
    )
    if finite.size == 0:
        info.update(usable=False, problem="the network's output is never finite")
    kind_guess = _probe.guess_kind(out, depths, panoramic=panoramic)
    info["kind_guess"] = kind_guess.as_dict()
    if info["output_kind"] is None and kind_guess.kind is not None:
        flags["output_kind"] = kind_guess.kind


def _finish(info: dict[str, Any], flags: dict[str, Any], given: dict[str, Any]) -> dict[str, Any]:
    """Add the flags (and the same as ModelOptions keywords) the user needs on top of ``given``."""
    info.setdefault("working_size", None)
    for key in ("output_shape", "output_scale", "output_range", "kind_guess", "normalize_guess"):
        info.setdefault(key, None)
    info.setdefault("normalize_scores", {})
    info.setdefault("output_finite", None)
    options = {**given, **flags}
    if info.get("kind") == "panoramic":
        options["kind"] = "panoramic"  # what `m360 run --model-kind panoramic` needs
    options.pop("providers", None)
    options.pop("threads", None)
    info["options"] = {k: list(v) if isinstance(v, tuple) else v for k, v in options.items()}
    info["flags"] = {k: info["options"][k] for k in flags}
    return info


def list_models() -> list[dict[str, Any]]:
    """One dict per registered model: name, size, licence, cached, verified hash, description."""
    rows = []
    for entry in REGISTRY.values():
        path = local_path(entry)
        rows.append(
            {
                "name": entry.name,
                "size_mb": None if entry.size_bytes is None else entry.size_bytes / 1e6,
                "licence": entry.licence,
                "input_size": entry.input_size,
                "output_kind": entry.output_kind,
                "kind": entry.kind,
                "sha256": entry.sha256,
                "cached": path is not None,
                "path": str(path if path is not None else cache_dir() / entry.filename),
                "description": entry.description,
            }
        )
    return rows


def _clear_verified() -> None:
    """Forget which files were verified in this process (tests)."""
    with _lock:
        _verified.clear()
