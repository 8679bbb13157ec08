"""Estimating the inverse camera response ``g(z) = log gamma^-1(z)`` from a bracket.

The relation is (3): ``g(z_ij) - log t_j = log E_i`` for every pixel i and frame j.
Methods are picked by name from :data:`CRF_ESTIMATORS`.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import lsqr

from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.weights import weights_debevec1997_triangle

#: largest number of unknown code levels solved for; finer codes are interpolated
MAX_LEVELS = 1024


def sample_pixels(middle: np.ndarray, samples: int, rng: np.random.Generator) -> np.ndarray:
    """Flat indices of ``samples`` pixels spread evenly over the code values of
    ``middle`` (the bracket's middle frame, one channel, any shape)."""
    flat = middle.ravel()
    order = np.argsort(flat, kind="stable")
    picks = np.linspace(0, flat.size - 1, min(samples, flat.size)).astype(np.int64)
    jitter = rng.integers(-(flat.size // (2 * len(picks)) or 0), (flat.size // (2 * len(picks))) + 1, len(picks))
    return order[np.clip(picks + jitter, 0, flat.size - 1)]


def crf_debevec1997(
    codes: np.ndarray, log_exposures: np.ndarray, n_codes: int, smoothing: float = 30.0
) -> np.ndarray:
    """Debevec and Malik (1997): least squares for ``g`` and ``log E_i`` with hat weights,
    a second-difference smoothness term ``lambda`` and ``g(mid-scale) = 0``
    (no monotonicity constraint: the baseline the paper's (37) improves on).

    codes : (N, P) integer code values of N sampled pixels in P frames
    log_exposures : (P,) ``log t_j``
    n_codes : number of code values 2^B
    Returns ``g`` : (n_codes,) float64.
    """
    codes = np.asarray(codes)
    n_pix, n_frames = codes.shape
    levels = min(n_codes, MAX_LEVELS)
    z = (codes.astype(np.int64) * (levels - 1)) // (n_codes - 1)
    v = np.arange(levels) / (levels - 1)
    w = weights_debevec1997_triangle(v, v)
    wz = w[z]
    rows_data = np.arange(n_pix * n_frames)
    # data terms: w (g(z_ij) - log E_i) = w log t_j
    a_g = sp.csr_matrix((wz.ravel(), (rows_data, z.ravel())), shape=(n_pix * n_frames, levels))
    a_e = sp.csr_matrix((-wz.ravel(), (rows_data, np.repeat(np.arange(n_pix), n_frames))), shape=(n_pix * n_frames, n_pix))
    b_data = (wz * log_exposures[None, :]).ravel()
    # g(mid) = 0
    mid = levels // 2
    a_fix = sp.csr_matrix(([1.0], ([0], [mid])), shape=(1, levels + n_pix))
    # smoothness: lambda w(z) (g(z-1) - 2 g(z) + g(z+1)) = 0
    inner = np.arange(1, levels - 1)
    scale = smoothing * w[inner]
    r = np.repeat(np.arange(inner.size), 3)
    c = (inner[:, None] + np.array([-1, 0, 1])).ravel()
    vals = (scale[:, None] * np.array([1.0, -2.0, 1.0])).ravel()
    a_smooth = sp.csr_matrix((vals, (r, c)), shape=(inner.size, levels + n_pix))
    a = sp.vstack([sp.hstack([a_g, a_e]), a_fix, a_smooth]).tocsr()
    b = np.concatenate([b_data, [0.0], np.zeros(inner.size)])
    sol = lsqr(a, b, atol=1e-10, btol=1e-10, iter_lim=20000)[0]
    g = sol[:levels]
    if not np.all(np.isfinite(g)):
        raise HdrMergeError("the CRF fit failed (no finite solution)")
    return np.interp(np.arange(n_codes) * (levels - 1) / (n_codes - 1), np.arange(levels), g)


def inverse_from_log(g: np.ndarray) -> tuple[np.ndarray, bool]:
    """``gamma^-1 = exp(g)`` scaled to end at 1, made non-decreasing where the fit was not
    (returns whether that was needed).  Monotonicity is imposed from the top down
    (``min`` over higher codes), so a kink in the poorly constrained dark end lowers only
    itself instead of flattening everything above it."""
    lin = np.exp(g - g[-1])
    mono = np.minimum.accumulate(lin[::-1])[::-1]
    return mono, bool(np.any(mono < lin * (1 - 1e-12)))


#: name -> estimator(codes (N, P), log_exposures (P,), n_codes, smoothing) -> g (n_codes,)
CRF_ESTIMATORS = {"debevec": crf_debevec1997}
