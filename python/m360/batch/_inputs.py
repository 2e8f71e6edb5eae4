"""What a batch takes from its inputs: folder scans and manifests (used by ``batch.collect``).

A folder scan takes the files with an image suffix (:data:`m360.io.decode.IMAGE_SUFFIXES`) and
leaves out, with the reason, m360's own outputs (by name) and depth maps (by their header,
:func:`m360.io.decode.image_header`: a single-channel PNG or TIFF of 16 bits or more, a
single-channel EXR; a panorama photo has three channels).
A file named on the command line or in a manifest is always tried.

A manifest is checked whole before anything is made: text that is not UTF-8, control characters
(a NUL, binary bytes), a line longer than two paths can be, or two lines writing the same
output make it a usage error (:class:`m360.InputError`) naming the line.
"""

from __future__ import annotations

import csv
import re
from pathlib import Path, PurePath

from ..errors import InputError, ReadError
from ..io import FORMAT_SUFFIXES, QUANTITIES
from ..io.decode import IMAGE_SUFFIXES, image_header
from .image import PATH_MAX

#: The longest manifest line (bytes): an input and an output path of PATH_MAX each.
MAX_LINE = 2 * PATH_MAX
#: The ends of the names of m360's own image outputs: left out of folder scans.
OUTPUT_TAILS = (
    *(
        f".{q}{s}"
        for q in (*QUANTITIES, "confidence")
        for s in sorted(set(FORMAT_SUFFIXES.values()))
    ),
    ".preview.png",
)
_CONTROL = re.compile(r"[\x00-\x08\x0b-\x1f\x7f]")  # tab and line breaks are text
#: Formats a depth map comes in (PNG, OpenEXR, TIFF): only their headers are read.
_DEPTH_MAP_MAGIC = (b"\x89PNG\r\n\x1a\n", b"\x76\x2f\x31\x01", b"II*\x00", b"MM\x00*")


# --------------------------------------------------------------------------------------------
# Folder scans.


def scan(folder: Path, *, recursive: bool) -> tuple[list[Path], list[tuple[Path, str]]]:
    """List the images of ``folder`` in sorted order, and the files left out with the reason."""
    pattern = folder.rglob("*") if recursive else folder.glob("*")
    images: list[Path] = []
    left_out: list[tuple[Path, str]] = []
    for path in sorted(pattern):
        try:
            if path.suffix.lower() not in IMAGE_SUFFIXES or not path.is_file():
                continue
        except OSError:  # a path the OS cannot take (too long): not an input
            continue
        reason = leave_out(path)
        if reason is None:
            images.append(path)
        else:
            left_out.append((path, reason))
    return images, left_out


def leave_out(path: Path) -> str | None:
    """Tell why a folder scan leaves ``path`` out (an m360 output, a depth map); None to take it.

    An m360 output by its name (``STEM.depth.EXT``, ``STEM.disparity.EXT``,
    ``STEM.confidence.EXT``, ``STEM.preview.png``); a depth map by its header. A file that
    cannot be read is taken: it fails when it is read, with the reason.
    """
    name = path.name.lower()
    for tail in OUTPUT_TAILS:
        if name.endswith(tail) and len(name) > len(tail):
            return f"an m360 output (*{tail})"
    try:
        with open(path, "rb") as f:
            magic = f.read(8)
            if not magic.startswith(_DEPTH_MAP_MAGIC):  # JPEG, HDR …: photos, read no further
                return None
            header = image_header(f)
    except OSError:
        return None
    if header is not None and header.channels == 1 and header.sample_bytes >= 2:
        wide = header.kind == "exr" or header.sample_bytes == 4  # 32-bit samples: floats
        bits = "float" if wide else f"{8 * header.sample_bytes}-bit"
        return f"a single-channel {bits} {header.kind.upper()}: a depth map, not a photo"
    return None


# --------------------------------------------------------------------------------------------
# Manifests.


def read_manifest(path: Path) -> list[tuple[int, Path, PurePath]]:
    """Read and check a ``.txt`` or ``.csv`` manifest whole: (line, input, output) per entry.

    Raises
    ------
    m360.ReadError
        If the file cannot be read.
    m360.InputError
        If it is not a manifest (not UTF-8, control characters, a line longer than
        :data:`MAX_LINE` bytes, a CSV row that cannot be parsed) or two lines write one output.
    """
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ReadError(f"cannot read the manifest {path}: {exc.strerror or exc}") from exc
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        where = data[: exc.start].count(b"\n") + 1
        raise InputError(
            f"manifest {path}, line {where}: not UTF-8 text (byte 0x{data[exc.start]:02x}); a "
            "manifest is a text file with one path (.txt) or input,output (.csv) per line"
        ) from None
    lines = re.split(r"\r\n|\r|\n", text)
    for number, line in enumerate(lines, 1):
        size = len(line.encode("utf-8", "surrogatepass"))
        if size > MAX_LINE:
            raise InputError(
                f"manifest {path}, line {number}: {size} bytes, longer than two paths can be "
                f"({MAX_LINE}); is it a manifest?"
            )
        bad = _CONTROL.search(line)
        if bad:
            code = ord(bad.group())
            raise InputError(
                f"manifest {path}, line {number}: holds the control character U+{code:04X}"
                f"{' (NUL)' * (code == 0)}; is it a manifest (a text file)?"
            )
    entries = _txt(path, lines) if path.suffix.lower() == ".txt" else _csv(path, lines)
    first: dict[PurePath, int] = {}
    for number, _, output in entries:
        if output in first:
            raise InputError(
                f"manifest {path}: lines {first[output]} and {number} both write the output "
                f"{output}; give each input its own output (a .csv manifest: input,output)"
            )
        first[output] = number
    return entries


def _txt(path: Path, lines: list[str]) -> list[tuple[int, Path, PurePath]]:
    entries = []
    for number, line in enumerate(lines, 1):
        entry = line.strip()
        if entry and not entry.startswith("#"):
            source = path.parent / entry
            entries.append((number, source, PurePath(source.stem)))
    return entries


def _csv(path: Path, lines: list[str]) -> list[tuple[int, Path, PurePath]]:
    entries = []
    reader = csv.reader(lines)
    try:
        for row in reader:
            number = reader.line_num
            cells = [c.strip() for c in row]
            if not cells or not cells[0] or cells[0].startswith("#"):
                continue
            if number == 1 and cells[0].lower() == "input":
                continue  # header
            source = path.parent / cells[0]
            output = cells[1] if len(cells) > 1 and cells[1] else source.stem
            entries.append((number, source, PurePath(output)))
    except csv.Error as exc:
        raise InputError(f"manifest {path}, line {reader.line_num}: {exc}") from None
    return entries
