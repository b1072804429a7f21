"""The video front end: a phone video in, the subject's masks and the camera out, before any
reconstruction (shared by every subject kind).

Modules: :mod:`~sync4d.frontend.config` (options), :mod:`~sync4d.frontend.stage` (``run_front_end``),
:mod:`~sync4d.frontend.checks` (refusals), :mod:`~sync4d.frontend.tracks` (corner tracks),
:mod:`~sync4d.frontend.camera` and :mod:`~sync4d.frontend.bundle` (the camera),
:mod:`~sync4d.frontend.motion` (what moves against the background), :mod:`~sync4d.frontend.parallax` and
:mod:`~sync4d.frontend.sweep` (the parts that never move), :mod:`~sync4d.frontend.segment` (GrabCut and propagation), :mod:`~sync4d.frontend.person` (people), :mod:`~sync4d.frontend.outputs`
(``masks.mp4``, ``camera.json``).
"""

from sync4d.frontend.config import CameraConfig, FrontEndConfig, SubjectConfig
from sync4d.frontend.stage import FrontEndResult, Prompt, complete_video, complete_video_up, run_front_end

__all__ = ["CameraConfig", "FrontEndConfig", "FrontEndResult", "Prompt", "SubjectConfig", "complete_video",
           "complete_video_up", "run_front_end"]
