"""Which way the target faces, told by how thick its lone limbs are (a cue beside the assignment's cost).

The structure match scores each turn of the target by where its limbs leave the trunk, where they end and
where their feet point (:func:`sync4d.match.structure.score_turns`). A quadruped stretching (front legs
along the floor, hind quarters high, the tail raised) fits the reference better turned round: its raised
tail takes the head and its low head the tail. The limbs without a left/right partner (a head, a tail)
tell the two ends apart by their thickness, which the pose does not change: a dog's head is about half as
thick as its trunk, its tail about a fifth. Partner limbs are left out: legs front and back are alike, and
their small differences would turn a cow whose front and hind legs the assignment swaps.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from sync4d.match.regions import limb_thickness


def part_radius(points: np.ndarray, labels: np.ndarray, parts: list[int] | tuple[int, ...]) -> float:
    """The median distance of the points of ``parts`` from their own part's principal axis (a capsule's
    radius); NaN if no part has 10 points."""
    dist = []
    for p in parts:
        q = points[labels == p]
        if len(q) < 10:
            continue
        q = q - q.mean(axis=0)
        axis = np.linalg.svd(q, full_matrices=False)[2][0]
        dist.append(np.linalg.norm(q - np.outer(q @ axis, axis), axis=1))
    return float(np.median(np.concatenate(dist))) if dist else float("nan")


def reference_thickness(points: np.ndarray, labels: np.ndarray, limb_parts: list[list[int]], trunk: list[int]
                        ) -> np.ndarray:
    """(L,) each reference limb's radius over the trunk's (:func:`part_radius` on its surface points)."""
    body = part_radius(points, labels, trunk)
    return np.array([part_radius(points, labels, parts) / body for parts in limb_parts])


def target_thickness(thickness: np.ndarray, members: tuple[np.ndarray, ...], core: np.ndarray) -> np.ndarray:
    """(T,) each candidate's thickness (:func:`sync4d.match.regions.limb_thickness`) over the thickness at the
    trunk's core: an inscribed ball's radius, as a capsule's radius is."""
    core_thickness = max(float(thickness[core].max()), 1e-12)
    return np.array([limb_thickness(thickness, m) / core_thickness for m in members])


def thickness_disagreement(pairs: list[tuple[int, int]], ref: np.ndarray, tgt: np.ndarray, lone: set[int]) -> float:
    """The mean squared log ratio of the target's to the reference's thickness over the (limb, candidate)
    ``pairs`` whose limb is in ``lone``; NaN if none is."""
    logs = [np.log(max(tgt[c], 1e-9) / max(ref[r], 1e-9)) ** 2 for r, c in pairs if r in lone and np.isfinite(ref[r])]
    return float(np.mean(logs)) if logs else float("nan")


def face_by_thickness(turns: list[Any], ref: np.ndarray, tgt: np.ndarray, lone: set[int]) -> list[Any]:
    """``turns`` (best first, each (score, rotation, pairs, cost)) with the best turn at least 90 deg from the
    first put first when its lone limbs' thickness agrees better (:func:`thickness_disagreement`) with the
    reference's; unchanged when either turn matches no lone limb or they agree as well (the same branches
    matched on both sides, e.g. a head that stays a head)."""
    first = turns[0][1]
    far = next((t for t in turns if float(np.trace(t[1] @ first.T)) <= 1.0 + 1e-9), None)
    if far is None:
        return turns
    here, there = (thickness_disagreement(t[2], ref, tgt, lone) for t in (turns[0], far))
    if np.isfinite(here) and np.isfinite(there) and there < here:
        return [far] + [t for t in turns if t is not far]
    return turns
