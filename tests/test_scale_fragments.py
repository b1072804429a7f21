"""count_fragments at scale: the one-query path for small pieces gives the brute-force count."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial.distance import cdist

from sync4d.run import metrics as M


def brute_force_fragments(x, pairs, strain, gap):
    """Every piece but the largest whose every point is >= gap from every point outside it."""
    keep = strain <= M.TORN_STRAIN
    n = len(x)
    graph = coo_matrix((np.ones(keep.sum()), (pairs[keep, 0], pairs[keep, 1])), shape=(n, n))
    n_comp, label = connected_components(graph, directed=False)
    main = np.argmax(np.bincount(label))
    d = cdist(x, x)
    return sum(1 for c in range(n_comp) if c != main and d[label == c][:, label != c].min() >= gap)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fragments_match_brute_force_with_many_small_and_some_large_pieces(seed):
    rng = np.random.default_rng(seed)
    x = rng.random((1500, 3))
    x[:150] += rng.choice([0.0, 2.5], (150, 1))  # some pieces far off
    pairs = M.rest_neighbour_pairs(x, 8)
    strain = rng.random(len(pairs)) * 0.25  # about half the pairs torn: hundreds of pieces of all sizes
    for gap in (0.005, 0.03, 0.1, 0.5):
        assert M.count_fragments(x, pairs, strain, gap) == brute_force_fragments(x, pairs, strain, gap), gap
