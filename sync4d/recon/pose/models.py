"""Where the learned pose models live and how they are loaded (LiteRT, no network).

The models are MediaPipe's legacy BlazePose files, taken from the ``mediapipe==0.10.14`` wheel by
``make models`` (Apache-2.0; the licence is copied next to them as ``LICENSE.mediapipe``):

* ``pose_detection.tflite``: person detector, 224x224 input, 2254 SSD anchors, 4 keypoints per box.
* ``pose_landmark_full.tflite``: 256x256 crop -> 39 landmarks (x, y, z, visibility, presence), 39 metric
  world landmarks, a 256x256 person segmentation and a pose-presence score.

They run under ``ai-edge-litert`` (LiteRT) in the main environment, beside protobuf 7 and numpy 2;
``mediapipe`` itself is not installed (it needs protobuf < 5, which tensorboard refuses).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from sync4d.errors import DataMissingError
from sync4d.paths import PROJECT_ROOT

DEFAULT_MODEL_DIR = PROJECT_ROOT / "models" / "mediapipe"
DETECTOR_FILE = "pose_detection.tflite"
LANDMARK_FILE = "pose_landmark_full.tflite"


def model_dir(path: str = "") -> Path:
    """The model folder: ``path`` if given, else ``$SYNC4D_MODEL_DIR``, else ``<project>/models/mediapipe``."""
    if path:
        return Path(path).expanduser()
    env = os.environ.get("SYNC4D_MODEL_DIR")
    return Path(env).expanduser() if env else DEFAULT_MODEL_DIR


def model_path(name: str, folder: str = "") -> Path:
    """Path of one model file; one clear line naming what to run when it is missing.

    Raises:
        DataMissingError: the file is not there.
    """
    path = model_dir(folder) / name
    if not path.is_file():
        raise DataMissingError(
            f"pose model {path} not found; run `make models` (extracts it from the mediapipe==0.10.14 wheel)"
        )
    return path


class TFLiteModel:
    """One .tflite model under LiteRT: ``run(x)`` returns the outputs by tensor name.

    Args:
        path: the .tflite file.
        threads: CPU threads for the XNNPACK delegate.
    """

    def __init__(self, path: Path, *, threads: int = 1) -> None:
        try:
            from ai_edge_litert.interpreter import Interpreter
        except ImportError as err:  # pragma: no cover - a broken setup, not a user input
            raise DataMissingError(
                f"ai-edge-litert is not installed ({err}); run `make venv` (requirements.txt pins ai-edge-litert)"
            ) from err
        self.path = path
        self._interp = Interpreter(model_path=str(path), num_threads=threads)
        self._interp.allocate_tensors()
        self._input = self._interp.get_input_details()[0]
        self._outputs = self._interp.get_output_details()

    def run(self, x: np.ndarray) -> dict[str, np.ndarray]:
        """Run on one (1, H, W, 3) float32 input; returns {output tensor name: array (copied)}."""
        self._interp.set_tensor(self._input["index"], np.ascontiguousarray(x, dtype=np.float32))
        self._interp.invoke()
        return {d["name"]: np.array(self._interp.get_tensor(d["index"])) for d in self._outputs}


def load_models(folder: str = "", *, threads: int = 1) -> tuple[Any, Any]:
    """(detector, landmark model) as :class:`TFLiteModel`; fails with one line if either file is missing."""
    det = model_path(DETECTOR_FILE, folder)
    lmk = model_path(LANDMARK_FILE, folder)
    return TFLiteModel(det, threads=threads), TFLiteModel(lmk, threads=threads)
