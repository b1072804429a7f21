"""Helpers shared by the feature extractors: Laplacian spectra, block normalisation, neighbour graphs."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import eigsh
from scipy.spatial import cKDTree

from sync4d.errors import InputError


def check_shape(points: np.ndarray, faces: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
    """Validate and convert ``points`` (V, 3) float64 and ``faces`` (F, 3) int64 or None."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 4:
        raise InputError(f"features: expected points of shape (V >= 4, 3), got {pts.shape}")
    if not np.isfinite(pts).all():
        raise InputError("features: points contain NaN/inf")
    if faces is None or len(faces) == 0:
        return pts, None
    fc = np.asarray(faces, dtype=np.int64)
    if fc.ndim != 2 or fc.shape[1] != 3 or fc.min() < 0 or fc.max() >= len(pts):
        raise InputError(f"features: faces must be (F, 3) indices into {len(pts)} points, got {fc.shape}")
    return pts, fc


def unit_rms(points: np.ndarray) -> np.ndarray:
    """(V, 3) points centred at their centroid and scaled to unit RMS radius (dimensionless)."""
    centred = points - points.mean(axis=0)
    rms = float(np.sqrt((centred**2).sum(axis=1).mean()))
    if rms <= 1e-12:
        raise InputError("features: all points coincide")
    return centred / rms


def laplacian(points: np.ndarray, faces: np.ndarray | None, *, n_neighbors: int = 30) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """Robust cotangent Laplacian (Sharp & Crane 2020) and lumped mass matrix.

    Args:
        points: (V, 3) vertex positions.
        faces: (F, 3) triangles, or None to build the point-cloud Laplacian from ``n_neighbors`` neighbours.

    Returns:
        L (V, V) positive semi-definite stiffness, M (V, V) diagonal mass (both CSR).
    """
    import robust_laplacian

    if faces is None:
        L, M = robust_laplacian.point_cloud_laplacian(np.ascontiguousarray(points, dtype=np.float64), n_neighbors=min(n_neighbors, len(points) - 1))
    else:
        L, M = robust_laplacian.mesh_laplacian(np.ascontiguousarray(points, dtype=np.float64), np.ascontiguousarray(faces, dtype=np.int64))
    return sp.csr_matrix(L), sp.csr_matrix(M)


def laplacian_spectrum(
    stiffness: sp.spmatrix, mass: sp.spmatrix, n_eigen: int
) -> tuple[np.ndarray, np.ndarray]:
    """Smallest eigenpairs of the generalised problem ``L phi = lambda M phi`` (shift-invert).

    Args:
        stiffness: (V, V) L.
        mass: (V, V) M.
        n_eigen: number of eigenpairs (clipped to V - 2).

    Returns:
        eigenvalues (K,) ascending, clipped at 0; eigenvectors (V, K), M-orthonormal.
    """
    n = stiffness.shape[0]
    k = max(2, min(n_eigen, n - 2))
    # A small negative shift keeps L - sigma M positive definite for the sparse factorisation even
    # though L is singular (constant functions, one per connected component).
    sigma = -1e-6 * float(stiffness.diagonal().mean() / max(mass.diagonal().mean(), 1e-30))
    vals, vecs = eigsh(stiffness.tocsc(), k=k, M=mass.tocsc(), sigma=sigma, which="LM")
    order = np.argsort(vals)
    return np.clip(vals[order], 0.0, None), vecs[:, order]


def heat_kernel_signature(evals: np.ndarray, evecs: np.ndarray, n_times: int, *, scaled: bool = True) -> np.ndarray:
    """Heat kernel signature (Sun, Ovsjanikov & Guibas 2009) at log-spaced times.

    ``hks(x, t) = sum_i exp(-lambda_i t) phi_i(x)^2`` for t between 4 ln10 / lambda_max and
    4 ln10 / lambda_1 (lambda_1 the first non-zero eigenvalue); ``scaled`` divides by the heat trace
    ``sum_i exp(-lambda_i t)`` so each column is comparable across shapes.

    Returns:
        (V, n_times) float64.
    """
    nonzero = evals[evals > 1e-8 * max(evals.max(), 1e-30)]
    if len(nonzero) == 0:
        raise InputError("features: the Laplacian has no non-zero eigenvalue (degenerate shape)")
    t = np.geomspace(4.0 * np.log(10) / nonzero.max(), 4.0 * np.log(10) / nonzero.min(), n_times)
    weights = np.exp(-np.outer(evals, t))  # (K, T)
    hks = (evecs**2) @ weights
    if scaled:
        hks = hks / weights.sum(axis=0, keepdims=True)
    return hks


def wave_kernel_signature(
    evals: np.ndarray, evecs: np.ndarray, n_energies: int, *, variance: float = 6.0
) -> np.ndarray:
    """Wave kernel signature (Aubry, Schlickewei & Cremers 2011) at log-spaced energies.

    ``wks(x, e) = sum_i phi_i(x)^2 exp(-(e - log lambda_i)^2 / 2 sigma^2) / C_e`` over the non-zero
    eigenvalues, with sigma = ``variance`` times the energy spacing and ``C_e`` the sum of the filter
    weights (so the signature does not depend on how many eigenvalues fall near ``e``).

    Returns:
        (V, n_energies) float64.
    """
    keep = evals > 1e-8 * max(evals.max(), 1e-30)
    log_e = np.log(evals[keep])
    phi2 = evecs[:, keep] ** 2
    if len(log_e) < 2:
        raise InputError("features: need at least two non-zero Laplacian eigenvalues for the WKS")
    delta = (log_e.max() - log_e.min()) / n_energies
    sigma = variance * delta
    energies = np.linspace(log_e.min() + 2 * sigma, log_e.max() - 2 * sigma, n_energies)
    if energies[0] >= energies[-1]:  # too few eigenvalues for the margin: span the raw range
        energies = np.linspace(log_e.min(), log_e.max(), n_energies)
    weights = np.exp(-((energies[None, :] - log_e[:, None]) ** 2) / (2 * sigma**2))  # (K, E)
    return (phi2 @ weights) / np.maximum(weights.sum(axis=0, keepdims=True), 1e-300)


def standardize_columns(block: np.ndarray) -> np.ndarray:
    """Zero mean, unit variance per column, then divided by sqrt(D) (mean squared row norm 1).

    A column that is constant over the shape (e.g. the HKS of a sphere) becomes 0 instead of being
    divided by ~0, which would amplify round-off into spurious structure.
    """
    mean = block.mean(axis=0, keepdims=True)
    std = block.std(axis=0, keepdims=True)
    flat = std <= 1e-6 * (np.abs(mean) + 1e-12)
    std = np.where(flat, 1.0, std)
    out = np.where(flat, 0.0, (block - mean) / std)
    return out / np.sqrt(block.shape[1])


def l2_rows(block: np.ndarray) -> np.ndarray:
    """Each row divided by its Euclidean norm (rows of zeros stay zero)."""
    norm = np.linalg.norm(block, axis=1, keepdims=True)
    return block / np.maximum(norm, 1e-12)


def fourier_encoding(points: np.ndarray, *, dims: int, bandwidth: float, seed: int) -> np.ndarray:
    """Random Fourier features of coordinates (Rahimi & Recht 2007).

    ``phi(x) = sqrt(2 / D) cos(W x / h + b)`` with W ~ N(0, I), b ~ U[0, 2 pi): the dot product
    ``phi(x) . phi(y)`` approximates the Gaussian kernel ``exp(-|x - y|^2 / 2 h^2)``. Why: the paper
    compares a vertex with a part's *mean* feature by cosine similarity; with raw coordinates that only
    sees the direction from the centroid (a thigh and a shin below it look the same), while with this
    encoding the part mean becomes a kernel density of the part and cosine a normalised density.

    Args:
        points: (V, 3) coordinates in the common normalised frame.
        dims: D, number of features.
        bandwidth: h, kernel width in the units of ``points``.
        seed: the same seed must be used for both shapes so they share W and b.

    Returns:
        (V, D) float64, rows of norm ~1.
    """
    rng = np.random.default_rng(seed)
    w = rng.standard_normal((3, dims))
    b = rng.uniform(0.0, 2 * np.pi, dims)
    return np.sqrt(2.0 / dims) * np.cos(points @ w / bandwidth + b)


def mesh_components(n_vertices: int, faces: np.ndarray) -> int:
    """Number of connected components of a triangle mesh (isolated vertices count as components)."""
    from scipy.sparse.csgraph import connected_components

    adj = sp.coo_matrix(
        (np.ones(3 * len(faces)), (faces.reshape(-1), np.roll(faces, 1, axis=1).reshape(-1))), shape=(n_vertices, n_vertices)
    )
    return int(connected_components(adj, directed=False)[0])


def neighbour_graph(points: np.ndarray, faces: np.ndarray | None, *, k: int = 8) -> sp.csr_matrix:
    """(V, V) symmetric 0/1 adjacency: mesh edges, or k nearest neighbours for a point cloud."""
    n = len(points)
    if faces is not None:
        rows = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2]])
        cols = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    else:
        _, idx = cKDTree(points).query(points, k=min(k + 1, n))
        rows = np.repeat(np.arange(n), idx.shape[1] - 1)
        cols = idx[:, 1:].reshape(-1)
    adj = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)).tocsr()
    adj = ((adj + adj.T) > 0).astype(np.float64)
    adj.setdiag(0)
    adj.eliminate_zeros()
    return adj.tocsr()
