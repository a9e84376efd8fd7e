"""Gram-matrix helpers shared by the aggregators.

Every aggregator in this package works on the k x k Gram matrix ``G = J J^T`` of the raw per-memory
gradients ``J`` (k x P), never on P-dimensional vectors: the normalized Gram matrix follows from ``G``
alone (Section 3, "Nash-bargained sleep consolidation"):

    g_hat_i = g_i / (||g_i|| + eps)   =>   G_hat_ij = G_ij / ((sqrt(G_ii) + eps) (sqrt(G_jj) + eps)).
"""

from __future__ import annotations

import math

import numpy as np

GRAD_NORM_EPS = 1e-5
"""Gradient-normalization constant eps (paper Table "Sleep-consolidation hyperparameters for MT5")."""


def as_gram(gram: np.ndarray) -> np.ndarray:
    """Validate a Gram matrix and return it as a float64 array.

    Raises:
        ValueError: if it is not square, not symmetric, or holds a non-finite entry (the message names the
            memories whose rows are non-finite).
    """
    gram = np.asarray(gram, dtype=np.float64)
    if gram.ndim != 2 or gram.shape[0] != gram.shape[1] or gram.shape[0] == 0:
        raise ValueError(f"Gram matrix must be a non-empty square matrix, got shape {gram.shape}")
    if not math.isfinite(float(gram.sum())):  # one reduction; the slow path names the rows
        bad = sorted({int(i) for i in np.argwhere(~np.isfinite(gram))[:, 0]})
        raise ValueError(f"Gram matrix has non-finite entries in rows {bad} (non-finite memory gradients)")
    scale = float(np.abs(gram).max())
    if float(np.abs(gram - gram.T).max()) > 1e-6 * max(1.0, scale):
        raise ValueError("Gram matrix is not symmetric")
    return gram


def gradient_norms(gram: np.ndarray) -> np.ndarray:
    """The per-memory gradient norms ``||g_i|| = sqrt(G_ii)``."""
    return np.sqrt(np.maximum(gram.diagonal(), 0.0))


def normalized_gram(gram: np.ndarray, eps: float = GRAD_NORM_EPS) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(G_hat, scale)`` with ``scale_i = 1 / (||g_i|| + eps)`` and ``G_hat = D G D``, D = diag(scale).

    A combination ``sum_j alpha_j g_hat_j`` of normalized gradients equals ``sum_j (alpha_j scale_j) g_j``
    of raw gradients, so aggregators return raw-gradient weights ``alpha * scale``.
    """
    scale = 1.0 / (gradient_norms(gram) + eps)
    g_hat = gram * scale[:, None] * scale[None, :]
    return 0.5 * (g_hat + g_hat.T), scale


def cosine_matrix(gram: np.ndarray, active: np.ndarray | None = None, norms: np.ndarray | None = None) -> np.ndarray:
    """The cosine matrix ``G_ij / (||g_i|| ||g_j||)`` of the ``active`` (non-zero) gradients: the Gram matrix of the
    exact unit directions, symmetrized, clipped to [-1, 1], unit diagonal. ``norms`` may pass precomputed norms."""
    norms = gradient_norms(gram) if norms is None else norms
    if active is not None and not active.all():
        gram, norms = gram[active][:, active], norms[active]
    cosine = gram / np.multiply.outer(norms, norms)
    cosine = np.minimum(np.maximum(0.5 * (cosine + cosine.T), -1.0), 1.0)
    np.fill_diagonal(cosine, 1.0)
    return cosine
