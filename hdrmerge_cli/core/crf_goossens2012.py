"""The paper's CRF estimation (section "Estimation of the CRF", (35)-(37)): a monotone,
noise-weighted quadratic program for ``g(z) = log gamma^-1(z)``.

For two frames ``j, j'`` of one pixel, (35) gives
``g(z_ij) - g(z_ij') ~ N(log(h_j / h_j'), sigma^2(E, h_j) + sigma^2(E, h_j'))``, so the
maximum-likelihood ``g`` minimises (36)/(37)::

    sum_{j<j'} f_jj' sum_i w_j(z_ij) w_j'(z_ij') (g(z_ij) - g(z_ij') - log(h_j / h_j'))^2
        + lambda * integral w_smooth(v)^2 g''(v)^2 dv
    s.t. g(z) >= g(z - 1) + epsilon,   g(mid-scale) = 0

with the image-pair factor ``f_jj' = h_j h_j' / (h_j + h_j')`` (photon noise dominant) or
``h_j^2 h_j'^2 / (h_j^2 + h_j'^2)`` (offset noise dominant), the position-dependent
``1 / E_i`` dropped as the paper proposes.

The residual depends on a pixel only through its pair of codes, so the pixels are first
aggregated into comparagrams (joint histograms of ``(z_ij, z_ij')``, Mann & Picard): the QP
has one row per occupied code pair, at most ``L (L - 1) / 2`` for ``L`` code levels, however
many pixels went in.  Codes of 12/16-bit data are binned to ``L <= 1024`` knots.

With a noise-model weighting, weights and CRF depend on each other: the first solve uses
the weights (e.g. the ``bounded`` scheme's) for an identity CRF, each next one the weights
for the CRF just found, until ``g`` stops changing.  The default weighting is ``triangle``
(see :data:`DEFAULT_WEIGHTING`).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.jit import njit, num_threads, prange
from hdrmerge_cli.core.weights import NOISE_MODEL_WEIGHTS


#: largest number of code levels (knots) solved for; finer codes are binned and interpolated
MAX_LEVELS = 1024
#: smallest step of g between neighbouring knots (the epsilon of (37))
EPSILON = 1e-5
#: default smoothness weight of (37); the data term is a weighted mean and the penalty the
#: integral of ``w_smooth^2 g''^2`` over normalised codes, so lambda does not depend on the
#: pixel count or the bit depth
DEFAULT_LAMBDA = 1e-5
#: default weight of the channel coupling of :func:`solve_qp_channels` (normalised like
#: lambda); chosen on the real brackets' leave-one-out (benchmarks/results/real_loo.md)
DEFAULT_COUPLING = 1e-2
#: default weight of the prior on the slopes of ``g`` (:func:`solve_qp_channels`, normalised
#: like lambda): it decides only where the frames leave the response undetermined.  Chosen
#: by leave-one-out on five of the shared real brackets and checked on the five others
#: (benchmarks/results/real_loo.md)
DEFAULT_ANCHOR = 3e-4
#: the weighting function ``w_j(z)`` of (36) unless told otherwise.  Not the paper's
#: ``bounded``: with its JPEG bounds the weights are too narrow for CRF estimation (the ends
#: of g are left to the smoothness term and the comparametric ambiguity of +-2 EV brackets
#: shows as waves); see benchmarks/results/crf_dorf.md
DEFAULT_WEIGHTING = "triangle"
#: mean of the irradiance prior handed to the noise-model weights: flat (see crf_goossens2012)
FLAT_PRIOR = 1e300
#: the image-pair factor ``f_jj'`` of (37) for each dominant noise source
PAIR_WEIGHTS = ("photon", "offset")


@dataclass(frozen=True)
class Comparagram:
    """Occupied code pairs of all frame pairs ``j < j'`` of one channel.

    a, b : (M,) knot indices of the shorter (``a``) and longer (``b``) exposure's code
    j, jp : (M,) the frame indices
    count : (M,) number of pixels with that pair of codes
    levels : number of knots ``L``
    """

    a: np.ndarray
    b: np.ndarray
    j: np.ndarray
    jp: np.ndarray
    count: np.ndarray
    levels: int


@dataclass(frozen=True)
class CRFFit:
    """g : (n_codes,) float64 ``log gamma^-1(z)`` with ``g(mid-scale) = 0``;
    iterations : solves done; converged : whether ``g`` settled before the limit;
    rows : occupied comparagram cells (the size of the data term)"""

    g: np.ndarray
    iterations: int
    converged: bool
    rows: int = 0


def standard_prior(n_codes: int) -> np.ndarray:
    """``(n_codes,)`` ``log gamma0^-1(z)`` of the standard response the slope prior added to
    (37) leans on (:func:`solve_qp_channels`): the sRGB curve (IEC 61966-2-1), which
    cameras' JPEG tone curves start from; floored at half a code's linear step so that
    ``log`` is finite at code 0."""
    from hdrmerge_cli.core.crf import CRF

    x = CRF("srgb").codes_table(n_codes)[0]
    return np.log(np.maximum(x, 0.5 * x[1]))


def knot_levels(n_codes: int) -> int:
    return min(n_codes, MAX_LEVELS)


def to_knots(codes: np.ndarray, n_codes: int, levels: int) -> np.ndarray:
    """Nearest knot of each code value (the codes themselves when every code is a knot)."""
    codes = np.asarray(codes)
    if levels == n_codes:
        return codes
    return np.rint(codes * ((levels - 1) / (n_codes - 1))).astype(np.uint16)


def from_knots(g_knots: np.ndarray, n_codes: int) -> np.ndarray:
    """``g`` at every code value, linearly interpolated from the ``L`` knots (knot ``k``
    sits at code ``k (n_codes - 1) / (L - 1)``, the centre of the codes binned to it)."""
    levels = g_knots.size
    return np.interp(np.arange(n_codes), np.arange(levels) * ((n_codes - 1) / (levels - 1)), g_knots)


def comparagram(knots: np.ndarray, levels: int) -> Comparagram:
    """Joint histograms of every frame pair.

    knots : (N, P) knot index (unsigned integers below ``levels``) of each pixel in each
        frame (frames in exposure order)
    """
    n_frames = knots.shape[1]
    parts = []
    for j in range(n_frames):
        for jp in range(j + 1, n_frames):
            counts = _pair_counts(knots, levels, j, jp, num_threads())
            occupied = np.flatnonzero(counts)
            parts.append((occupied // levels, occupied % levels, np.full(occupied.size, j), np.full(occupied.size, jp),
                          counts[occupied]))
    a, b, j, jp, count = (np.concatenate(col) for col in zip(*parts))
    return Comparagram(a, b, j, jp, count.astype(np.float64), levels)


@njit(parallel=True, nogil=True, cache=True)
def _pair_counts(knots, levels, j, jp, chunks):  # pragma: no cover
    """Counts of ``(knots[:, j], knots[:, jp])``, flattened ``(levels * levels,)``; one
    histogram per chunk of pixels, summed at the end."""
    n = knots.shape[0]
    step = (n + chunks - 1) // chunks
    hist = np.zeros((chunks, levels * levels), np.int64)
    for t in prange(chunks):
        for i in range(t * step, min(n, (t + 1) * step)):
            hist[t, np.intp(knots[i, j]) * levels + np.intp(knots[i, jp])] += 1
    return hist.sum(axis=0)


def pair_factor(h: np.ndarray, kind: str = "photon") -> np.ndarray:
    """``f_jj'`` of (37) for every frame pair, (P, P): the inverse of the summed variances
    of (22) up to a factor common to all pairs."""
    hj, hk = h[:, None], h[None, :]
    if kind == "photon":
        return hj * hk / (hj + hk)
    if kind == "offset":
        return hj**2 * hk**2 / (hj**2 + hk**2)
    raise ValueError(f"unknown pair weight {kind!r}; choose from {', '.join(PAIR_WEIGHTS)}")


def _data_rows(cg: Comparagram, w: np.ndarray, log_h: np.ndarray):
    """The data term of (37) as ``|D g - r ybar|^2``, rows of equal code pairs merged
    (``sum_k w_k (d - y_k)^2 = W (d - ybar)^2 + const``), normalised to a weighted mean."""
    import scipy.sparse as sp

    L = cg.levels
    target = log_h[cg.j] - log_h[cg.jp]
    keep = w > 1e-12 * w.max(initial=0.0)  # underflowed noise-model weights add nothing but ill-conditioning
    if not np.any(keep):
        raise HdrMergeError("no pair of frames shares a pixel that both expose validly; the CRF is not identifiable")
    cell = cg.a[keep].astype(np.int64) * L + cg.b[keep]
    uniq, inv = np.unique(cell, return_inverse=True)
    wsum = np.bincount(inv, weights=w[keep])
    ybar = np.bincount(inv, weights=w[keep] * target[keep]) / wsum
    a, b = uniq // L, uniq % L
    r = np.sqrt(wsum / wsum.sum())
    m = uniq.size
    d = sp.csr_matrix((np.concatenate([r, -r]), (np.tile(np.arange(m), 2), np.concatenate([a, b]))), shape=(m, L))
    return d, r * ybar


def solve_qp_channels(cgs: list[Comparagram], ws: list[np.ndarray], w_smooths: list[np.ndarray], log_h: np.ndarray,
                      smoothing: float, coupling: float = 0.0, epsilon: float = EPSILON, anchor: float = 0.0,
                      prior: np.ndarray | None = None) -> np.ndarray:
    """(37) for ``C`` channels at once, optionally coupled: each channel's data and
    smoothness terms, plus
    ``coupling * sum_c integral (g_c'(v) - mean_c g_c'(v))^2 dv``, which pulls the slopes of
    the channels' curves together where their own data are weak (a camera applies one tone
    curve to every channel, so a neutral ramp should stay neutral), and leaves them apart
    where the data say they differ.  ``coupling = 0`` gives ``C`` independent solves.
    With a ``prior`` curve ``g0`` (``(C, L)``, knots) and ``anchor > 0``, also
    ``anchor * sum_c integral (g_c'(v) - g0_c'(v))^2 dv``: a Gaussian prior on the slopes,
    which decides only where the comparagrams leave ``g`` undetermined (code levels no
    pair reaches, the comparametric ambiguity of frames far apart), since the data term is a
    weighted mean of order 1 and the prior spreads ``anchor`` over every knot.

    cgs : per channel, the :class:`Comparagram` (same ``L``)
    ws : per channel, ``(M,)`` weight of each comparagram cell (count times ``w_j w_j' f_jj'``)
    w_smooths : per channel, ``(L,)`` weight of the smoothness penalty at each knot
    log_h : ``(P,)``
    Returns G : (C, L) with ``G[:, L // 2] = 0``.
    """
    import scipy.sparse as sp

    C, L = len(cgs), cgs[0].levels
    # one vector g = (g_0, ..., g_{C-1}) of C * L knots; every term a sparse matrix on it
    rows, targets = zip(*(_data_rows(cg, w, log_h) for cg, w in zip(cgs, ws)))
    data = sp.block_diag(rows, format="csr")
    # the objective as the quadratic form g' P g - 2 q' g (+ const): C * L unknowns however
    # many comparagram rows there are, which Clarabel solves directly
    quad = data.T @ data
    smooth = sp.block_diag([second_difference(ws_) for ws_ in w_smooths], format="csr")
    if smoothing > 0 and smooth.shape[0]:
        quad = quad + smoothing * (smooth.T @ smooth)
    step = sp.diags([-np.ones(L - 1), np.ones(L - 1)], [0, 1], shape=(L - 1, L))
    steps = sp.kron(sp.identity(C), step, format="csr")
    if coupling > 0 and C > 1:
        # slopes minus the channels' mean slope; integral on the knot spacing dv = 1 / (L - 1)
        centre = sp.csr_matrix(sp.kron(sp.identity(C) - np.full((C, C), 1.0 / C), sp.identity(L - 1)) @ steps)
        quad = quad + coupling * (L - 1) * (centre.T @ centre)
    linear = data.T @ np.concatenate(targets)
    if anchor > 0 and prior is not None:
        quad = quad + anchor * (L - 1) * (steps.T @ steps)
        linear = linear + anchor * (L - 1) * (steps.T @ (steps @ np.asarray(prior, np.float64).reshape(-1)))
    quad = sp.csc_matrix((quad + quad.T) / 2)
    mid = sp.csr_matrix((np.ones(C), (np.arange(C), np.arange(C) * L + L // 2)), shape=(C, C * L))
    g = _solve_clarabel(quad, linear, mid, steps, epsilon)
    if g is None:
        g = _solve_cvxpy(quad, linear, mid, steps, epsilon)
    return g.reshape(C, L)


def _solve_clarabel(quad, linear, mid, steps, epsilon: float) -> np.ndarray | None:
    """The QP of (37), ``min g' Q g - 2 l' g`` s.t. ``mid g = 0`` (``g(mid-scale) = 0`` per
    channel) and ``steps g >= epsilon``, with Clarabel directly (its form: ``min x' P x / 2
    + q' x``, ``A x + s = b``, ``s`` in the zero cone then the nonnegative cone); None when
    it does not solve."""
    import clarabel
    import scipy.sparse as sp

    a = sp.vstack([mid, -steps], format="csc")
    b = np.concatenate([np.zeros(mid.shape[0]), np.full(steps.shape[0], -epsilon)])
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    cones = [clarabel.ZeroConeT(mid.shape[0]), clarabel.NonnegativeConeT(steps.shape[0])]
    solution = clarabel.DefaultSolver(sp.triu(2 * quad, format="csc"), -2 * np.asarray(linear, np.float64), a, b,
                                      cones, settings).solve()
    if str(solution.status) not in ("Solved", "AlmostSolved"):
        return None
    x = np.asarray(solution.x, dtype=np.float64)
    return x if np.all(np.isfinite(x)) else None


def _solve_cvxpy(quad, linear, mid, steps, epsilon: float) -> np.ndarray:
    """The same QP through cvxpy with OSQP, where Clarabel stalls."""
    import cvxpy as cp

    g = cp.Variable(quad.shape[0])
    objective = cp.quad_form(g, cp.psd_wrap(quad)) - 2 * linear @ g
    problem = cp.Problem(cp.Minimize(objective), [steps @ g >= epsilon, mid @ g == 0])
    status = "not run"
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            problem.solve(solver="OSQP")
        status = problem.status
    except cp.error.SolverError:
        status = "OSQP failed"
    if status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) or g.value is None:
        raise HdrMergeError(f"the CRF quadratic program did not solve ({status}); try another --lambda or --method")
    return np.asarray(g.value, dtype=np.float64)


def second_difference(w_smooth: np.ndarray):
    """Rows ``S`` with ``|S g|^2 = integral w_smooth(v)^2 g''(v)^2 dv`` (the smoothness term
    of (37)) by central differences on the knots ``v = k / (L - 1)``.  w_smooth : (L,)"""
    import scipy.sparse as sp

    L = w_smooth.size
    k = np.arange(1, L - 1)
    scale = w_smooth[k] * (L - 1) ** 1.5  # g'' = (L-1)^2 * second difference, dv = 1/(L-1)
    return sp.csr_matrix(((scale[:, None] * np.array([1.0, -2.0, 1.0])).ravel(),
                          (np.repeat(np.arange(k.size), 3), (k[:, None] + np.array([-1, 0, 1])).ravel())),
                         shape=(k.size, L))


def crf_goossens2012(
    codes,
    log_exposures: np.ndarray,
    n_codes: int,
    smoothing: float = DEFAULT_LAMBDA,
    *,
    weighting: str = DEFAULT_WEIGHTING,
    noise=None,
    bounds=None,
    pair_weight: str = "photon",
    coupling: float = DEFAULT_COUPLING,
    anchor: float = 0.0,
    prior: np.ndarray | None = None,
    max_iterations: int = 10,
    tol: float = 1e-3,
) -> CRFFit:
    """(37) with the chicken-and-egg loop between weights and CRF.

    codes : (N, P) integer code values of N pixels in P frames, frames in exposure order;
        or a list of C such arrays, one per channel, solved together with the channel
        ``coupling`` of :func:`solve_qp_channels` (``g`` is then (C, n_codes))
    log_exposures : (P,) ``log h_j``
    n_codes : number of code values ``2^B``
    smoothing : lambda of (37)
    weighting : the ``w_j(z)`` of (36), a name in
        :data:`~hdrmerge_cli.core.weights.WEIGHTING_FUNCTIONS`; noise-model weights are
        evaluated with a flat irradiance prior (both codes of a pair see the same ``E``, so
        no per-frame prior applies) for the current CRF estimate
    noise, bounds : :class:`~hdrmerge_cli.core.noise.NoiseParams` (code values of the
        linear signal; one, or one per channel) for the noise-model weights, or the
        ``(1/alpha, sigma_o^2, beta)`` upper bounds of ``bounded`` (default: the paper's JPEG values)
    pair_weight : ``photon`` or ``offset``, which noise dominates (the factor ``f_jj'``)
    anchor, prior : the weight of a prior on the slopes of ``g`` and the prior curve,
        ``(n_codes,)`` or ``(C, n_codes)`` ``log gamma0^-1(z)`` of a standard response
        (see :func:`solve_qp_channels`); 0 or None: no prior
    tol : stop when ``g`` moves less than this (natural log units) at every used knot
    """
    from hdrmerge_cli.core.crf import table_crf
    from hdrmerge_cli.core.reconstruct import certainty_table

    single = not isinstance(codes, (list, tuple))
    channels = [codes] if single else list(codes)
    noises = noise if isinstance(noise, (list, tuple)) else [noise] * len(channels)
    log_h = np.asarray(log_exposures, dtype=np.float64)
    h = tuple(float(x) for x in np.exp(log_h))
    L = knot_levels(n_codes)
    cgs = [comparagram(to_knots(z, n_codes, L), L) for z in channels]
    pair = pair_factor(np.asarray(h), pair_weight)
    knot_codes = np.rint(np.arange(L) * ((n_codes - 1) / (L - 1))).astype(np.int64)
    used = np.zeros(L, bool)
    for cg in cgs:
        used[cg.a] = used[cg.b] = True
    lin = np.tile(np.arange(n_codes) / (n_codes - 1), (len(channels), 1))  # identity CRF to start
    g_prev, converged, it = None, False, 0
    prior_knots = None
    if prior is not None:
        prior_knots = np.broadcast_to(np.asarray(prior, np.float64).reshape(-1, n_codes), (len(channels), n_codes))
        prior_knots = prior_knots[:, knot_codes] - prior_knots[:, knot_codes[L // 2]][:, None]
    for it in range(1, max_iterations + 1):
        ws, smooths = [], []
        for c, cg in enumerate(cgs):
            crf = table_crf(lin[c][None], "estimate")
            wk = np.stack([certainty_table(n_codes, 0.0, n_codes - 1.0, crf, weighting, hj,
                                           None if noises[c] is None else [noises[c]], FLAT_PRIOR, h, bounds=bounds)[0]
                           for hj in h])[:, knot_codes]
            ws.append(cg.count * wk[cg.j, cg.a] * wk[cg.jp, cg.b] * pair[cg.j, cg.jp])
            smooths.append(np.maximum(wk.mean(axis=0), 1e-3 * max(wk.max(), 1e-300)))
        g_knots = solve_qp_channels(cgs, ws, smooths, log_h, smoothing, coupling, anchor=anchor, prior=prior_knots)
        g = np.stack([from_knots(gk, n_codes) for gk in g_knots])
        lin = np.exp(g - g[:, -1:])
        if weighting not in NOISE_MODEL_WEIGHTS:  # the weights do not depend on the CRF
            converged = True
            break
        if g_prev is not None and np.max(np.abs(g_knots - g_prev)[:, used]) < tol:
            converged = True
            break
        g_prev = g_knots
    return CRFFit(g[0] if single else g, it, converged, sum(cg.a.size for cg in cgs))


def crf_goossens2012_prior(codes, log_exposures: np.ndarray, n_codes: int, smoothing: float = DEFAULT_LAMBDA, *,
                           anchor: float = DEFAULT_ANCHOR, prior: np.ndarray | None = None, **options) -> CRFFit:
    """:func:`crf_goossens2012` with its prior towards the standard curve (``prior``, default
    :func:`standard_prior`; weight ``anchor``) where the frames leave ``g`` open: the method
    ``goossens`` of estimate-crf and of the merge's response."""
    prior = standard_prior(n_codes) if prior is None else prior
    return crf_goossens2012(codes, log_exposures, n_codes, smoothing, anchor=anchor, prior=prior, **options)
