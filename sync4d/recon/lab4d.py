"""``recon=lab4d``: import a Lab4D reconstruction as an articulated reference.

Layouts (read by :mod:`sync4d.io.lab4d`):

* **Lab4D export**: rest mesh ``fg.obj``; ``fg-motion.json`` ``field2cam`` (T x 4 x 4) becomes G_t (the
  "world" of the reference is then the camera of each frame) and ``t_articulation`` (T x K x 4 x 4)
  becomes J_{t,b} (rest -> t, object frame). Skinning: ``fg-skin.npy`` (V x K) when present, else fitted
  per vertex to the posed meshes ``fg-%05d.obj`` with the file's transforms held fixed
  (non-negative least squares, rows summing to 1). Bone Gaussians are the skinning-weighted mean and
  covariance of the rest vertices.
* **Per-frame layout** (``gengshan-y/ppr-diffphys``, MIT; e.g. ``lab4d_export/shiba-haru-1002``):
  posed meshes, ``se3`` bone transforms, ``cam`` files and ``val-rest-skin.npy``. It has no rest mesh;
  when the bone count of the transforms equals the skinning's columns, the rest shape is frame 0
  un-skinned (inverse of the blended transform) and the import is checked against every frame.

Inconsistent inputs (e.g. shiba-haru-1002: 25 bone transforms but 13 skinning columns) follow
``on_mismatch``: ``error`` (default) raises :class:`~sync4d.errors.InputError` saying what disagrees;
``refit`` ignores the file's bones and skinning and fits ``bones`` Gaussian bones to the posed meshes
with ``recon=skinning_fit`` (the choice is logged).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from scipy.optimize import nnls

from sync4d.errors import InputError
from sync4d.io.lab4d import Lab4DExport, read_lab4d_export
from sync4d.recon import skinning as sk
from sync4d.recon.skinning_fit import FitOptions, bbox_diagonal, fit_skinning, parse_bones, reference_from_fit
from sync4d.registry import register
from sync4d.types import Reference, ReferenceInput

log = logging.getLogger(__name__)


def fit_weights_fixed_transforms(
    rest: np.ndarray, posed: np.ndarray, transforms: np.ndarray, *, sum_weight: float = 100.0
) -> np.ndarray:
    """Per-vertex skinning weights reproducing posed frames with known bone transforms.

    Solves, per vertex, ``min_w sum_t || sum_b w_b J_{t,b} x - y_t ||^2`` with ``w >= 0`` and
    ``sum_b w_b = 1`` (the equality enforced by a heavily weighted extra row).

    Args:
        rest: (V, 3) rest vertices [m].
        posed: (T, V, 3) posed vertices in the object frame [m].
        transforms: (T, B, 4, 4) bone transforms rest -> t.
        sum_weight: weight of the sum-to-one row (relative to metres).

    Returns:
        (V, B) weights, rows sum to 1.
    """
    n_frames, n_verts, _ = posed.shape
    n_bones = transforms.shape[1]
    # moved[v, t, b] = J_{t,b} x_v
    moved = np.einsum("tbij,vj->vtbi", transforms[..., :3, :3], rest) + transforms[None, :, :, :3, 3]
    out = np.zeros((n_verts, n_bones))
    scale = max(bbox_diagonal(rest), 1e-9)
    for v in range(n_verts):
        a = moved[v].transpose(0, 2, 1).reshape(n_frames * 3, n_bones) / scale
        b = posed[:, v].reshape(-1) / scale
        a = np.vstack([a, np.full((1, n_bones), sum_weight)])
        b = np.append(b, sum_weight)
        w, _ = nnls(a, b)
        total = w.sum()
        out[v] = w / total if total > 0 else np.full(n_bones, 1.0 / n_bones)
    return out


def weighted_bones(rest: np.ndarray, weights: np.ndarray, *, floor: float) -> tuple[np.ndarray, np.ndarray]:
    """Bone centres (B, 3) [m] and covariances (B, 3, 3) [m^2]: skinning-weighted moments of the rest shape.

    Covariance eigenvalues are floored at ``floor``^2 so every bone is positive definite.
    """
    mass = np.maximum(weights.sum(0), 1e-12)
    centers = (weights.T @ rest) / mass[:, None]
    covs = np.zeros((weights.shape[1], 3, 3))
    for b in range(weights.shape[1]):
        d = rest - centers[b]
        c = (weights[:, b, None] * d).T @ d / mass[b]
        evals, evecs = np.linalg.eigh(0.5 * (c + c.T))
        covs[b] = (evecs * np.maximum(evals, floor**2)) @ evecs.T
    return centers, covs


def unskin(posed: np.ndarray, weights: np.ndarray, transforms: np.ndarray) -> np.ndarray:
    """(V, 3) rest points whose LBS with ``weights`` and (B, 4, 4) ``transforms`` gives ``posed`` (V, 3)."""
    blended = np.einsum("vb,bij->vij", weights, transforms)
    return np.linalg.solve(blended[:, :3, :3], (posed - blended[:, :3, 3])[..., None])[..., 0]


@register("recon", "lab4d")
class Lab4DReconstructor:
    """Import a Lab4D export folder (``ReferenceInput.path``) as a reference."""

    @dataclass
    class Config(FitOptions):
        """``recon=lab4d`` options (the :class:`FitOptions` are used by ``on_mismatch: refit``).

        Attributes:
            on_mismatch: ``error`` (raise, naming what disagrees) or ``refit`` (fit ``bones`` bones to the
                posed meshes with skinning_fit, ignoring the file's bones and skinning).
            bones: bone count for ``refit``: an int, ``"auto"``, or ``"file"`` (the skinning's column count).
            tolerance_pct: an imported reference must reproduce the posed meshes within this mean vertex
                error [% of the bbox diagonal], else it is treated as a mismatch.
            posed_frame: frame of the export layout's posed meshes ``fg-%05d.obj``: ``object`` (Lab4D
                writes the deformed mesh in the object/field frame) or ``camera`` (already moved by
                ``field2cam``).
            bone_floor: smallest std-dev of a bone Gaussian, as a fraction of the bbox diagonal.
            auto_tolerance_pct: as in ``recon=skinning_fit`` (for ``bones: auto``).
            auto_candidates: as in ``recon=skinning_fit``.
        """

        on_mismatch: Literal["error", "refit"] = "error"
        bones: Any = "file"
        tolerance_pct: float = 2.0
        posed_frame: Literal["object", "camera"] = "object"
        bone_floor: float = 0.01
        auto_tolerance_pct: float = 1.5
        auto_candidates: list[int] = field(default_factory=lambda: [2, 3, 4, 5, 6, 8, 10, 13, 16, 20, 25])

        def validate(self) -> None:
            if self.bones != "file":
                self.bones = parse_bones(self.bones)

    def __init__(self, config: Config, *, device: str = "cpu") -> None:
        config.validate()
        self.config = config
        self.device = device
        self.last_fit_report: dict[str, Any] = {}

    def reconstruct(self, source: ReferenceInput) -> Reference:
        """Read ``source.path`` and return the imported (or refitted) reference, validated."""
        if not source.path:
            raise InputError(f"recon=lab4d needs the export folder, but reference '{source.name}' has no path; "
                             "use reference=lab4d")
        export = read_lab4d_export(source.path)
        problem = self.consistency_problem(export)
        if problem is None:
            ref, err = self._import(export, source)
            if err is None or err <= self.config.tolerance_pct:
                self.last_fit_report = {"mode": "import", "mean_error_pct": err, "bones": ref.num_bones}
                log.info("lab4d: imported %s (%d bones, mean error %s %%)", export.path, ref.num_bones, err)
                return ref
            problem = (f"the imported bones and skinning reproduce the posed meshes with a mean error of {err:.2f}% "
                       f"of the bbox diagonal (tolerance {self.config.tolerance_pct}%)")
        if self.config.on_mismatch == "error":
            raise InputError(
                f"recon=lab4d: {export.path}: {problem}; fix the export, or set recon.on_mismatch=refit to fit "
                "new bones to the posed meshes"
            )
        return self._refit(export, source, problem)

    @staticmethod
    def consistency_problem(export: Lab4DExport) -> str | None:
        """A sentence naming what disagrees in the export, or None when it can be imported as is."""
        transforms = export.bone_transforms
        if transforms is None:
            return "no per-bone transforms (t_articulation / se3 files)"
        k_bones = transforms.shape[1]
        k_skin = None if export.rest_skinning is None else export.rest_skinning.shape[1]
        if k_skin is not None and k_skin != k_bones:
            return (f"the bone transforms hold {k_bones} bones but the rest skinning has {k_skin} columns, "
                    "so skinning column b cannot be matched to a bone transform")
        if export.rest_skinning is not None:
            sums = export.rest_skinning.sum(1)
            if export.rest_skinning.min() < -1e-6 or not np.allclose(sums, 1.0, atol=1e-3):
                return f"the rest skinning rows do not sum to 1 (sums in [{sums.min():.3g}, {sums.max():.3g}])"
        if export.rest_vertices is None and export.rest_skinning is None:
            return "neither a rest mesh nor rest skinning, so the bones cannot be tied to the meshes"
        if export.rest_skinning is None and export.posed_vertices is None:
            return "no skinning weights (fg-skin.npy) and no posed meshes (fg-%05d.obj) to fit them from"
        if export.posed_vertices is not None and export.posed_vertices.shape[0] != transforms.shape[0]:
            return f"{export.posed_vertices.shape[0]} posed meshes but bone transforms for {transforms.shape[0]} frames"
        return None

    def _import(self, export: Lab4DExport, source: ReferenceInput) -> tuple[Reference, float | None]:
        """Build the reference from the file's transforms; returns it and its mean error [% diag] or None."""
        transforms = export.bone_transforms
        assert transforms is not None
        n_frames = transforms.shape[0]
        if export.layout == "export":
            glob = export.object_to_camera if export.object_to_camera is not None else np.tile(np.eye(4), (n_frames, 1, 1))
        else:
            glob = np.tile(np.eye(4), (n_frames, 1, 1))  # per-frame meshes and se3 share one frame
        glob = sk.project_to_rigid(glob)
        rest = export.rest_vertices
        weights = export.rest_skinning
        if rest is None:
            assert weights is not None and export.posed_vertices is not None
            local0 = export.posed_vertices[0]  # per-frame layout: meshes and se3 share one frame (G = I)
            rest = unskin(local0, weights, transforms[0])
        local = None
        if export.posed_vertices is not None and export.layout == "export" and self.config.posed_frame == "object":
            local = export.posed_vertices
        elif export.posed_vertices is not None:
            inv = sk.rigid_inverse(glob)
            local = np.einsum("tij,tvj->tvi", inv[:, :3, :3], export.posed_vertices) + inv[:, None, :3, 3]
        if weights is None:
            assert local is not None
            log.info("lab4d: no skinning file; fitting weights to %d posed meshes with the file's transforms", n_frames)
            weights = fit_weights_fixed_transforms(rest, local, transforms)
        diag = bbox_diagonal(rest)
        centers, covs = weighted_bones(rest, weights, floor=self.config.bone_floor * diag)
        err = None
        if local is not None:
            posed = sk.linear_blend(rest, weights, transforms)
            err = float(100.0 * np.linalg.norm(posed - local, axis=-1).mean() / diag)
        ref = Reference(
            rest_vertices=rest, rest_faces=export.faces, bone_centers=centers, bone_covariances=covs,
            skinning=weights / weights.sum(1, keepdims=True), bone_transforms=transforms, global_transforms=glob,
            fps=source.fps, vertex_colors=export.colors, name=source.name,
        ).validate()
        return ref, err

    def _refit(self, export: Lab4DExport, source: ReferenceInput, problem: str) -> Reference:
        if export.posed_vertices is None:
            raise InputError(f"recon=lab4d: {export.path}: {problem}, and there are no posed meshes to refit from")
        from sync4d.recon.skinning_fit import choose_bones

        bones = self.config.bones
        if bones == "file":
            counted = export.rest_skinning if export.rest_skinning is not None else export.bone_transforms
            if counted is None:
                raise InputError(f"recon=lab4d: {export.path}: {problem}; recon.bones=file needs a skinning or "
                                 "transform file to count the bones: set recon.bones to a number")
            bones = counted.shape[1]
        log.warning("lab4d: %s: %s; on_mismatch=refit: fitting %s bones to the %d posed meshes",
                    export.path, problem, bones, export.posed_vertices.shape[0])
        opts = FitOptions(**{k: getattr(self.config, k) for k in FitOptions.__dataclass_fields__})
        curve: list[tuple[int, float]] = []
        if bones == "auto":
            fit, curve = choose_bones(export.posed_vertices, list(self.config.auto_candidates),
                                      self.config.auto_tolerance_pct, opts)
        else:
            fit = fit_skinning(export.posed_vertices, int(bones), opts)
        self.last_fit_report = {
            "mode": "refit", "problem": problem, "bones": int(fit.centers.shape[0]),
            "mean_error_pct": fit.mean_error_pct, "frame_error_pct": fit.frame_error_pct.tolist(),
            "bones_curve": curve,
        }
        return reference_from_fit(fit, faces=export.faces, fps=source.fps, name=source.name, colors=export.colors)
