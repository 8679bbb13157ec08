"""merge --align / --deghost: bring hand-held frames onto a reference frame, and drop
moving objects from the frames that disagree with it (see core/align.py, core/deghost.py)."""
from __future__ import annotations

import logging

import numpy as np

from hdrmerge_cli.core import align, deghost
from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.noise import NoiseParams
from hdrmerge_cli.core.reconstruct import channel_index, lookup
from hdrmerge_cli.io.frames import Frame, load_codes

log = logging.getLogger("hdrmerge_cli")

ALIGN_MODES = ("off", "auto", "translation", "similarity")
DEGHOST_MODES = ("off", "auto", "on")
#: ``--align auto`` applies the warps when some frame is displaced by more than this (pixels)
AUTO_ALIGN_PX = 0.25
#: a frame pair is registered only when this fraction of pixels is well exposed in both
MIN_SHARED = 0.2


def reference_index(frames: list[Frame]) -> int:
    """The reference frame of alignment and deghosting: the middle exposure."""
    return len(frames) // 2


def _linear(frame: Frame, codes: np.ndarray, crf: CRF) -> np.ndarray:
    """The registration image of a frame, full scale 1: RAW the mean of each 2 x 2 CFA cell
    (black subtracted; half resolution), images the mean of the linearised channels."""
    if frame.kind == "raw":
        black = float(np.mean(frame.black))
        return align.block_mean((codes.astype(np.float32) - black) / float(np.mean(frame.white) - black), 2)
    full = frame.n_codes - 1.0
    chans = [crf.inverse(codes[..., c] / full, c) for c in range(codes.shape[-1])]
    return np.mean(chans, axis=0).astype(np.float32)


def estimate_alignment(frames: list[Frame], exposures: np.ndarray, crf: CRF, mode: str) -> dict:
    """Warps bringing every frame onto the reference (``core.align``); ``auto`` measures
    translations and keeps them only when one exceeds :data:`AUTO_ALIGN_PX`.  Returns
    ``{"mode", "reference", "applied", "motion", "warps": [(2, 3) ...], "shift_px": [...]}``
    with warps in the frames' own sample coordinates."""
    ref = reference_index(frames)
    motion = "translation" if mode == "auto" else mode
    raw = frames[0].kind == "raw"
    images = [_linear(f, load_codes(f), crf) for f in frames]

    identity = np.hstack([np.eye(2), np.zeros((2, 1))])
    unaligned = []

    def step(a: int, b: int) -> np.ndarray:
        """Warp from frame a's coordinates to frame b's (neighbours in exposure); identity
        when too few pixels are well exposed in both to register them."""
        y_full = float(np.min(frames[a].white - frames[a].black))
        lo, hi = exposures[b] / exposures[a], 0.0  # no shared range unless common_range finds one
        try:
            lo, hi = align.common_range([exposures[a], exposures[b]], lo_code=min(0.02, 16.0 / y_full))
        except HdrMergeError:
            pass
        ea, eb = images[a] / exposures[a], images[b] / exposures[b]
        shared = float(np.mean((ea > lo) & (ea < hi) & (eb > lo) & (eb < hi)))
        if shared < MIN_SHARED:
            unaligned.append(frames[b].path)
            log.warning("%s: only %.1f %% of its pixels are well exposed in its neighbour too; left unaligned",
                        frames[b].path, 100 * shared)
            return identity
        w = align.estimate_warp(align.log_irradiance(images[a], exposures[a], lo, hi),
                                align.log_irradiance(images[b], exposures[b], lo, hi), motion)
        return align.rescale_warp(w, 2, 0.5) if raw else w  # RAW: found on 2 x 2 cells (centre 2u + 0.5)

    # each frame is registered to its neighbour towards the reference (they share the most
    # well-exposed range) and the warps are chained: W_j = step(j -+ 1, j) o W_(j -+ 1)
    warps = [None] * len(frames)
    warps[ref] = identity
    for j in list(range(ref + 1, len(frames))) + list(range(ref - 1, -1, -1)):
        prev = j - 1 if j > ref else j + 1
        warps[j] = align.compose(step(prev, j), warps[prev])
    sizes = [align.warp_size(w, f.height, f.width) for w, f in zip(warps, frames)]
    applied = mode != "auto" or max(sizes) > AUTO_ALIGN_PX
    if raw and motion == "translation":  # whole CFA periods only
        applied &= any(np.any(np.rint(w[:, 2] / 2) != 0) for w in warps)
    out = {"mode": mode, "motion": motion, "reference": frames[ref].path, "applied": bool(applied),
           "shift_px": [[round(float(w[0, 2]), 3), round(float(w[1, 2]), 3)] for w in warps],
           "largest_displacement_px": [round(s, 3) for s in sizes], "unaligned": unaligned}
    if motion == "similarity":
        out["rotation_deg"] = [round(float(np.degrees(np.arctan2(w[1, 0], w[0, 0]))), 4) for w in warps]
        out["scale"] = [round(float(np.hypot(w[0, 0], w[1, 0])), 6) for w in warps]
    out["warps"] = warps
    log.info("alignment (%s): largest displacement %.2f px; %s", motion, max(sizes),
             "applied" if applied else "not needed")
    return out


def loader(frames: list[Frame], alignment: dict | None):
    """``frame -> codes``, brought onto the reference when the alignment is applied."""
    if not alignment or not alignment["applied"]:
        return load_codes
    warps = {f.path: w for f, w in zip(frames, alignment["warps"])}
    motion = alignment["motion"]

    def load(frame: Frame) -> np.ndarray:
        codes = load_codes(frame)
        clip = int(np.max(frame.white))
        if frame.kind == "raw":
            return align.apply_warp_mosaic(codes, warps[frame.path], clip, motion)
        return align.apply_warp(codes, warps[frame.path], clip)

    return load


def _samples(codes: np.ndarray) -> np.ndarray:
    return codes.reshape(codes.shape[0], -1)


def find_ghosts(frames: list[Frame], exposures: np.ndarray, crf: CRF, noise: list[NoiseParams], load, mode: str,
                p_fa: float = deghost.P_FALSE_ALARM) -> dict:
    """Per frame, the cells inconsistent with the anchor (``core.deghost``), cleaned.
    ``noise``: one parameter set per channel (code units).  Returns ``{"mode", "applied",
    "p_false_alarm", "rejected_fraction": [...], "masks": [(cells) bool ...], "cell"}``;
    ``auto`` applies the masks only when some frame has more than
    :data:`~hdrmerge_cli.core.deghost.AUTO_FRACTION` of its cells rejected."""
    first = frames[0]
    raw = first.kind == "raw"
    cell = (2, 2) if raw else (1, first.channels)
    from hdrmerge_cli.pipeline.merge import sample_pattern

    shape = (first.height, first.width) + (() if raw else (first.channels,))
    rows2 = _samples(channel_index(shape, sample_pattern(first))).astype(np.int32)

    def estimates(k: int, bounds: bool = False):
        """Frame k's x, s and validity per sample; with ``bounds`` also what its dark or
        clipped readings bound: > 0 the x of the lowest measuring code (dark), < 0 minus the
        x of the highest one (clipped), 0 where it measures."""
        f = frames[k]
        n = f.n_codes
        tabs = [deghost.ghost_tables(n, f.black[c], f.white[c], lambda v, c=c: crf.inverse(v, 0 if raw else c),
                                     exposures[k], noise[min(c, len(noise) - 1)]) for c in range(len(f.black))]
        x_t, s_t, ok_t = (np.concatenate(col) for col in zip(*tabs))
        idx = rows2 * np.int32(n) + np.minimum(_samples(load(f)), n - 1).astype(np.int32)
        x, s, ok = x_t.astype(np.float32)[idx], s_t.astype(np.float32)[idx], ok_t[idx]
        if not bounds:
            return x, s, ok
        low = np.array([t[0][np.flatnonzero(t[2])[0]] for t in tabs], np.float32)
        high = np.array([t[0][np.flatnonzero(t[2])[-1]] for t in tabs], np.float32)
        dark = (np.arange(len(x_t)) % n <= np.repeat(np.asarray(f.black), n)) & ~ok_t
        bound_t = np.where(ok_t, 0.0, np.where(dark, np.repeat(low, n), -np.repeat(high, n))).astype(np.float32)
        return x, s, ok, bound_t[idx]

    ref = reference_index(frames)
    bound_r = estimates(ref, bounds=True)[3]
    order = sorted(range(len(frames)), key=lambda k: (abs(np.log(exposures[k] / exposures[ref])), k))
    xa = sa = None
    beyond = {}  # per frame: readings far outside the reference's dark / clipped bound
    for k in order:  # the anchor: the reference where it measures, else the nearest frame consistent with it
        x, s, ok = estimates(k)
        beyond[k] = deghost.violates_bound(x, s, bound_r) & ok
        ok &= ~beyond[k]
        if xa is None:
            xa, sa, va = x, s, ok
            source = np.where(ok, k, -1).astype(np.int16)
            continue
        take = ok & ~va
        xa[take], sa[take], source[take] = x[take], s[take], k
        va |= ok
    grad2 = _samples(deghost.squared_gradient(xa.reshape(shape), "mosaic" if raw else "rgb"))
    masks, fractions = [], []
    for k in range(len(frames)):
        x, s, ok = estimates(k)
        bad = deghost.inconsistent_cells(x, s, ok, xa, sa, va, grad2, cell, p_fa)
        bad |= deghost.cell_sums(beyond.pop(k), *cell) > 0
        bad = deghost.clean(bad) & ~(deghost.cell_sums(source == k, *cell) > 0)  # the anchor itself stays
        masks.append(bad)
        fractions.append(float(bad.mean()))
    applied = mode == "on" or max(fractions) > deghost.AUTO_FRACTION
    log.info("deghosting: up to %.2f %% of a frame's cells move; %s", 100 * max(fractions),
             "applied" if applied else "not needed")
    return {"mode": mode, "applied": bool(applied), "p_false_alarm": p_fa, "cell": cell,
            "rejected_fraction": [round(f, 6) for f in fractions], "masks": masks}


def covered(frame: Frame, warp: np.ndarray, motion: str) -> np.ndarray:
    """Which samples of the aligned frame come from inside it, ``(H, W')`` bool (a pixel's
    channels share its value); the others are stand-ins (the edge repeated) and get no
    weight in the merge."""
    h, w = frame.height, frame.width
    if frame.kind == "raw" and motion == "translation":  # whole CFA periods
        tx, ty = (2 * np.rint(warp[:, 2] / 2)).astype(int)
        rows = (np.arange(h) + ty >= 0) & (np.arange(h) + ty <= h - 1)
        cols = (np.arange(w) + tx >= 0) & (np.arange(w) + tx <= w - 1)
        return rows[:, None] & cols[None, :]
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    sx = warp[0, 0] * x + warp[0, 1] * y + warp[0, 2]
    sy = warp[1, 0] * x + warp[1, 1] * y + warp[1, 2]
    inside = (sx >= -0.5) & (sx <= w - 0.5) & (sy >= -0.5) & (sy <= h - 0.5)
    return inside if frame.kind == "raw" else np.repeat(inside, frame.channels, axis=1)


def sample_weights(tables, pattern, frames: list[Frame], ghosts: dict | None, alignment: dict | None):
    """``(k, codes) -> weights`` for the merge (see :meth:`LogMerge.add`), or None when
    neither applies: frame ``k``'s table weight ``w(z) sigma^-2``, zero in its rejected
    ghost cells and where the aligned frame does not cover the reference."""
    ghosts = ghosts if ghosts and ghosts["applied"] else None
    alignment = alignment if alignment and alignment["applied"] else None
    if ghosts is None and alignment is None:
        return None

    def weights(k: int, codes: np.ndarray) -> np.ndarray:
        rows = None if pattern is None else channel_index(codes.shape, pattern)
        w = _samples(lookup(tables[k].weight, tables[k].n_codes, codes, rows))
        if ghosts is not None:
            w *= ~deghost.expand(ghosts["masks"][k], ghosts["cell"], w.shape)
        if alignment is not None:
            w *= covered(frames[k], alignment["warps"][k], alignment["motion"])
        return w.reshape(codes.shape).astype(np.float32)

    return weights


def require_noise(noise, frames, crf, load=load_codes) -> list[NoiseParams]:
    """Noise parameters for the ghost test: given, measured on the bracket, or (failing
    both) a conservative default with a warning."""
    if noise:
        from hdrmerge_cli.io.noisespec import per_channel

        return per_channel(noise, frames[0].channel_names)
    from hdrmerge_cli.pipeline.calibrate import estimate_bracket_noise

    try:
        used, _ = estimate_bracket_noise(frames, crf, load)  # on the aligned frames
        return [NoiseParams(**used[name]) if name in used else NoiseParams(**next(iter(used.values())))
                for name in frames[0].channel_names]
    except HdrMergeError as exc:
        y_full = float(np.max(frames[0].white) - np.min(frames[0].black))
        log.warning("could not measure the noise for the ghost test (%s); assuming 1 %% of full scale", exc)
        return [NoiseParams((0.01 * y_full) ** 2, 1e-12, 0.0)]  # a 1 % read noise, no photon term
