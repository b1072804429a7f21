"""Does the video's optical flow agree with the truth's image motion on a rendered quadruped clip, and which cells lie?

    python -m sync4d_tools.quadruped_flow --clip /work/scratch/qp/dog_front [/work/scratch/qp/fox_walk_orbit ...]

For each clip (``body_suite``'s folder, true masks and camera): A2 (the template fitted to the truth joints under
the fit's priors, :func:`sync4d_tools.quadruped_climb.a2_params`) stands in for the truth; its image motion
(:func:`quadruped_fit.predicted_flow`) is compared with the fit's DIS flow on the cells the fit trusts (on the mask,
landing on it, back within 1 px, covered by the body), in grid cells (the flow term's unit). The motion is predicted
three ways (:func:`camera_check`): through the given per-frame cameras (what the fit does), with the camera taken as
static, and through the inverted relative cameras; a frame or sign error in the fit's camera handling would put the
given row above one of the others. Then the residual is split by the quartiles of three per-cell trust features
(:func:`trust_features`): the forward-backward error [px], the texture (the smaller structure-tensor eigenvalue of
the grey frame, OpenCV's ``cornerMinEigenVal``) and the distance inside the mask [px]: a trust test is useful when
its worst quartile holds the large residuals. Prints one JSON row per clip.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from sync4d.recon.pose import quadruped_fit as qf


def flow_residual(prob: qf.QuadrupedProblem, params: qf.Params, cams: torch.Tensor | None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(T-1, P) distance [grid cells] between the video's flow and the image motion of ``params`` seen by ``cams``
    ((T, 4, 4) first camera -> frame t camera, None = static), where it is evaluated ((T-1, P) bool: the fit's
    trusted cells, covered by the body), and (T-1, P) the predicted motion's length [grid cells]."""
    if prob.flow is None or prob.flow_ok is None:
        raise ValueError("quadruped_flow: the problem has no video frames (no flow)")
    saved = prob.cams
    prob.cams = cams
    try:
        with torch.no_grad():
            _, verts = qf.pose_body(prob.tt, params)
            flow, body = qf.predicted_flow(prob, verts, params["log_scale"].exp())
    finally:
        prob.cams = saved
    cell = 2 * prob.tau
    keep = (body > 0.5) & prob.flow_ok & (prob.target[:-1] > 0.5)
    return ((flow - prob.flow).norm(dim=-1) / cell).numpy(), keep.numpy(), (flow.norm(dim=-1) / cell).numpy()


def summary(residual: np.ndarray) -> dict:
    """Median, mean and the share above one grid cell of residuals [grid cells]."""
    if residual.size == 0:
        return {"median": None, "mean": None, "above_1_cell": None, "cells": 0}
    return {"median": round(float(np.median(residual)), 3), "mean": round(float(residual.mean()), 3),
            "above_1_cell": round(float((residual > 1).mean()), 3), "cells": int(residual.size)}


def camera_check(prob: qf.QuadrupedProblem, params: qf.Params) -> dict:
    """:func:`summary` of the residual with the motion seen through the given cameras, a static camera and, when the
    camera moves, the inverted relative cameras (each on its own trusted, covered cells)."""
    variants: dict[str, torch.Tensor | None] = {"given": prob.cams, "static": None}
    if prob.cams is not None:
        variants["inverse"] = torch.linalg.inv(prob.cams)
    out = {}
    for key, cams in variants.items():
        res, keep, _ = flow_residual(prob, params, cams)
        out[key] = summary(res[keep])
    return out


def trust_features(frames: np.ndarray, uv: np.ndarray, masks: np.ndarray) -> dict[str, np.ndarray]:
    """Per frame pair and cell (T-1, P): ``fb`` the forward-backward error of the DIS flow [px], ``texture`` the
    smaller eigenvalue of the grey frame's structure tensor (9 px window), ``inside`` the distance inside the mask
    [px] (0 off it), all at frame t."""
    import cv2

    # OpenCV's stubs omit the DIS optical flow factory that the module has.
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)  # type: ignore[attr-defined]
    grey = [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in frames]
    h, w = grey[0].shape

    def pixel(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.clip(p[:, 1].astype(int), 0, h - 1), np.clip(p[:, 0].astype(int), 0, w - 1)

    fb, tex, inside = [], [], []
    for t in range(len(grey) - 1):
        fwd = dis.calc(grey[t], grey[t + 1], None)[pixel(uv)]
        back = dis.calc(grey[t + 1], grey[t], None)[pixel(uv + fwd)]
        fb.append(np.linalg.norm(fwd + back, axis=1))
        tex.append(cv2.cornerMinEigenVal(grey[t].astype(np.float32), 9, ksize=3)[pixel(uv)])
        inside.append(cv2.distanceTransform(masks[t].astype(np.uint8), cv2.DIST_L2, 3)[pixel(uv)])
    return {"fb": np.stack(fb), "texture": np.stack(tex), "inside": np.stack(inside)}


def by_quartile(feature: np.ndarray, residual: np.ndarray) -> list[float | None]:
    """Mean residual in each quartile of ``feature`` (lowest first); None for an empty quartile."""
    bins = np.digitize(feature, np.quantile(feature, [0.25, 0.5, 0.75]))
    return [round(float(residual[bins == b].mean()), 3) if (bins == b).any() else None for b in range(4)]


def check_clip(folder: Path) -> dict:
    """The camera check and the trust features' quartiles of one rendered clip, at A2 (the module docstring)."""
    from sync4d.io.video import read_video_clip
    from sync4d_tools import quadruped_climb as qc

    cfg = qf.QuadrupedFitConfig()
    c = qc.Clip(folder, cfg)
    a2 = qc.a2_params(c, cfg)
    prob = c.prob
    res, keep, motion = flow_residual(prob, a2, prob.cams)
    frames = read_video_clip(folder / "rgb.mp4", folder / "masks").frames
    feats = trust_features(frames, prob.uv.numpy(), c.masks)
    inside = (prob.target[:-1] > 0.5).numpy()
    assert prob.flow is not None and prob.flow_ok is not None  # flow_residual has checked
    row: dict = {"clip": folder.name, "cell_px": round(2 * prob.tau, 2), "a2_mpjpe_pct": c.score(a2)["mpjpe_pct_height"],
                 "moving_camera": prob.cams is not None, **camera_check(prob, a2),
                 "trusted_share_of_mask": round(float(prob.flow_ok.numpy()[inside].mean()), 3),
                 "flow_length_cells": round(float((prob.flow.norm(dim=-1) / (2 * prob.tau)).numpy()[keep].mean()), 3),
                 "truth_motion_cells": round(float(motion[keep].mean()), 3)}
    for name, feat in feats.items():
        row[f"residual_by_{name}_quartile"] = by_quartile(feat[keep], res[keep])
    return row


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clip", nargs="+", required=True, help="rendered quadruped clips (body_suite's folders)")
    args = parser.parse_args(argv)
    rows = []
    for folder in args.clip:
        rows.append(check_clip(Path(folder)))
        print(json.dumps(rows[-1]), flush=True)
    return rows


if __name__ == "__main__":
    main()
