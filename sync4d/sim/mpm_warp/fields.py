"""Velocity fields of multi-field MPM (Bardenhagen et al. 2000; Nairn 2013): touching parts that are not joined
do not share grid velocities.

With one velocity grid, two parts a few millimetres apart share grid nodes and P2G/G2P average their velocities:
they glue, and a drive that moves them apart shears and tears the glued layers. Here each part gets one of at most
:data:`MAX_FIELDS` fields by greedy colouring of the conflict graph (parts that touch at rest, within
:data:`TOUCH_CELLS` grid cells, and are not parent and child in the part tree). Every field has its own grid
momentum and mass: a particle scatters into and gathers from its own field only, so different fields move
independently where they overlap (no contact between fields: they may pass through each other if driven
into each other).

Joined parts (parent and child) share a field whenever the colouring allows; those that do not are bonded at their
joint: a particle within :data:`BOND_CELLS` cells of its joined part in another field is flagged, P2G accumulates
each field's flagged mass per node, and at a node where two or more fields carry flagged mass (at least
:data:`BOND_SHARE` of their own mass there) those fields move with their common mass-weighted velocity
(:func:`kernels.grid_update`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)

#: The most velocity fields a model uses (parts that would need more share the least conflicting field).
MAX_FIELDS = 4
#: Parts touch when particles of the two lie within this many grid cells of each other at rest.
TOUCH_CELLS = 1.5
#: A particle is flagged for bonding within this many cells of the joined part (in another field).
BOND_CELLS = 2.0
#: A field takes part in a node's bond when its flagged mass there is at least this share of its node mass.
BOND_SHARE = 0.1


@dataclass(frozen=True)
class FieldSplit:
    """Each particle's velocity field and bond flag.

    Attributes:
        field: (P,) field of each particle, in [0, num_fields).
        bond: (P,) 1.0 for a particle within :data:`BOND_CELLS` cells of a joined part in another field, else 0.0.
        part_field: (B,) field of each part.
        num_fields: fields in use (>= 2: a model with one field carries no split).
    """

    field: np.ndarray
    bond: np.ndarray
    part_field: np.ndarray
    num_fields: int

    @property
    def bonding(self) -> bool:
        """Whether any particle is flagged (the kernels then accumulate flagged mass)."""
        return bool(self.bond.any())


def cross_pairs(points: np.ndarray, part: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pairs (i, j, distance [m]) of particles of two different parts (both >= 0) within ``reach`` [m]."""
    from scipy.spatial import cKDTree

    own = np.flatnonzero(part >= 0)
    ij = cKDTree(points[own]).query_pairs(reach, output_type="ndarray")
    i, j = own[ij[:, 0]], own[ij[:, 1]]
    cross = part[i] != part[j]
    i, j = i[cross], j[cross]
    return i, j, np.linalg.norm(points[i] - points[j], axis=1)


def colour_parts(conflict: np.ndarray, parent: np.ndarray, max_fields: int = MAX_FIELDS) -> np.ndarray:
    """(B,) field of each part: greedy colouring of the symmetric (B, B) ``conflict`` graph.

    Parts are coloured parents first (breadth first from the roots); each takes its parent's field when no
    conflicting part holds it, else the lowest free one; with none free (more than ``max_fields`` would be
    needed) the field shared with the fewest conflicting parts (those glue, as on one grid; logged).
    """
    num = len(parent)
    children: list[list[int]] = [[] for _ in range(num)]
    for c, p in enumerate(parent):
        if p >= 0:
            children[int(p)].append(c)
    order: list[int] = []
    for root in [b for b in range(num) if parent[b] < 0] + list(range(num)):
        if root in order:
            continue
        queue = [root]
        while queue:
            b = queue.pop(0)
            if b not in order:
                order.append(b)
                queue.extend(children[b])
    colour = np.full(num, -1, dtype=np.int64)
    for b in order:
        taken = np.bincount(colour[conflict[b] & (colour >= 0)], minlength=max_fields)[:max_fields]
        p = int(parent[b])
        if p >= 0 and taken[colour[p]] == 0:
            colour[b] = colour[p]
        elif (taken == 0).any():
            colour[b] = int(np.argmax(taken == 0))
        else:
            colour[b] = int(np.argmin(taken))
            log.warning("sim: part %d shares field %d with %d touching parts it is not joined to (more than %d "
                        "fields would be needed)", b, colour[b], int(taken[colour[b]]), max_fields)
    return colour


def field_split(points: np.ndarray, part: np.ndarray, parent: np.ndarray, dx: float) -> FieldSplit | None:
    """The fields of particles at rest ``points`` (P, 3) [m] labelled ``part`` (P,) (-1: no part, field 0) with
    the part tree ``parent`` (B,) (-1: a root) on a grid of cell ``dx`` [m]; None when one field suffices."""
    part = np.asarray(part, dtype=np.int64)
    parent = np.asarray(parent, dtype=np.int64)
    num_parts = max(len(parent), int(part.max()) + 1 if len(part) else 0)
    parent = np.concatenate([parent, np.full(num_parts - len(parent), -1)])
    i, j, d = cross_pairs(points, part, max(TOUCH_CELLS, BOND_CELLS) * dx)
    touch = np.zeros((num_parts, num_parts), dtype=bool)
    close = d <= TOUCH_CELLS * dx
    touch[part[i[close]], part[j[close]]] = True
    touch = touch | touch.T
    joined = np.zeros_like(touch)
    child = np.flatnonzero(parent >= 0)
    joined[child, parent[child]] = joined[parent[child], child] = True
    colour = colour_parts(touch & ~joined, parent)
    if colour.max(initial=0) == 0:
        return None
    own = part >= 0
    field = np.where(own, colour[np.where(own, part, 0)], 0)
    # flagged: near a joined part that lies in another field
    band = (d <= BOND_CELLS * dx) & joined[part[i], part[j]] & (colour[part[i]] != colour[part[j]])
    bond = np.zeros(len(points))
    bond[i[band]] = 1.0
    bond[j[band]] = 1.0
    return FieldSplit(field.astype(np.int64), bond, colour, int(colour.max()) + 1)
