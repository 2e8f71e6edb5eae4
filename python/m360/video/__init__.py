"""360° video: depth for every frame that does not flicker, resumable (:func:`run`, ``m360 video``).

:mod:`~m360.video.reader` reads frames of video files (PyAV, extra ``m360[video]``) and of
folders of images (:func:`frames`); :mod:`~m360.video.temporal` is the temporal term that keeps
a frame consistent with the one before; :mod:`~m360.video.runner` runs a whole video with the
batch's guarantees (resume, claims, atomic writes, failures) and writes the preview video;
:mod:`~m360.video.chunks` runs a video in chunks, on Ray (``engine="ray"``) or here.
"""

from __future__ import annotations

from .reader import VIDEO_SUFFIXES, Frame, Source, frames, probe
from .runner import RUN_FILE, STATE_SUFFIX, VideoReport, frame_stem, run
from .temporal import TEMPORAL_MODES, Temporal, TemporalState, scene_cut

__all__ = [
    "RUN_FILE",
    "STATE_SUFFIX",
    "TEMPORAL_MODES",
    "VIDEO_SUFFIXES",
    "Frame",
    "Source",
    "Temporal",
    "TemporalState",
    "VideoReport",
    "frame_stem",
    "frames",
    "probe",
    "run",
    "scene_cut",
]
