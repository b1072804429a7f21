"""Helpers of ``python -m sync4d.evaluate match_gt`` on a tiny synthetic skeleton (no shared data)."""

from __future__ import annotations

import numpy as np
import pytest

from sync4d_tools.evaluate.match_gt import (
    body_reference,
    grouped_body,
    rescale_skeleton,
    sample_labelled_surface,
    segment_to_part,
)

# A 'T': root 0 -> spine 1 -> left arm 2, right arm 3.
JOINTS = np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-0.6, 1.0, 0.0], [0.6, 1.0, 0.0]])
PARENTS = np.array([-1, 0, 1, 1])


def test_rescale_skeleton_scales_segments_and_carries_children() -> None:
    out = rescale_skeleton(JOINTS, PARENTS, np.array([1.0, 2.0, 0.5, 1.0]))
    assert np.allclose(out[1], [0.0, 2.0, 0.0])
    assert np.allclose(out[2], [-0.3, 2.0, 0.0])
    assert np.allclose(out[3], [0.6, 2.0, 0.0])


def test_grouped_body_keeps_outer_surface_with_parts() -> None:
    joint_part = segment_to_part(["root", "spine", "larm", "rarm"], {"body": ("spine",), "arms": ("larm", "rarm")})
    assert joint_part.tolist() == [-1, 0, 1, 1]
    body = grouped_body(JOINTS, PARENTS, joint_part, np.array([0.15, 0.08]), ("body", "arms"), max_edge=0.1)
    assert set(np.unique(body.part)) == {0, 1}
    # no kept vertex is buried inside the spine capsule while belonging to an arm
    arm = body.vertices[body.part == 1]
    d_spine = np.linalg.norm(arm[:, [0, 2]], axis=1)  # distance to the vertical spine axis
    assert (d_spine[(arm[:, 1] > 0) & (arm[:, 1] < 1)] >= 0.15 * 0.98 - 1e-6).all()
    ref = body_reference(body, name="t")
    assert ref.num_bones == 2 and np.array_equal(ref.part_labels(), body.part)
    pts, lab = sample_labelled_surface(body.vertices, body.faces, body.part, 500, np.random.default_rng(0))
    assert pts.shape == (500, 3) and set(np.unique(lab)) == {0, 1}
    assert np.mean(lab == 1) == pytest.approx(np.mean(np.abs(pts[:, 0]) > 0.15), abs=0.1)


def pipeline_match_options():
    """The matching defaults (MatchConfig, the one source of them), with pca_icp: the pairs are randomly rotated."""
    from sync4d.match import MatchConfig

    return MatchConfig(align="pca_icp")


@pytest.fixture(scope="module")
def geometric_extractor():
    from sync4d_tools.evaluate.match_gt import load_features_config
    from sync4d.registry import build

    return build("features", load_features_config("geometric"), device="cpu")


def test_laptop_of_other_proportions_meets_the_accuracy_goal(geometric_extractor) -> None:
    """Issue goal (b): >= 95% part-label accuracy with the pipeline defaults (no shared data needed)."""
    from sync4d_tools.evaluate.match_gt import pair_laptop_proportions

    pair = pair_laptop_proportions(geometric_extractor, pipeline_match_options(), n_points=1500)
    assert pair.accuracy >= 0.95


def test_human_self_copy_meets_the_accuracy_goal(geometric_extractor) -> None:
    """Issue goal (a): a resampled, rescaled, rotated, jittered copy of the CMU capsule body, >= 95%."""
    from sync4d.errors import DataMissingError
    from sync4d_tools.evaluate.match_gt import pair_self_copy

    try:
        pair = pair_self_copy(geometric_extractor, pipeline_match_options(), n_points=2000)
    except DataMissingError as err:
        pytest.skip(str(err))
    assert pair.accuracy >= 0.95


def test_labels_option_reports_limb_accuracy_per_pair(tmp_path, capsys) -> None:
    """``--labels FILE`` (a procedural target: no shared data): one JSON line with cross_category."""
    import json

    from sync4d_tools.evaluate.match_gt import main
    from sync4d_tools.match_labels.labels import default_label_files

    chair = next(p for p in default_label_files() if p.name == "chair.json")
    try:
        out = main(["--pairs", "", "--method", "structure", "--labels", str(chair), "--match",
                    "structure.skeleton.samples=3000"])
    except Exception as err:  # the dog reference body needs ../shared/data
        from sync4d.errors import DataMissingError

        if isinstance(err, DataMissingError):
            pytest.skip(str(err))
        raise
    last = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    pair = last["cross_category"]["dog_to_chair"]
    assert pair["kind"] == "cross" and out == last
    # the chair's legs, back and seat are all scored; the floors are what no matching reaches
    assert set(pair["per_label"]) == {"legs", "back", "seat"}
    assert pair["chance"] == max(pair["constant"], pair["random"]) and pair["constant_part"] != ""
    # the structure match beats chance clearly (measured 0.6-0.7 at seeds 0-2; a map by chance scores ~0)
    assert pair["accuracy"] > pair["chance"] and pair["corrected"] > 0.4
    from sync4d.errors import ConfigError

    with pytest.raises(ConfigError, match="match"):
        main(["--pairs", "", "--method", "structure", "--labels", str(chair), "--match", "structure.nope=1"])


def test_laptop_to_shell_pair_needs_no_shared_data_and_auto_keeps_the_features(capsys) -> None:
    """The default scene's pair (procedural laptop -> procedural clam shell): ``auto`` runs both methods;
    the features' map keeps the two parts' structure as fully as the structure match's, so the paper's
    method is kept (no threshold decides); structure also passes (its bottom dome takes a little lid)."""
    import json

    from sync4d_tools.evaluate.match_gt import main
    from sync4d_tools.match_labels.labels import default_label_files

    shell = next(p for p in default_label_files() if p.name == "shell.json")
    main(["--pairs", "", "--method", "auto", "--labels", str(shell)])
    pair = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["cross_category"]["laptop_to_shell"]
    assert pair["method"] == "features" and pair["auto_scores"]["features"] == [1.0, 1.0]
    assert pair["limb_accuracy"] > 0.95
    main(["--pairs", "", "--method", "structure", "--labels", str(shell)])
    pair = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["cross_category"]["laptop_to_shell"]
    assert pair["method"] == "structure" and pair["limb_accuracy"] > 0.9


def test_score_puts_the_floors_beside_the_accuracy_and_can_fail() -> None:
    """Two limb labels and a trunk label over four parts: the right map scores 1 (corrected 1), the best
    constant assignment and a uniformly random one score what their definitions say, and a map that puts
    every point on the trunk scores its area share, corrected to <= 0."""
    from pathlib import Path

    from sync4d_tools.match_labels.labels import LabelFile, LabelSpec, chance_corrected, score

    names = ("trunk", "arm_l", "arm_r", "head")
    spec = LabelFile(Path("t.json"), "t", "human", "procedural:t", "same_structure", "y", (
        LabelSpec("arms", [], ("arm_l", "arm_r")), LabelSpec("head", [], ("head",)),
        LabelSpec("body", [], ("trunk",), trunk=True)))
    labels = np.array([0] * 30 + [1] * 20 + [2] * 50)          # 30 % arms, 20 % head, 50 % body
    right = np.array([1] * 30 + [3] * 20 + [0] * 50)
    weights = np.ones(100)
    good = score(spec, labels, weights, right, names)
    assert good["accuracy"] == 1.0 and good["limb_accuracy"] == 1.0 and good["corrected"] == 1.0
    assert good["constant"] == pytest.approx(0.5) and good["constant_part"] == "trunk"
    assert good["random"] == pytest.approx(0.3 * 2 / 4 + 0.2 / 4 + 0.5 / 4)
    trunk_only = score(spec, labels, weights, np.zeros(100, dtype=np.int64), names)
    assert trunk_only["accuracy"] == pytest.approx(0.5) and trunk_only["limb_accuracy"] == 0.0
    assert trunk_only["corrected"] == pytest.approx(0.0)
    swapped = score(spec, labels, weights, np.array([3] * 30 + [1] * 20 + [0] * 50), names)
    assert swapped["limb_accuracy"] == 0.0 and swapped["corrected"] == pytest.approx(0.0)
    assert chance_corrected(0.3, 0.5) < 0 and np.isnan(chance_corrected(1.0, 1.0))


@pytest.mark.parametrize("name", ["long_tail", "chibi", "flush_penguin", "stretch"])
def test_new_procedural_targets_are_labelled_by_construction(name: str) -> None:
    """The hard-case targets: a surface with every label of their label file covering some of it (the trunk
    included)."""
    from sync4d_tools.match_labels.labels import default_label_files, read_label_file, vertex_labels
    from sync4d_tools.match_labels.procedural import SHAPES

    v, f, names = SHAPES[name]()
    assert len(f) > 1000 and np.isfinite(v).all() and f.max() < len(v)
    spec = next(read_label_file(p) for p in default_label_files() if read_label_file(p).target == f"procedural:{name}")
    labels = vertex_labels(spec, v, names)
    assert set(np.unique(labels)) == set(range(len(spec.labels)))  # every label covers some vertices
    assert any(lab.trunk for lab in spec.labels)
