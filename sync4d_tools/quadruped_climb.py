"""Is the truth the quadruped objective's minimum? The from-scratch hypotheses against the fit started at the truth.

    python -m sync4d_tools.quadruped_climb --clip outputs/q36/fox_walk_side --save hyps.pt          # main's search
    python -m sync4d_tools.quadruped_climb --clip outputs/q36/fox_walk_side --load hyps.pt \\
        --set inside_weight=0.2 --steps 60 --pick 0,4                                                # re-judged
    python -m sync4d_tools.quadruped_climb --clip outputs/q36/fox_walk_side --headings [--pick 0]    # every heading
    python -m sync4d_tools.quadruped_climb --clip outputs/q36/fox_walk_side --gap                    # B -> rest split

The first form runs the fit's search (first-frame starts, ``tracks`` tracks refined on the clip, each with its
legs swapped: the hypotheses) with the defaults, saves them and scores each (loss, optical-flow error, mpjpe
in % of the height as ``body_suite`` scores). Both forms then fit ``B`` (the template fitted to the truth joints
under the fit's priors, then the silhouette clip fit from there, as ``body_suite --split`` does) and, with
``--load``, refine every saved hypothesis the same ``--steps`` under the configuration given by ``--set``: the
truth is the objective's minimum on this clip when B's loss is below every hypothesis'. ``--headings`` instead
tracks every start heading (or those ``--pick`` names) as the fit tracks its best ``tracks``, and scores each
with its gait cue (:func:`gait_cue`), loss, flow error and mpjpe (the truth's heading printed first). ``--gap``
splits the gap between B and the rest pose at the true root (:func:`gap`): the truth's first frame tracked as the
fit tracks, with and without the first-frame schedule, the legs' or the torso's true rotations only, the first
frame alone wrong, one tracking step from the truth; each row with its per-frame error. Prints JSON rows.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sync4d.recon.pose import quadruped_fit as qf
from sync4d.recon.pose.templates import LEG_PREFIXES
from sync4d_tools import camera_of, video_of
from sync4d_tools import body_suite as bs


class Clip:
    """A rendered quadruped clip and the fit's problem on it."""

    def __init__(self, folder: Path, cfg: qf.QuadrupedFitConfig) -> None:
        source, self.truth, self.names, self.w2c = bs.load_quadruped_clip(folder)
        clip = video_of(source)
        self.masks = clip.masks
        self.prob = qf.QuadrupedProblem(clip.masks, camera_of(source), cfg, frames=clip.frames,
                                        extrinsics=clip.extrinsics, fps=source.fps)
        tmpl = self.prob.tt.template
        self.ids = [tmpl.names.index(dict(tmpl.vocabulary)[n]) for n in self.names]
        self.frames = np.arange(len(self.truth))

    def score(self, params: qf.Params) -> dict:
        with torch.no_grad():
            joints = qf.pose_body(self.prob.tt, params)[0].numpy().astype(np.float64)
        return bs.joint_score(bs.first_camera_to_world(joints[:, self.ids], self.w2c[0]), self.truth)

    def terms(self, params: qf.Params) -> dict:
        """The silhouette's cross-entropy (unweighted) and the grid IoU."""
        prob = self.prob
        with torch.no_grad():
            _, verts = qf.pose_body(prob.tt, params)
            occ = qf.body_silhouette(prob, verts, prob.cams_of(self.frames), params["log_scale"].exp())
            tgt = prob.target[self.frames]
            bce = -(tgt * torch.log(occ.clamp(1e-5)) + (1 - tgt) * torch.log((1 - occ).clamp(1e-5))).mean()
            iou = (((occ > 0.5) & (tgt > 0.5)).sum(1) / ((occ > 0.5) | (tgt > 0.5)).sum(1)).float().mean()
        return {"bce": round(float(bce), 4), "iou": round(float(iou), 3)}


def truth_started(c: Clip, cfg: qf.QuadrupedFitConfig, steps: int) -> dict:
    """``B``: A2 (the template fitted to the truth joints under the priors), girth, then ``steps`` clip steps."""
    truth_cam = np.einsum("ij,tkj->tki", c.w2c[0][:3, :3], c.truth) + c.w2c[0][:3, 3]
    params = bs.truth_start(c.prob, truth_cam, c.names, c.w2c[0][:3, :3] @ np.array([0.0, 1.0, 0.0]))
    bs.fit_to_truth(c.prob, params, torch.tensor(truth_cam, dtype=qf.DTYPE), c.ids, cfg, True)
    qf.run_steps(c.prob, c.frames, params, cfg, 60, free=("log_thick", "log_girth"))
    loss = qf.run_steps(c.prob, c.frames, params, cfg, steps)[0]
    return {"what": "B (truth-started)", "loss": round(loss, 4), **c.terms(params), **c.score(params)}


def search(c: Clip, cfg: qf.QuadrupedFitConfig) -> list[tuple[str, qf.Params]]:
    """The fit's hypotheses (heading / legs swapped, parameters), as :func:`qf.best_hypothesis` makes them."""
    up_cam = c.w2c[0][:3, :3] @ np.array([0.0, 1.0, 0.0])
    starts = qf.first_frame_starts(c.prob, c.masks[0], up_cam, cfg)
    out = []
    for _, k, params in sorted(starts, key=lambda x: x[0])[: cfg.tracks]:
        full = qf.track(c.prob, params, cfg, len(c.frames))
        qf.run_steps(c.prob, c.frames, full, cfg, cfg.iterations)
        for pairs in ((), ("f",), ("h",), ("f", "h")):
            trial = {**full, "local": qf.swap_legs(c.prob.tt, full["local"].detach(), pairs)}
            out.append((f"{360 * k / cfg.starts:.0f} deg, swapped {'+'.join(pairs) or 'none'}",
                        {n: v.detach().clone().requires_grad_(True) for n, v in trial.items()}))
    return out


def feet_motion(prob: qf.QuadrupedProblem, band: float = 0.2) -> torch.Tensor | None:
    """(T-1, 2) optical flow [px] of the mask's lowest cells (the bottom ``band`` of its height each frame: the paws
    near the ground) minus the mean flow of the whole mask; None without the video's frames."""
    if prob.flow is None:
        return None
    out = []
    for t in range(len(prob.flow)):
        inside = prob.target[t] > 0.5
        v = prob.uv[:, 1][inside]
        feet = prob.uv[:, 1] >= v.max() - band * (v.max() - v.min())
        out.append(prob.flow[t][inside & feet].mean(0) - prob.flow[t][inside].mean(0))
    return torch.stack(out)


def gait_cue(prob: qf.QuadrupedProblem, feet: torch.Tensor | None, params: qf.Params) -> float:
    """The gait cue of a start [grid cells a frame]: the paws' motion relative to the body (:func:`feet_motion`) along
    the image motion the start predicts for its paws' centre stepping a tenth of the body length toward its head
    (through each frame's camera; a one-frame start held over the clip), weighted by that motion's image length.
    Negative when the start faces the way the animal walks: a paw on the ground moves toward the tail relative to
    the body, in place or across the image. 0 without the video's frames. A diagnostic (results page): as the
    starts' ranking it helped three rendered rows and hurt two."""
    if feet is None:
        return 0.0
    tmpl = prob.tt.template
    paws = [int(tmpl.leg(p)[-1]) for p in LEG_PREFIXES]
    with torch.no_grad():
        joints = qf.pose_body(prob.tt, params)[0]
        joints = joints.expand(len(prob.target), *joints.shape[1:]) if len(joints) == 1 else joints
        paw = joints[:, paws].mean(1)
        step = 0.1 * (joints[:, tmpl.head] - joints[:, tmpl.tail])
        uv = qf.project_points(qf.to_cameras(torch.stack([paw, paw + step], 1), prob.cams), prob.K)[:-1]
        ahead = uv[:, 1] - uv[:, 0]
        along = (feet * ahead).sum() / ahead.norm(dim=-1).sum().clamp_min(1e-9)
    return float(along) / (2 * prob.tau)


def true_heading(c: Clip, up_cam: np.ndarray) -> float:
    """The truth's first-frame heading [deg] in the starts' convention (0 = :func:`qf.heading_rotation`'s angle 0):
    the pelvis-to-neck direction about the camera-frame up."""
    from scipy.spatial.transform import Rotation

    truth_cam = c.truth[0] @ c.w2c[0][:3, :3].T + c.w2c[0][:3, 3]
    fwd = truth_cam[c.names.index("neck")] - truth_cam[c.names.index("pelvis")]
    base = Rotation.from_rotvec(qf.heading_rotation(up_cam, 0.0)).as_matrix()
    local = base.T @ fwd  # template axes: facing -x, +z the left
    return float(np.degrees(np.arctan2(local[2], -local[0])) % 360)


def every_heading(c: Clip, cfg: qf.QuadrupedFitConfig, save: str | None, pick: list[int] | None = None) -> list[dict]:
    """Every start heading tracked and refined as :func:`qf.best_hypothesis` does the best ``tracks``: per heading and
    leg swap the clip loss, the cross-entropy, the optical-flow error and the mpjpe (the climb's step "true masks
    and camera, the heading given" is the row of the true heading)."""
    up_cam = c.w2c[0][:3, :3] @ np.array([0.0, 1.0, 0.0])
    truth = true_heading(c, up_cam)
    print(json.dumps({"true_heading_deg": round(truth, 1)}), flush=True)
    starts = qf.first_frame_starts(c.prob, c.masks[0], up_cam, cfg)
    feet = feet_motion(c.prob)
    rows, kept = [], []
    for first, k, params in starts:
        if pick is not None and k not in pick:
            continue
        cue = gait_cue(c.prob, feet, params)
        full = qf.track(c.prob, params, cfg, len(c.frames))
        loss = qf.run_steps(c.prob, c.frames, full, cfg, cfg.iterations)[0]
        kept.append({n: v.detach().clone() for n, v in full.items()})
        for pairs in ((), ("f",), ("h",), ("f", "h")):
            trial = {**full, "local": qf.swap_legs(c.prob.tt, full["local"].detach(), pairs)}
            rows.append({"heading": 360 * k / cfg.starts, "swapped": "+".join(pairs) or "none",
                         "first_loss": round(first, 4), "gait_cue": round(cue, 3), "loss": round(loss, 4),
                         "flow_error": round(qf.flow_error(c.prob, trial), 4), **c.terms(trial), **c.score(trial)})
            print(json.dumps(rows[-1]), flush=True)
    if save:
        torch.save({"true_heading_deg": truth, "tracks": kept}, save)
    return rows


def a2_params(c: Clip, cfg: qf.QuadrupedFitConfig) -> qf.Params:
    """A2: the template fitted to the truth joints of every frame under the fit's priors, then its girth (60 clip
    steps with only the girths free), as :func:`truth_started` starts B."""
    truth_cam = np.einsum("ij,tkj->tki", c.w2c[0][:3, :3], c.truth) + c.w2c[0][:3, 3]
    params = bs.truth_start(c.prob, truth_cam, c.names, c.w2c[0][:3, :3] @ np.array([0.0, 1.0, 0.0]))
    bs.fit_to_truth(c.prob, params, torch.tensor(truth_cam, dtype=qf.DTYPE), c.ids, cfg, True)
    qf.run_steps(c.prob, c.frames, params, cfg, 60, free=("log_thick", "log_girth"))
    return params


def first_frame_fit(c: Clip, params: qf.Params, cfg: qf.QuadrupedFitConfig) -> qf.Params:
    """The fit's first-frame schedule (:func:`qf.first_frame_starts`) on a one-frame start: rigid, then all free."""
    qf.run_steps(c.prob, np.arange(1), params, cfg, cfg.start_iterations // 2, free=qf.RIGID)
    qf.run_steps(c.prob, np.arange(1), params, cfg, cfg.start_iterations - cfg.start_iterations // 2)
    return params


def per_frame(c: Clip, params: qf.Params) -> list[float]:
    """mpjpe % of the height per frame, after the one similarity for the clip (the score's alignment)."""
    from sync4d_tools.evaluate.recon_joints import joint_errors

    with torch.no_grad():
        joints = qf.pose_body(c.prob.tt, params)[0].numpy().astype(np.float64)
    height = float((c.truth[..., 1].max(1) - c.truth[..., 1].min(1)).max())
    err = joint_errors(bs.first_camera_to_world(joints[:, c.ids], c.w2c[0]), c.truth)
    return [round(100 * float(e) / height, 1) for e in err.mean(1)]


def gap_row(c: Clip, cfg: qf.QuadrupedFitConfig, what: str, params: qf.Params, *, tracked: bool = True) -> dict:
    """Score a clip's parameters (after the fit's clip steps when ``tracked``), with its per-frame error."""
    loss = qf.run_steps(c.prob, c.frames, params, cfg, cfg.iterations if tracked else 0)[0]
    shape = {k: round(float(params[p].detach().exp()), 3) for k, p in (("scale", "log_scale"), ("girth", "log_thick"))}
    row = {"what": what, "loss": round(loss, 4), **c.terms(params), **c.score(params), **shape,
           "per_frame": per_frame(c, params)}
    print(json.dumps(row), flush=True)
    return row


def rest_at(params: qf.Params, keep: np.ndarray | None = None) -> qf.Params:
    """Leaf copies of one-frame ``params`` with every joint's rotation at rest but those in ``keep``."""
    out = {k: v.detach().clone() for k, v in params.items()}
    local = torch.zeros_like(out["local"])
    if keep is not None:
        local[:, keep] = out["local"][:, keep]
    out["local"] = local
    return {k: v.requires_grad_(True) for k, v in out.items()}


def oracle_steps(c: Clip, a2: qf.Params, cfg: qf.QuadrupedFitConfig) -> qf.Params:
    """Each frame t > 0 warm-started from the truth's frame t - 1 (A2) and run as the fit's tracking runs it."""
    frames = [qf.frame_params(a2, 0)]
    for t in range(1, len(c.frames)):
        cur = qf.frame_params(a2, t - 1)
        hist = qf.history_of(c.prob, [qf.frame_params(a2, s) for s in range(max(0, t - 2), t)])
        with torch.no_grad():
            prev = qf.pose_body(c.prob.tt, qf.frame_params(a2, t - 1))[1]
        qf.run_steps(c.prob, np.array([t]), cur, cfg, cfg.frame_iterations, history=hist, prev=prev)
        frames.append(cur)
    return {k: (torch.cat([p[k].detach() for p in frames]) if k not in qf.CLIP else a2[k].detach().clone()
                ).requires_grad_(True) for k in a2}


def gap(c: Clip, cfg: qf.QuadrupedFitConfig, quick: bool = False) -> list[dict]:
    """The gap between B (started at the truth) and the rest pose at the true heading, split by what is given;
    ``quick``: only A2, the truth's frame 0 tracked and one tracking step from the truth (the rows an objective
    is judged by first)."""
    n, tmpl = len(c.frames), c.prob.tt.template
    a2 = a2_params(c, cfg)
    rows = [gap_row(c, cfg, "A2 (truth under the priors), no silhouette steps", a2, tracked=False)]
    first = qf.frame_params(a2, 0)
    rows.append(gap_row(c, cfg, "truth's frame 0 as is, the fit's tracking", qf.track(c.prob, first, cfg, n)))
    if quick:
        rows.append(gap_row(c, cfg, "each frame one tracking step from the truth's previous frame (no clip steps)",
                            oracle_steps(c, a2, cfg), tracked=False))
        return rows
    f0 = first_frame_fit(c, qf.frame_params(a2, 0), cfg)
    rows.append(gap_row(c, cfg, "truth's frame 0 + the first-frame schedule, the fit's tracking",
                        qf.track(c.prob, f0, cfg, n)))
    legs = first_frame_fit(c, rest_at(qf.frame_params(a2, 0), tmpl.leg_joints), cfg)
    rows.append(gap_row(c, cfg, "true root, legs' true phase, rest elsewhere; schedule, tracking",
                        qf.track(c.prob, legs, cfg, n)))
    other = np.setdiff1d(np.arange(len(tmpl.parents)), tmpl.leg_joints)
    body = first_frame_fit(c, rest_at(qf.frame_params(a2, 0), other), cfg)
    rows.append(gap_row(c, cfg, "true root, spine/head/tail true, legs at rest; schedule, tracking",
                        qf.track(c.prob, body, cfg, n)))
    rest = first_frame_fit(c, rest_at(qf.frame_params(a2, 0)), cfg)
    grown = qf.track(c.prob, rest, cfg, n)
    rows.append(gap_row(c, cfg, "true root, rest pose; schedule, tracking", grown))
    spliced = {k: v.detach().clone() for k, v in a2.items()}
    for k in ("root_rot", "root_pos", "local"):
        spliced[k][0] = rest[k].detach()[0]
    rows.append(gap_row(c, cfg, "rest-grown frame 0, the truth's later frames (no steps)",
                        {k: v.requires_grad_(True) for k, v in spliced.items()}, tracked=False))
    rows.append(gap_row(c, cfg, "each frame one tracking step from the truth's previous frame (no clip steps)",
                        oracle_steps(c, a2, cfg), tracked=False))
    return rows


def config_from(sets: list[str]) -> qf.QuadrupedFitConfig:
    """The defaults with ``name=value`` fields set, each read as its default's type (``True``/``False`` for a flag:
    ``bool("False")`` would be true)."""
    base = qf.QuadrupedFitConfig()
    over: dict[str, Any] = {}
    for name, value in (s.split("=", 1) for s in sets):
        kind = type(getattr(base, name))
        if kind is bool and value not in ("True", "False"):
            raise ValueError(f"quadruped_climb: {name} is a flag: True or False, got {value!r}")
        over[name] = value == "True" if kind is bool else kind(value)
    return qf.QuadrupedFitConfig(**over)


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clip", required=True, help="a rendered quadruped clip (body_suite's folder)")
    parser.add_argument("--save", help="run the defaults' search and save its hypotheses here (.pt)")
    parser.add_argument("--load", help="hypotheses saved by --save, refined under --set")
    parser.add_argument("--set", nargs="*", default=[], help="QuadrupedFitConfig fields, name=value")
    parser.add_argument("--steps", type=int, default=140, help="clip steps for B and each loaded hypothesis")
    parser.add_argument("--headings", action="store_true", help="track every start heading (no B); --save keeps them")
    parser.add_argument("--gap", action="store_true", help="split the gap between B and the rest pose at the true root")
    parser.add_argument("--quick", action="store_true", help="with --gap: only A2, the truth's frame 0 tracked, one step")
    parser.add_argument("--pick", default="", help="comma-separated indices of the loaded hypotheses (with --headings: of the start headings)")
    args = parser.parse_args(argv)
    if args.quick and not args.gap:
        parser.error("--quick shortens --gap only; add --gap")
    cfg = config_from(args.set)
    c = Clip(Path(args.clip), cfg)
    if args.gap:
        return gap(c, cfg, args.quick)
    if args.headings:
        return every_heading(c, cfg, args.save, [int(i) for i in args.pick.split(",")] if args.pick else None)
    rows = [truth_started(c, cfg, args.steps)]
    print(json.dumps(rows[-1]), flush=True)
    if args.save:
        hyps = search(c, cfg)
        torch.save([(name, {k: v.detach() for k, v in p.items()}) for name, p in hyps], args.save)
        for name, p in hyps:
            rows.append({"what": name, "loss": round(qf.run_steps(c.prob, c.frames, p, cfg, 0)[0], 4),
                         "flow_error": round(qf.flow_error(c.prob, p), 4), **c.terms(p), **c.score(p)})
            print(json.dumps(rows[-1]), flush=True)
    if args.load:
        saved = torch.load(args.load)
        keep = [int(i) for i in args.pick.split(",")] if args.pick else range(len(saved))
        for i in keep:
            name, p = saved[i]
            p = {k: v.clone().requires_grad_(True) for k, v in p.items()}
            loss = qf.run_steps(c.prob, c.frames, p, cfg, args.steps)[0]
            rows.append({"what": name, "loss": round(loss, 4), **c.terms(p), **c.score(p)})
            print(json.dumps(rows[-1]), flush=True)
    return rows


if __name__ == "__main__":
    main()
