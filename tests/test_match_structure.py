"""Structure-aware matching: curve skeleton, reference limbs, branch assignment, the benchmark's labels."""

from __future__ import annotations

import json

import numpy as np
import pytest

from sync4d.errors import InputError
from sync4d.match import MatchConfig, match_parts
from sync4d.match.surface_points import skeleton_points
from sync4d.match.structure import assign_limbs, reference_limbs, yaw_rotations
from sync4d.match.skeleton import SkeletonConfig, curve_skeleton, volume_points
from sync4d.types import Reference, TargetGaussians
from sync4d_tools.match_labels.procedural import box_union

PARTS = ("trunk", "leg_fl", "leg_fr", "leg_bl", "leg_br", "head", "tail")


def animal(leg: float = 0.35, head: float = 0.12, body: float = 0.6) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A box animal facing -x (Y up): trunk, four legs of length ``leg``, a head of size ``head``, a tail."""
    top, w = leg + 0.2, 0.05
    boxes = [("trunk", (-body / 2, leg, -0.12), (body / 2, top, 0.12))]
    for name, x, z in (
        ("leg_fl", -body / 2, 0.07),
        ("leg_fr", -body / 2, -0.12),
        ("leg_bl", body / 2 - w, 0.07),
        ("leg_br", body / 2 - w, -0.12),
    ):
        boxes.append((name, (x, 0.0, z), (x + w, leg + 0.01, z + w)))
    boxes.append(("head", (-body / 2 - head - 0.05, top - 0.05, -head / 2), (-body / 2 + 0.01, top + head, head / 2)))
    boxes.append(("tail", (body / 2 - 0.01, top - 0.05, -0.02), (body / 2 + 0.3, top - 0.01, 0.02)))
    v, f, names = box_union(boxes, max_edge=0.04)
    return v, f, np.array([PARTS.index(n) for n in names])


def box_reference(v: np.ndarray, f: np.ndarray, part: np.ndarray, *, parents: bool = True) -> Reference:
    b = len(PARTS)
    return Reference(
        rest_vertices=v,
        rest_faces=f,
        bone_centers=np.stack([v[part == i].mean(0) for i in range(b)]),
        bone_covariances=np.tile(np.eye(3) * 1e-3, (b, 1, 1)),
        skinning=np.eye(b)[part],
        bone_transforms=np.tile(np.eye(4), (1, b, 1, 1)),
        global_transforms=np.eye(4)[None],
        fps=30.0,
        bone_names=PARTS,
        bone_parents=np.array([-1, 0, 0, 0, 0, 0, 0]) if parents else None,
    ).validate()


def gaussians_at(points: np.ndarray) -> TargetGaussians:
    n = len(points)
    return TargetGaussians(
        means=points,
        quats=np.tile([1.0, 0, 0, 0], (n, 1)),
        log_scales=np.full((n, 3), -4.0),
        opacity_logits=np.full(n, 3.0),
        sh=np.zeros((n, 1, 3)),
    ).validate()


def test_volume_points_fill_the_solid_and_the_skeleton_separates_the_limbs() -> None:
    v, f, part = animal()
    pts = volume_points(v, f, 48, np.random.default_rng(0))
    lo, hi = v.min(0), v.max(0)
    assert ((pts >= lo - 0.05) & (pts <= hi + 0.05)).all()
    # the trunk's centre is inside the solid (filled), not only its skin
    assert np.linalg.norm(pts - [0.0, 0.45, 0.0], axis=1).min() < 0.03
    sk = curve_skeleton((pts - pts.mean(0)) / np.sqrt(((pts - pts.mean(0)) ** 2).sum(1).mean()), SkeletonConfig())
    from scipy.spatial import cKDTree

    owner = part[cKDTree(v).query(pts)[1]]
    # each leg's lower half lies in one terminal branch, and the four legs in four different ones
    low = pts[:, 1] < 0.15
    legs = []
    for leg in (1, 2, 3, 4):
        branches = sk.branch[low & (owner == leg)]
        main = np.bincount(branches).argmax()
        assert (branches == main).mean() > 0.9
        legs.append(main)
    assert len(set(legs)) == 4


def test_solid_depth_and_the_trunk_core() -> None:
    """Depth: one voxel at the skin, half the thickness at the middle; the core sits in the trunk and the
    levels measured from it give every leg its own terminal branch holding most of the leg (levels from
    the centre point also separate this long-legged box; on Spot they do not: docs/results/matching.md)."""
    from sync4d.match.skeleton import fill_solid, trunk_core

    box = np.random.default_rng(0).random((20000, 3)) * [1.0, 0.4, 0.4]
    skin = np.concatenate(
        [np.column_stack([box[:, 0], np.full(len(box), y), box[:, 2]]) for y in (0.0, 0.4)]
        + [np.column_stack([box[:, 0], box[:, 1], np.full(len(box), z)]) for z in (0.0, 0.4)]
        + [np.column_stack([np.full(len(box), x), box[:, 1], box[:, 2]]) for x in (0.0, 1.0)]
    )
    pts, depth = fill_solid(skin, 0.02, with_depth=True)
    assert depth.min() == pytest.approx(0.02)
    assert depth.max() == pytest.approx(0.2, abs=0.03)

    v, f, part = animal()
    from sync4d.match.surface_points import skeleton_points_depth
    from scipy.spatial import cKDTree

    pts, depth = skeleton_points_depth(v, f, SkeletonConfig(), np.random.default_rng(0))
    centre, size = pts.mean(0), np.sqrt(((pts - pts.mean(0)) ** 2).sum(1).mean())
    norm = (pts - centre) / size
    owner = part[cKDTree(v).query(pts)[1]]
    sk = curve_skeleton(norm, SkeletonConfig(), depth / size)
    from sync4d.match.skeleton import neighbour_graph

    core = trunk_core(neighbour_graph(norm, 10, 4.0), norm, depth / size, 0.8, 2.0)
    assert (owner[core] == 0).all()
    leg_branches = []
    for leg in (1, 2, 3, 4):
        b = np.bincount(sk.branch[owner == leg]).argmax()
        assert not sk.branches[b].children
        assert (sk.branch[owner == leg] == b).mean() > 0.6
        leg_branches.append(b)
    assert len(set(leg_branches)) == 4


def test_reference_limbs_from_the_bone_tree() -> None:
    v, f, part = animal()
    pts = skeleton_points(v, f, SkeletonConfig(volume=False, samples=2000), np.random.default_rng(0))
    from scipy.spatial import cKDTree

    labels = part[cKDTree(v).query(pts)[1]]
    sk = curve_skeleton((pts - pts.mean(0)) / np.sqrt(((pts - pts.mean(0)) ** 2).sum(1).mean()), SkeletonConfig())
    limbs, trunk = reference_limbs(sk, labels, len(PARTS), np.array([-1, 0, 0, 0, 0, 0, 0]))
    assert trunk == [0] and sorted(limbs) == [[1], [2], [3], [4], [5], [6]]


@pytest.mark.parametrize("quarter_turns", [1, 2])
def test_structure_match_follows_limbs_across_proportions_and_heading(quarter_turns: int) -> None:
    """Target: longer legs, a bigger head, facing another way (turned 90 or 180 deg about the up axis);
    left and right legs included (a narrow body: the lateral offset counts per axis spread)."""
    v, f, part = animal()
    reference = box_reference(v, f, part)
    tv, tf, tpart = animal(leg=0.5, head=0.2, body=0.7)
    turn = yaw_rotations("y", 4)[quarter_turns]
    tv = tv @ turn.T
    result = match_parts(
        reference, gaussians_at(tv), None, MatchConfig(method="structure"), target_vertices=tv, target_faces=tf
    )
    got = result.part_map.tgt_part
    limbs = tpart > 0
    assert (got[limbs] == tpart[limbs]).mean() > 0.85
    assert result.diagnostics.structure is not None and len(result.diagnostics.structure.leftover) == 0
    # the alignment undoes the turn (reference frame = target frame turned back)
    assert np.allclose(result.alignment.rotation, turn.T, atol=1e-6)


def test_assignment_leaves_a_limb_unmatched_rather_than_nesting() -> None:
    """Two reference limbs, two candidates where candidate 1 is inside candidate 0: only one is used."""

    class Tree:
        @staticmethod
        def is_ancestor(a: int, b: int) -> bool:
            return a == b or (a == 1 and b == 2)

    cost = np.array([[0.1, 0.2], [0.3, 0.1]])
    pairs, total = assign_limbs(cost, Tree(), np.array([1, 2]), miss_cost=1.0)  # type: ignore[arg-type]
    assert len(pairs) == 1 and total == pytest.approx(1.1)


def test_labels_score_the_expected_parts_and_fail_when_they_are_wrong(tmp_path) -> None:
    from sync4d_tools.match_labels.labels import limb_accuracy, read_label_file, vertex_areas, vertex_labels
    from sync4d_tools.match_labels.procedural import chair

    spec = read_label_file(
        next(
            p
            for p in __import__("sync4d_tools.match_labels.labels", fromlist=["x"]).default_label_files()
            if p.name == "chair.json"
        )
    )
    v, f, names = chair()
    labels = vertex_labels(spec, v, names)
    dog = (
        "torso",
        "head_neck",
        "leg_a_upper",
        "leg_a_lower",
        "leg_b_upper",
        "leg_b_lower",
        "leg_c_upper",
        "leg_c_lower",
        "leg_d_upper",
        "leg_d_lower",
        "tail",
    )
    right = np.where(
        np.char.startswith(names.astype(str), "leg"),
        dog.index("leg_a_lower"),
        np.where(names == "back", dog.index("tail"), 0),
    )
    acc, per = limb_accuracy(spec, labels, vertex_areas(v, f), right, dog)
    assert acc == pytest.approx(1.0) and set(per) == {"legs", "back", "seat"}
    wrong = np.zeros(len(v), dtype=np.int64)  # everything 'torso': only the seat (the trunk) is right
    acc, per = limb_accuracy(spec, labels, vertex_areas(v, f), wrong, dog)
    assert per == {"legs": 0.0, "back": 0.0, "seat": 1.0} and 0.0 < acc < 0.5
    bad = tmp_path / "bad.json"
    bad.write_text(
        json.dumps({"name": "x", "reference": "dog", "target": "procedural:chair", "kind": "nope", "labels": []})
    )
    with pytest.raises(InputError, match="kind"):
        read_label_file(bad)
    with pytest.raises(InputError, match="not parts of"):
        typo = read_label_file(bad.with_name("typo.json") if False else _typo_file(tmp_path))
        limb_accuracy(typo, vertex_labels(typo, v, names), vertex_areas(v, f), right, dog)


def _typo_file(tmp_path):
    path = tmp_path / "typo.json"
    path.write_text(
        json.dumps(
            {
                "name": "x",
                "reference": "dog",
                "target": "procedural:chair",
                "kind": "cross",
                "labels": [{"name": "legs", "where": {"part": ["leg_fl"]}, "expect": ["leg_z"]}],
            }
        )
    )
    return path


def test_mocap_bone_parents_follow_the_skeleton() -> None:
    from sync4d.recon.mocap import segment_group_parents

    # root 0 -> 1 -> 2 (arm: segments 2, 3), 0 -> 4 (leg); joint 1 is a zero-length helper (no segment)
    parents = np.array([-1, 0, 1, 2, 0])
    segments = np.array([2, 3, 4])
    groups = np.array([0, 1, 2])
    assert segment_group_parents(parents, segments, groups).tolist() == [-1, 0, -1]


def test_capsule_bands_put_vertices_along_the_limb_and_keep_it_closed() -> None:
    """Mocap bodies: without bands a capsule has vertices only at its end caps (spheres at the joints)."""
    import trimesh

    from sync4d.recon.body import capsule_mesh

    v, f = capsule_mesh(np.zeros(3), np.array([0.0, 0.0, 1.0]), 0.1, rings=4, sectors=10, band_spacing=0.1)
    assert trimesh.Trimesh(v, f, process=True).is_watertight
    heights = np.unique(np.round(v[np.abs(v[:, 2] - 0.5) < 0.5][:, 2], 6))
    assert np.diff(heights).max() <= 0.1 + 1e-9
    v0, _ = capsule_mesh(np.zeros(3), np.array([0.0, 0.0, 1.0]), 0.1, rings=4, sectors=10)
    assert np.diff(np.unique(np.round(v0[:, 2], 6))).max() > 0.9  # the old single band


def test_structure_match_refuses_a_bad_target_before_any_work() -> None:
    v, f, part = animal()
    reference = box_reference(v, f, part)
    bad = v.copy()
    bad[3] = np.nan
    with pytest.raises(InputError, match="finite"):
        match_parts(
            reference, gaussians_at(v), None, MatchConfig(method="structure"), target_vertices=bad, target_faces=f
        )


def test_mirror_pairs_and_the_repair_give_a_leg_back_from_the_tail() -> None:
    """Four legs left/right of the plane z = 0 and a tail on it; a tail holding the mirror image of the
    matched hind-left leg's branch hands it to the hind-right leg."""
    from sync4d.match.structure import LimbSet, mirror_plane_pairs, mirror_repair

    bases = np.array([[-1.0, 0, 0.3], [-1.0, 0, -0.3], [1.0, 0, 0.3], [1.0, 0, -0.3], [1.2, 0, 0.0]])
    scale = np.array([1.0, 1.0, 0.3])
    pairs, normal = mirror_plane_pairs(bases, 1, scale)
    assert sorted(pairs) == [(0, 1), (2, 3)]
    assert abs(normal[2]) == pytest.approx(1.0)

    def limbs(base: np.ndarray) -> LimbSet:
        n = len(base)
        empty = tuple(np.zeros(0, dtype=np.int64) for _ in range(n))
        return LimbSet(empty, base, base, np.zeros(n), np.ones(n), np.full(n, 0.1))

    ref = limbs(bases)
    tgt = limbs(bases[:4] * [1.1, 1, 1.2])  # four leg branches, no tail branch
    chosen = [(0, 0), (1, 1), (2, 2), (4, 3)]  # the tail took the hind-right branch; leg 3 left over
    repaired = mirror_repair(chosen, ref, tgt, np.eye(3), 1, scale, scale)
    assert repaired == [(0, 0), (1, 1), (2, 2), (3, 3)]
    # nothing changes when the partner of a left-over limb is itself unmatched
    assert mirror_repair([(0, 0), (4, 3)], ref, tgt, np.eye(3), 1, scale, scale) == [(0, 0), (4, 3)]


def test_auto_uses_the_features_on_a_shape_of_the_same_kind_and_structure_across_kinds() -> None:
    """``method=auto``: on an animal of other proportions the features' map keeps the reference's structure
    as well as the structure match's (and its accuracy is kept); on a chair the features' map breaks it and
    the structure match is kept: its legs take leg parts, its back the head or the tail."""
    from sync4d.errors import ConfigError
    from sync4d.registry import build
    from sync4d_tools.match_labels.procedural import chair

    extractor = build("features", {"type": "geometric", "n_eigen": 32}, device="cpu")
    v, f, part = animal()
    reference = box_reference(v, f, part)
    tv, tf, tpart = animal(leg=0.5, head=0.2, body=0.7)
    tv = tv + 0.3
    same = match_parts(reference, gaussians_at(tv), extractor, MatchConfig(method="auto"), target_vertices=tv, target_faces=tf)
    scores = same.diagnostics.auto_scores
    assert same.diagnostics.method == "features" and scores["features"].kept >= scores["structure"].kept
    assert (same.part_map.tgt_part == tpart).mean() > 0.95
    cv, cf, names = chair()
    other = match_parts(reference, gaussians_at(cv), extractor, MatchConfig(method="auto"), target_vertices=cv, target_faces=cf)
    scores = other.diagnostics.auto_scores
    assert other.diagnostics.method == "structure" and scores["structure"].kept > scores["features"].kept
    got = other.part_map.tgt_part
    legs = np.char.startswith(names.astype(str), "leg_")
    assert np.isin(got[legs], [PARTS.index(n) for n in PARTS if n.startswith("leg_")]).mean() > 0.9
    assert np.isin(got[names == "back"], [PARTS.index("head"), PARTS.index("tail")]).mean() > 0.6
    with pytest.raises(TypeError):  # no residual threshold any more
        MatchConfig(auto_residual=0.155)  # type: ignore[call-arg]
    with pytest.raises(ConfigError, match="features component"):
        match_parts(reference, gaussians_at(tv), None, MatchConfig(method="auto"))


def test_local_thickness_and_limb_growth_stop_where_the_limb_enters_the_trunk():
    """A thick ball (radius 1) with a thin rod (radius 0.2) leaving it: the rod's points are thin, the ball's
    thick even near its surface; a limb seeded at the rod's tip grows up the rod and stops at the ball."""
    from scipy.ndimage import distance_transform_edt

    from sync4d.match.regions import grow_limbs, local_thickness
    from sync4d.match.skeleton import neighbour_graph

    pitch = 0.1
    g = np.mgrid[-1.2:3.2:pitch, -1.2:1.2:pitch, -1.2:1.2:pitch].reshape(3, -1).T
    ball = np.linalg.norm(g, axis=1) <= 1.0
    rod = (g[:, 0] > 0) & (g[:, 0] <= 3.0) & (np.linalg.norm(g[:, 1:], axis=1) <= 0.2)
    inside = ball | rod
    shape = tuple(len(np.arange(lo, hi, pitch)) for lo, hi in ((-1.2, 3.2), (-1.2, 1.2), (-1.2, 1.2)))
    depth = distance_transform_edt(np.pad(inside.reshape(shape), 1))[1:-1, 1:-1, 1:-1].reshape(-1) * pitch
    pts, depth = g[inside], depth[inside]
    thick = local_thickness(pts, depth)
    shell = (np.linalg.norm(pts, axis=1) > 0.85) & (pts[:, 0] < 0.5)
    assert thick[shell].min() > 0.8                                     # the ball's surface layer: thick
    assert np.median(thick[pts[:, 0] > 1.5]) < 0.35                     # the rod: thin
    labels = np.full(len(pts), -1)
    tip = np.flatnonzero(pts[:, 0] > 2.5)
    labels[tip] = 7
    grown = grow_limbs(neighbour_graph(pts, 10, 4.0), labels, [tip], thick, reach=20.0)
    assert (grown[(pts[:, 0] > 1.3) & rod[inside]] == 7).all()                # the whole rod outside the ball
    assert (grown[np.linalg.norm(pts, axis=1) < 0.8] == -1).all()        # not into the ball


def test_consistency_scores_a_broken_map_lower_and_ignores_stray_points():
    """Two touching boxes (parts 0, 1) and a third part far away: the right map keeps everything; a map
    with a chunk of part 0 inside part 1 loses connectivity; a map that puts part 2 where 0 meets 1
    makes contacts the reference lacks; three stray points change nothing."""
    from sync4d.match.consistency import consistency

    rng = np.random.default_rng(0)
    pts = np.concatenate([rng.uniform([0, 0, 0], [1, 1, 1], (1500, 3)), rng.uniform([1, 0, 0], [2, 1, 1], (1500, 3)),
                          rng.uniform([4, 0, 0], [5, 1, 1], (1500, 3))])
    parts = np.repeat([0, 1, 2], 1500)
    ref = consistency(pts, parts, pts, parts, 3)
    assert ref.connected == 1.0 and ref.contacts == 1.0 and ref.kept == 1.0
    chunk = parts.copy()
    chunk[(pts[:, 0] > 1.4) & (pts[:, 0] < 1.6)] = 0
    assert consistency(pts, chunk, pts, parts, 3).connected < 0.95
    seam = parts.copy()
    seam[(pts[:, 0] > 0.9) & (pts[:, 0] < 1.1)] = 2
    assert consistency(pts, seam, pts, parts, 3).contacts < 0.5
    stray = parts.copy()
    stray[[10, 500, 1000]] = 1
    assert consistency(pts, stray, pts, parts, 3).kept == 1.0


def test_limb_partners_come_from_the_bone_tree_and_complete_an_unmatched_leg() -> None:
    """Limbs off the same trunk part with as many parts pair up (of four legs off one part, the nearest
    bases); a leg left over while its partner is matched takes the free branch at the mirror image."""
    from sync4d.match.skeleton import Branch, CurveSkeleton
    from sync4d.match.structure import LimbSet, complete_partners, limb_partners, partner_plane

    # parts: 0 trunk, 1-2 leg a, 3-4 leg b, 5-6 leg c, 7-8 leg d, 9 head, 10 tail
    parent = np.array([-1, 0, 1, 0, 3, 0, 5, 0, 7, 0, 0])
    limb_parts = [[1, 2], [3, 4], [5, 6], [7, 8], [9], [10]]
    bases = np.array([[-1.0, 0, 0.3], [-0.9, 0, -0.3], [1.0, 0, 0.3], [1.0, 0, -0.3], [-1.4, 0.3, 0], [1.3, 0.2, 0]])
    length = np.array([1.0, 1.1, 1.0, 1.0, 1.2, 0.6])  # a head twice as long as the tail: no pair
    partners = limb_partners(limb_parts, parent, bases, length)
    assert sorted(partners) == [(0, 1), (2, 3)]
    scale = np.array([1.0, 1.0, 0.3])
    normal = partner_plane(bases, partners, 1, scale)
    assert abs(normal[2]) > 0.99

    def limbs(base: np.ndarray) -> LimbSet:
        n = len(base)
        empty = tuple(np.zeros(0, dtype=np.int64) for _ in range(n))
        return LimbSet(empty, base, base, np.zeros(n), np.ones(n), np.full(n, 0.1))

    branches = tuple(Branch((i,), 0 if i else -1, (), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64),
                            np.zeros(3), np.zeros(3), 0.0, 1.0) for i in range(5))
    skeleton = CurveSkeleton(np.zeros((1, 3)), np.zeros(1), 0, np.zeros(1, dtype=np.int64),
                             np.zeros(1, dtype=np.int64), branches, 0.1)
    tgt = limbs(bases[:4] * [1.1, 1, 1.2])  # four leg branches (candidates 0-3 = branches 1-4)
    cand = np.arange(1, 5)
    chosen = [(0, 0), (2, 2), (3, 3)]  # leg b left over although the branch opposite leg a is free
    done = complete_partners(chosen, partners, tgt, skeleton, cand, np.eye(3), normal, scale)
    assert done == [(0, 0), (1, 1), (2, 2), (3, 3)]
    # a branch far from the mirror image is not taken
    far = limbs(np.array([[-1.0, 0, 0.3], [0.0, 0, 0.3], [1.0, 0, 0.3], [1.0, 0, -0.3]]))
    assert complete_partners(chosen, partners, far, skeleton, cand, np.eye(3), normal, scale) == chosen


def test_the_trunk_is_the_blob_nearer_the_ground_not_a_bigger_head() -> None:
    """A toy whose head is thicker than its body: the skeleton's core is the body (it carries the legs),
    so the legs and the head leave the root branch."""
    from sync4d.match.skeleton import trunk_core, trunk_on_legs
    from sync4d.match.skeleton import neighbour_graph as graph_of

    v, f, names = box_union([
        ("leg_l", (-0.12, 0.0, -0.05), (-0.04, 0.25, 0.05)), ("leg_r", (0.04, 0.0, -0.05), (0.12, 0.25, 0.05)),
        ("body", (-0.17, 0.24, -0.14), (0.17, 0.54, 0.14)), ("neck", (-0.04, 0.53, -0.04), (0.04, 0.7, 0.04)),
        ("head", (-0.25, 0.69, -0.22), (0.25, 1.14, 0.22)),
    ], max_edge=0.03)
    raw, depth = volume_points(v, f, 48, np.random.default_rng(0), with_depth=True)
    centre, size = raw.mean(axis=0), np.sqrt(((raw - raw.mean(axis=0)) ** 2).sum(axis=1).mean())
    pts, depth = (raw - centre) / size, depth / size  # normalised, as the structure match sees a shape
    config = SkeletonConfig()
    graph = graph_of(pts, config.neighbours, config.max_edge_factor)
    deepest = trunk_core(graph, pts, depth, config.core_depth, config.core_reach)
    assert raw[deepest, 1].min() > 0.69  # the head is the deepest blob
    core = trunk_on_legs(graph, pts, depth, deepest, config, 1)
    assert 0.24 < raw[core, 1].min() and raw[core, 1].max() < 0.54  # the body is the trunk


def test_the_branches_between_the_root_and_a_matched_limb_are_trunk() -> None:
    """A branch no limb took that lies between the root and matched branches (levels that had not yet
    parted two legs) is trunk; an unmatched branch hanging off the root is not."""
    from sync4d.match.skeleton import Branch, CurveSkeleton
    from sync4d.match.structure import trunk_branches

    parents = [-1, 0, 1, 1, 0, 4]  # 1 parts into 2 and 3; 4 into 5
    branches = tuple(Branch((i,), p, (), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(3),
                            np.zeros(3), 0.0, 1.0) for i, p in enumerate(parents))
    skeleton = CurveSkeleton(np.zeros((1, 3)), np.zeros(1), 0, np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int64),
                             branches, 0.1)
    assert trunk_branches(skeleton, [2, 3]) == [0, 1]
    assert trunk_branches(skeleton, [2, 4]) == [0, 1]
    assert trunk_branches(skeleton, []) == [0]


def test_the_skeleton_picture_draws_what_the_structure_match_saw(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """``sync4d_tools.match_labels.skeleton_picture``: reference limbs, the target's branches and its parts."""
    import matplotlib.pyplot as plt

    from sync4d_tools.match_labels.skeleton_picture import save_small, skeleton_figure

    v, f, part = animal()
    tv, tf, _ = animal(leg=0.45, head=0.15)
    result = match_parts(box_reference(v, f, part), gaussians_at(tv), None, MatchConfig(method="structure"),
                         target_vertices=tv, target_faces=tf)
    fig = skeleton_figure(result.diagnostics.structure, result.diagnostics.reference_labels, PARTS, "animal")
    path = tmp_path / "skeleton.png"
    save_small(fig, path)
    plt.close(fig)
    assert path.stat().st_size > 1000
    texts = [t.get_text() for ax in fig.axes for t in ax.texts]
    assert any(t.startswith("b1 -> ") for t in texts) and "head" in texts


def _limb_set(base: np.ndarray, members: tuple[np.ndarray, ...] | None = None) -> "LimbSet":  # noqa: F821
    from sync4d.match.structure import LimbSet

    n = len(base)
    empty = tuple(np.zeros(0, dtype=np.int64) for _ in range(n)) if members is None else members
    return LimbSet(empty, base, base, np.zeros(n), np.ones(n), np.full(n, 0.1))


def test_attach_heights_say_where_a_limb_leaves_the_trunk_whatever_its_pose() -> None:
    """A standing trunk (height 1) with a limb leaving at its bottom and one at its top: -0.45 and +0.45 of
    the trunk's length; an arm hanging beside the trunk (touching it from shoulder to elbow) leaves at its
    end away from its other parts, not half-way down."""
    from sync4d.match.skeleton import CurveSkeleton
    from sync4d.match.structure import attach_heights

    rng = np.random.default_rng(0)
    trunk = np.c_[rng.uniform(-0.1, 0.1, 400), rng.uniform(0.0, 1.0, 400), rng.uniform(-0.1, 0.1, 400)]
    s = np.linspace(0.1, 0.5, 20)
    low, high = np.c_[s, np.full(20, 0.05), np.zeros(20)], np.c_[s, np.full(20, 0.95), np.zeros(20)]
    hanging = np.c_[np.full(20, 0.15), np.linspace(0.9, 0.3, 20), np.zeros(20)]
    pts = np.concatenate([trunk, low, high, hanging])
    geo = np.concatenate([np.zeros(400), s, s, np.full(20, 0.05)])  # the hanging arm touches the trunk all along
    sk = CurveSkeleton(pts, geo, 0, np.zeros(len(pts), dtype=np.int64), np.zeros(len(pts), dtype=np.int64), (), 0.06)
    members = [400 + np.arange(20), 420 + np.arange(20)]
    h = attach_heights(sk, members, np.arange(400), 1)
    assert abs(h[0] + 0.45) < 0.05 and abs(h[1] - 0.45) < 0.05
    arm = [440 + np.arange(20)]
    assert abs(attach_heights(sk, arm, np.arange(400), 1)[0] - 0.1) < 0.05           # first level: half-way
    away = np.array([[0.15, 0.1, 0.0]])                                               # its forearm below
    assert attach_heights(sk, arm, np.arange(400), 1, away)[0] > 0.35                 # the shoulder


def test_partners_in_one_straddling_branch_split_it_and_a_misplaced_pair_hands_a_branch_over() -> None:
    """Two legs in one branch across the plane of symmetry: the left-over leg takes its side's half. A thigh
    holding an arm's mirror branch while its partner sits on the midline hands it to the left-over arm."""
    from sync4d.match.structure import mirror_repair, split_partners

    rng = np.random.default_rng(0)
    legs = np.c_[rng.uniform(-0.3, 0.3, 200), rng.uniform(-1.0, -0.5, 200), rng.uniform(-0.1, 0.1, 200)]
    ref_base = np.array([[-0.2, -0.4, 0.0], [0.2, -0.4, 0.0]])
    normal = np.array([1.0, 0.0, 0.0])
    tgt = _limb_set(np.array([[0.0, -0.5, 0.0]]), (np.arange(200),))
    (limb, cand, half), = split_partners([(0, 0)], [(0, 1)], ref_base, normal, legs, tgt)
    assert (limb, cand) == (1, 0) and (legs[half, 0] > 0).all() and (legs[~half, 0] <= 0).all()
    one_leg = _limb_set(np.array([[0.2, -0.5, 0.0]]), (np.flatnonzero(legs[:, 0] > 0),))
    assert split_partners([(0, 0)], [(0, 1)], ref_base, normal, legs, one_leg) == []

    # limbs: 0, 1 thighs, 2, 3 arms; branches: 0, 1 arm stubs at x = -/+0.8, 2 both legs on the midline
    tgt = _limb_set(np.array([[-0.8, 0.0, 0.0], [0.8, 0.0, 0.0], [0.0, -1.0, 0.0]]))
    ones = np.ones(3)
    repaired = mirror_repair([(0, 1), (1, 2), (2, 0)], tgt, tgt, np.eye(3), 1, ones, ones, ([(0, 1), (2, 3)], normal))
    assert repaired == [(1, 2), (2, 0), (3, 1)]
    # a thigh pair that does mirror each other keeps its branches
    tgt = _limb_set(np.array([[-0.8, 0.0, 0.0], [0.8, 0.0, 0.0], [-0.7, 0.0, 0.0]]))
    kept = mirror_repair([(0, 1), (1, 2), (2, 0)], tgt, tgt, np.eye(3), 1, ones, ones, ([(0, 1), (2, 3)], normal))
    assert kept == [(0, 1), (1, 2), (2, 0)]


def test_a_limb_as_thick_as_the_trunk_is_not_grown() -> None:
    """A big head on a small body: the head's branch is not grown over the body (the trunk is thinner)."""
    from sync4d.match.regions import grow_limbs
    from sync4d.match.skeleton import neighbour_graph

    rng = np.random.default_rng(0)
    pts = rng.uniform(0.0, 1.0, (600, 3))
    thick = np.where(pts[:, 1] > 0.5, 0.5, 0.2)  # head above, body below
    labels = np.full(600, -1)
    head = np.flatnonzero(pts[:, 1] > 0.7)
    labels[head] = 3
    graph = neighbour_graph(pts, 10, 4.0)
    assert (grow_limbs(graph, labels, [head], thick, reach=20.0, trunk=0.2) == labels).all()
    assert (grow_limbs(graph, labels, [head], thick, reach=20.0, trunk=1.0)[pts[:, 1] > 0.5] == 3).all()


def test_the_trunk_takes_the_reference_trunk_parts_by_relative_position() -> None:
    """A short trunk (a toy's body under a big head) fitted to a long reference trunk: its top takes the
    chest, its bottom the pelvis, though every point of it lies nearest the reference's pelvis."""
    from scipy.spatial import cKDTree

    from sync4d.match.regions import fit_spread

    rng = np.random.default_rng(0)
    ref = np.c_[rng.uniform(-0.2, 0.2, 400), rng.uniform(-1.0, 1.0, 400), rng.uniform(-0.1, 0.1, 400)]
    ref_part = np.where(ref[:, 1] > 0.0, 1, 0)  # 1 chest above, 0 pelvis below
    short = np.c_[rng.uniform(-0.3, 0.3, 300), rng.uniform(-1.0, -0.4, 300), rng.uniform(-0.2, 0.2, 300)]
    tree = cKDTree(ref)
    assert (ref_part[tree.query(short)[1]] == 0).mean() > 0.9
    fitted = ref_part[tree.query(fit_spread(short, ref))[1]]
    top, bottom = short[:, 1] > -0.6, short[:, 1] < -0.8
    assert (fitted[top] == 1).mean() > 0.9 and (fitted[bottom] == 0).mean() > 0.9


def test_a_leg_on_an_arm_stub_beside_the_legs_straddling_branch_hands_it_to_the_arms() -> None:
    """Legs 0/1 (partners), arms 2/3 (partners, both left over). Leg 0 holds an arm stub (a side branch)
    while leg 1 holds the legs' branch straddling the midline: the stub goes to the arm that fits it best;
    with no left-over pair, or with the legs on two side branches, nothing changes."""
    from sync4d.match.structure import LimbSet, straddle_repair

    # candidates: 0 the legs' branch (points on both sides), 1 and 2 arm stubs (one side each)
    side = np.array([-1.0, -1.0, 1.0, 1.0, -2.0, -2.0, 2.0, 2.0])
    members = (np.arange(4), np.array([4, 5]), np.array([6, 7]))
    tgt = LimbSet(members, np.zeros((3, 3)), np.zeros((3, 3)), np.zeros(3), np.ones(3), np.full(3, 0.1))
    partners = [(0, 1), (2, 3)]
    cost = np.array([[1.0, 1.5, 5.0], [1.1, 5.0, 2.0], [6.0, 4.9, 4.0], [6.0, 4.0, 4.8]])
    assert straddle_repair([(0, 1), (1, 0)], partners, cost, side, tgt) == [(1, 0), (3, 1)]
    assert straddle_repair([(0, 1), (1, 0), (2, 2)], partners, cost, side, tgt) == [(0, 1), (1, 0), (2, 2)]
    assert straddle_repair([(0, 1), (1, 2)], partners, cost, side, tgt) == [(0, 1), (1, 2)]


def test_a_foot_points_where_the_toes_reach_and_a_turned_foot_costs() -> None:
    """A leg whose lowest points reach forward (+z) of the points above has a foot pointing +z; an arm off
    the ground has none. Turned half a turn, the target's foot disagrees with the reference's in full."""
    from dataclasses import replace

    from sync4d.match.structure import LimbSet, foot_disagreement, limb_feet, yaw_rotations

    shin = np.stack([np.zeros(20), np.linspace(0.06, 0.25, 20), np.zeros(20)], axis=1)
    toes = np.stack([np.zeros(10), np.full(10, 0.01), np.linspace(0.0, 0.2, 10)], axis=1)
    arm = np.stack([np.full(10, 0.5), np.linspace(0.6, 1.0, 10), np.zeros(10)], axis=1)
    points = np.concatenate([shin, toes, arm])
    feet = limb_feet(points, [np.arange(30), np.arange(30, 40)], up=1)
    assert feet[0, 2] > 0.05 and abs(feet[0, 0]) < 1e-9 and feet[0, 1] == 0.0
    assert np.allclose(feet[1], 0.0)
    n = 2
    limbs = replace(LimbSet(tuple(np.zeros(0, dtype=np.int64) for _ in range(n)), np.zeros((n, 3)), np.zeros((n, 3)),
                            np.zeros(n), np.ones(n), np.ones(n)), foot=feet)
    same = foot_disagreement(limbs, limbs, np.eye(3))
    half = foot_disagreement(limbs, limbs, yaw_rotations("y", 2)[1])
    assert same[0, 0] < 1e-9 and half[0, 0] > 0.99 * np.linalg.norm(feet[0])
    assert same[1, 1] == 0.0 and half[1, 1] == 0.0 and half[0, 1] == 0.0


def test_left_over_limbs_take_the_free_branches_off_the_trunk_at_least_cost() -> None:
    """Branches no limb holds and no matched branch is nested with (the outermost of them) go to the
    left-over limbs by least cost, whatever the miss cost; a branch nested with a matched one is never free."""
    from sync4d.match.skeleton import Branch, CurveSkeleton
    from sync4d.match.structure import free_branches, pair_leftovers

    parents = [-1, 0, 1, 1, 0, 4]  # 1 parts into 2 and 3; 4 carries 5
    branches = tuple(Branch((i,), p, (), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(3),
                            np.zeros(3), 0.0, 1.0) for i, p in enumerate(parents))
    skeleton = CurveSkeleton(np.zeros((1, 3)), np.zeros(1), 0, np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int64),
                    branches, 0.1)
    cand = np.arange(1, 6)  # candidate c is branch c + 1
    pairs = [(0, 1)]  # limb 0 holds branch 2
    assert free_branches(pairs, skeleton, cand) == [2, 3]  # branches 3 and 4 (5 is inside 4; 1 holds 2)
    cost = np.full((3, 5), 9.0)
    cost[1, 3], cost[2, 2], cost[1, 2], cost[2, 3] = 5.0, 6.0, 4.0, 8.0
    assert pair_leftovers(pairs, cost, skeleton, cand) == [(0, 1), (1, 3), (2, 2)]  # 5 + 6 < 4 + 8
    assert pair_leftovers([(0, 1), (1, 2), (2, 3)], cost, skeleton, cand) == [(0, 1), (1, 2), (2, 3)]


def test_a_capsules_radius_and_the_lone_limbs_thickness_turn_a_target_round() -> None:
    """part_radius reads a cylinder's radius off its surface. Between the best turn and the best one at least
    90 deg away, the one whose lone limbs (no left/right partner) are as thick, relative to the trunk, as the
    reference's comes first: a raised thin tail is no head. Partner limbs do not count, and without a lone
    limb matched on both sides, or with the same thickness both ways, the order stays."""
    from sync4d.match.heading import face_by_thickness, part_radius, target_thickness, thickness_disagreement
    from sync4d.match.structure import yaw_rotations

    angle = np.linspace(0.0, 2 * np.pi, 60, endpoint=False)
    ring = np.stack([0.3 * np.cos(angle), np.zeros(60), 0.3 * np.sin(angle)], axis=1)
    cylinder = np.concatenate([ring + [0.0, h, 0.0] for h in np.linspace(0.0, 2.0, 20)])
    assert abs(part_radius(cylinder, np.zeros(len(cylinder), dtype=np.int64), [0]) - 0.3) < 1e-6
    thickness = np.array([1.0, 0.5, 0.2, 0.3, 0.3])
    tgt = target_thickness(thickness, (np.array([1]), np.array([2]), np.array([3]), np.array([4])), np.array([0]))
    assert np.allclose(tgt, [0.5, 0.2, 0.3, 0.3])
    ref = np.array([0.5, 0.2, 0.3, 0.3])  # head, tail, two partner legs
    lone = {0, 1}
    ahead, behind = yaw_rotations("y", 2)
    turned_round = (1.0, ahead, [(0, 1), (1, 0), (2, 2), (3, 3)], 1.0)  # the head on the thin branch
    facing = (2.0, behind, [(0, 0), (1, 1), (2, 3), (3, 2)], 2.0)
    assert thickness_disagreement(facing[2], ref, tgt, lone) < 1e-12
    assert face_by_thickness([turned_round, facing], ref, tgt, lone)[0] is facing
    assert face_by_thickness([facing, turned_round], ref, tgt, lone)[0] is facing
    legs_only = (2.0, behind, [(2, 3), (3, 2)], 2.0)
    assert face_by_thickness([turned_round, legs_only], ref, tgt, lone)[0] is turned_round
    swapped_legs = (2.0, behind, [(0, 1), (1, 0), (2, 3), (3, 2)], 2.0)
    assert face_by_thickness([turned_round, swapped_legs], ref, tgt, lone)[0] is turned_round


def test_a_poles_column_stays_trunk_under_its_shade_but_not_without_one() -> None:
    """A lamp: a pole (half-width 0.2), an arm along x at its top and a thick shade hanging from the arm. Levels
    from the pole's middle part: the branch going up holds the pole's upper half, the arm and the shade; its
    levels along the pole at the pole's thickness continue the trunk's column, the arm and the shade do not.
    Without the shade (a thin arm at the end) nothing is given back: a limb thinner than the trunk stays a limb."""
    from scipy.ndimage import distance_transform_edt
    from scipy.sparse.csgraph import dijkstra

    from sync4d.match.regions import local_thickness, trunk_column
    from sync4d.match.skeleton import neighbour_graph

    pitch = 0.1
    axes = [np.arange(lo, hi, pitch) + pitch / 2 for lo, hi in ((-0.4, 3.2), (0.0, 4.2), (-0.8, 0.8))]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    pole = (np.abs(g[:, 0]) < 0.2) & (np.abs(g[:, 2]) < 0.2) & (g[:, 1] < 4.0)
    arm = (g[:, 0] > -0.2) & (g[:, 0] < 2.4) & (g[:, 1] > 3.6) & (g[:, 1] < 4.0) & (np.abs(g[:, 2]) < 0.2)
    shade = (g[:, 0] > 1.6) & (g[:, 0] < 2.8) & (g[:, 1] > 2.6) & (g[:, 1] < 3.7) & (np.abs(g[:, 2]) < 0.6)
    for with_shade in (True, False):
        inside = pole | arm | (shade if with_shade else False)
        depth = distance_transform_edt(np.pad(inside.reshape([len(a) for a in axes]), 1))[1:-1, 1:-1, 1:-1]
        pts, depth = g[inside], depth.reshape(-1)[inside] * pitch
        thick = local_thickness(pts, depth)
        graph = neighbour_graph(pts, 10, 4.0)
        root = np.flatnonzero((np.abs(pts[:, 0]) < 0.2) & (pts[:, 1] > 1.5) & (pts[:, 1] < 2.5))
        geo = dijkstra(graph, directed=False, indices=root, min_only=True)
        branch = np.flatnonzero(pts[:, 1] >= 2.5)
        column = trunk_column(pts, geo, 0.2, thick, root, branch)
        if not with_shade:
            assert len(column) == 0
            continue
        upper_pole = branch[(np.abs(pts[branch, 0]) < 0.2) & (pts[branch, 1] < 3.4)]
        assert np.isin(upper_pole, column).mean() > 0.9                    # the pole up to below the arm
        assert not np.isin(column, np.flatnonzero(pts[:, 0] > 0.5)).any()  # neither the arm nor the shade


def test_legs_end_at_the_bodys_underside() -> None:
    """A box body (underside at height 1) on four thin legs. The legs' branches stop half-way up (legs that
    part low): below the underside they grow up to it; one leg's branch also holds the body's thick points
    above it (levels that part high): it gives them back to the trunk, and keeps its own thin points."""
    from scipy.ndimage import distance_transform_edt

    from sync4d.match.regions import legs_to_underside, local_thickness
    from sync4d.match.skeleton import neighbour_graph

    pitch = 0.1
    axes = [np.arange(lo, hi, pitch) + pitch / 2 for lo, hi in ((-1.6, 1.6), (0.0, 2.0), (-0.7, 0.7))]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    body = (np.abs(g[:, 0]) < 1.5) & (g[:, 1] > 1.0) & (np.abs(g[:, 2]) < 0.6)
    feet = [(x, z) for x in (-1.1, 1.1) for z in (-0.35, 0.35)]
    leg = [(np.abs(g[:, 0] - x) < 0.15) & (np.abs(g[:, 2] - z) < 0.15) & (g[:, 1] <= 1.0) for x, z in feet]
    inside = body | np.any(leg, axis=0)
    depth = distance_transform_edt(np.pad(inside.reshape([len(a) for a in axes]), 1))[1:-1, 1:-1, 1:-1]
    pts, depth = g[inside], depth.reshape(-1)[inside] * pitch
    thick = local_thickness(pts, depth)
    on_leg = [m[inside] for m in leg]
    limbs = [np.flatnonzero(m & (pts[:, 1] < 0.6)) for m in on_leg]
    over_first = np.flatnonzero((np.linalg.norm(pts[:, [0, 2]] - feet[0], axis=1) < 0.2) & (pts[:, 1] > 1.0)
                                & (pts[:, 1] < 1.2))
    limbs[0] = np.union1d(limbs[0], over_first)
    labels = np.full(len(pts), -1)
    for i, m in enumerate(limbs):
        labels[m] = i
    trunk = np.setdiff1d(np.arange(len(pts)), np.concatenate(limbs))
    out, back = legs_to_underside(pts, neighbour_graph(pts, 10, 4.0), labels, limbs, trunk, thick, 1,
                                  cap=float(thick.max()))
    for i, m in enumerate(on_leg):
        assert (out[np.flatnonzero(m & (pts[:, 1] < 0.9))] == i).all()  # each leg up to the underside
    assert (out[np.flatnonzero(pts[:, 1] > 1.1)] == -1).all()            # nothing of the body
    high = over_first[pts[over_first, 1] > 1.1]                           # above the underside's layer
    assert len(high) and np.isin(high, back).all()                       # the body's thick points given back


def test_a_belly_below_half_the_leg_is_no_underside() -> None:
    """The belly points beside two legs: at height 2 they are the legs' underside; on the floor (a cat
    stretching, its chest down) they are none: a leg hangs below the belly, not beside it."""
    from sync4d.match.regions import undersides

    column = np.stack([np.zeros(11), np.linspace(0.0, 1.0, 11), np.zeros(11)], axis=1)
    legs = [column + [x, 0.0, 0.0] for x in (-1.0, 1.0)]
    for height, expect in ((2.0, 2.0), (0.1, np.nan)):
        belly = np.stack([np.linspace(-3.0, 3.0, 61), np.full(61, height), np.full(61, 2.0)], axis=1)
        pts = np.concatenate(legs + [belly])
        labels = np.r_[np.zeros(11), np.ones(11), np.full(61, -1)].astype(np.int64)
        level, _ = undersides(pts, labels, [np.arange(11), np.arange(11, 22)], np.arange(22, 83), np.full(83, 0.1), 1)
        np.testing.assert_allclose(level[:22], expect)
