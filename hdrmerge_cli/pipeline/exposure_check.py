"""Exposure labels checked against the frames (and, on request, replaced by estimates),
and the order and overlap checks that read real frames.

The numerics are :mod:`hdrmerge_cli.core.samples` and :mod:`hdrmerge_cli.core.exposure_estimate`;
here the frames are decoded, subsampled (CFA cells kept whole), normalised to
``v = (z - black) / (white - black)``, cut to the pixels worth comparing (constant borders
off, clipped and noise-floor codes off) and linearised through the response in use.
Before a label is called wrong, the pairs that decided it are registered on the same
samples (:func:`~hdrmerge_cli.core.registration.moved_pairs`): frames that moved between exposures (a hand-held bracket
merged without ``--align``) leave the labels unchecked, with a line saying so, instead of
a false label warning.
"""
from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.exposure_estimate import LABEL_TOLERANCE_EV, LabelCheck, Motion, check_exposures
from hdrmerge_cli.core.crf_estimate import MIN_OVERLAP, thin_overlap
from hdrmerge_cli.core.samples import Samples, disordered_pair, normalised_samples, sample_set
from hdrmerge_cli.io.frames import Frame, load_codes
from hdrmerge_cli.io.metadata import EQUAL_EXPOSURE_RTOL, fmt_time

log = logging.getLogger("hdrmerge_cli")

#: samples per frame the checks and estimates read (an even subsample of the frame)
MAX_SAMPLES = 1 << 18
#: spread (in v) of a line constant in every frame: a scan border
BORDER_TOL = 0.03


def ordered_samples(frames: list[Frame], exposures: np.ndarray, load=load_codes, cell=None, also=None,
                    max_samples: int = MAX_SAMPLES) -> Samples:
    """The exposures stage's one sample set: every frame decoded (two at a time), subsampled
    to about ``max_samples`` and normalised (:func:`~hdrmerge_cli.core.samples.normalised_samples`;
    ``cell``: a RAW bracket's 2 x 2 CFA cell, :func:`~hdrmerge_cli.io.frames.cfa_corner`, the
    bracket's pattern), off the constant borders, then the frames' order checked: frames
    sorted by their labels must not get darker (:func:`~hdrmerge_cli.core.samples.disordered_pair`;
    frames that read black, at the floor, and equal exposures pass: they neither confirm nor
    contradict an order), else a one-line error naming both frames.  Everything after it
    (the response, registration, the labels) trusts the order.  Frames whose labels tie
    (:data:`~hdrmerge_cli.io.metadata.EQUAL_EXPOSURE_RTOL`) are not ordered by them: the
    merge compares them as repeats, and ``--times estimate`` orders them by their estimates.
    ``also(frame, codes)``, when given, sees each frame's codes too (e.g. info's clip classes)."""
    first = frames[0]
    step = max(1, int(np.ceil(np.sqrt(first.width * first.height / max_samples))))
    if first.kind == "raw" and cell is None:
        raise ValueError("the samples of a RAW bracket need its 2 x 2 CFA cell")
    cell = np.asarray(cell, np.intp) if first.kind == "raw" else None

    def one(frame):
        codes = load(frame)
        if also is not None:
            also(frame, codes)
        return normalised_samples(codes, frame.black, frame.white, step, cell)

    with ThreadPoolExecutor(2) as pool:
        v = list(pool.map(one, frames))
    s = sample_set(v, step, first.black, first.white, first.n_codes, first.kind == "raw", BORDER_TOL)
    if any(s.border):
        log.info("constant border (rows top/bottom, columns left/right, subsampled by %d): %s left out of the checks",
                 step, "/".join(map(str, s.border)))
    found = disordered_pair(s, exposures, EQUAL_EXPOSURE_RTOL)
    if found is not None:
        k, t = found
        raise HdrMergeError(
            f"{frames[k].path}: darker than {frames[k - 1].path} on {100 * t.down_fraction:.0f} % of the pixels that "
            f"changed, though labelled a longer exposure ({fmt_time(frames[k].exposure_time)} vs "
            f"{fmt_time(frames[k - 1].exposure_time)}); check the exposure times"
        )
    return s


# ---------------------------------------------------------------- checks
def check_overlap(frames: list[Frame], s: Samples) -> None:
    """Refuse a bracket with a :func:`thin_overlap` pair, in one line naming both frames."""
    thin = thin_overlap(s)
    if thin is not None:
        k, both = thin
        pixels = frames[k].width * frames[k].height
        why = (f"the frames have only {pixels} pixels to estimate a CRF" if pixels < MIN_OVERLAP else
               _clipped_alone(frames, s, k) or "the exposures are too far apart to estimate a CRF")
        raise HdrMergeError(f"{frames[k].path}: only {both} pixels are unclipped both here and in "
                            f"{frames[k - 1].path} (need {MIN_OVERLAP}); {why}")


def _clipped_alone(frames: list[Frame], s: Samples, k: int) -> str | None:
    """Why the pair ending at frame ``k`` shares too few unclipped pixels when one frame
    alone has too few (black or white), else None."""
    lo, hi = 0.5 * s.codes_step, s.top
    for j in (k - 1, k):
        v = s.v[j][s.inside]
        if np.count_nonzero(((v > lo) & (v < hi)).all(-1)) * s.step ** 2 < MIN_OVERLAP:
            parts = [f"{100 * x:.1f} % of its pixels {what}" for x, what in (
                (np.mean((v <= lo).any(-1)), "read black"), (np.mean((v >= hi).any(-1)), "are clipped at white")) if x]
            return f"{frames[j].path} holds too few unclipped pixels ({' and '.join(parts)})"
    return None


# ---------------------------------------------------------------- the labels judged
def user_times(frames: list[Frame]) -> list[bool]:
    """Per frame, whether its time is the user's (``--times``, a times file), not its metadata's."""
    return [f.time_source != "its metadata" for f in frames]


def check_labels(frames: list[Frame], exposures: np.ndarray, s: Samples, crf: CRF, hint: str,
                 estimates: bool = False) -> dict:
    """The labels judged once on the exposures measured on the samples ``s`` through
    ``crf`` (:func:`~hdrmerge_cli.core.exposure_estimate.check_exposures`: through a
    response fitted on the bracket where ``crf`` is an unverified model; the pairs that
    decided a label in question registered on the samples), their warnings
    (:func:`warn_mislabelled`) and the ``--json`` record (:func:`report`, of the
    ``estimates`` used or the labels)."""
    labels = check_exposures(exposures, s, crf, user_times(frames))
    warn_mislabelled(frames, exposures, labels, hint)
    return report(frames, exposures, labels, "estimates" if estimates else "labels")


def warn_moved(frames: list[Frame], k: int, j: int, motion: Motion, consequence: str) -> None:
    log.warning("%s: the frames moved between exposures (about %s px between %s and %s); %s; consider --align auto",
                frames[k].path, f"{motion.px[j]:.{0 if motion.px[j] >= 10 else 1}f}", frames[j].name, frames[j + 1].name, consequence)


def report(frames: list[Frame], exposures: np.ndarray, labels: LabelCheck, used: str,
           tol_ev: float = LABEL_TOLERANCE_EV) -> dict:
    """The ``--json`` record of the estimates: per frame the label and the estimate (in
    seconds: the estimated ``h`` over the label's ISO factor) and their difference in EV,
    the estimate's standard error, the share of well-exposed pixels it rests on and whether
    it is measured (:meth:`~hdrmerge_cli.core.exposure_estimate.ExposureEstimate.measured`),
    and its :func:`~hdrmerge_cli.core.exposure_estimate.label_verdicts` entry: whether its
    label is blamed (``mislabelled``), could not be checked because the frames moved
    (``moved``), or the response is blamed instead (``response_at_fault``: why); per
    neighbour pair the measured ratio and, where registered
    (:func:`~hdrmerge_cli.core.registration.moved_pairs`), ``moved_px`` (null: not registered: no
    label in question, or too little texture); which exposures the merge used."""
    est, motion = labels.est, labels.motion
    est_h, stderr_ev, share, measured = np.exp(est.log_h), est.stderr_ev(), est.share(), est.measured()
    rows = []
    for k, f in enumerate(frames):
        factor = exposures[k] / f.exposure_time
        verdict, why, _ = labels.verdicts.get(k, (None, None, None))
        rows.append({"name": f.name, "label_seconds": f.exposure_time, "estimate_seconds": float(est_h[k] / factor),
                     "difference_ev": round(float(est.difference_ev[k]), 4),
                     "stderr_ev": round(float(stderr_ev[k]), 4), "share": round(float(share[k]), 4),
                     "measured": bool(measured[k]),
                     "mislabelled": verdict in ("pair", "given", "label"), "moved": verdict == "moved",
                     "response_at_fault": why if verdict == "response" else None})
    px = motion.px
    pairs = [{"frames": [frames[k].name, frames[k + 1].name],
              "label_ev": round(float(np.log2(exposures[k + 1] / exposures[k])), 4),
              "measured_ev": round(float(p.log_ratio / np.log(2)), 4) if p.counted else None,
              "stderr_ev": round(float(p.stderr / np.log(2)), 5) if p.counted else None,
              "pixels": p.kept, "coverage": round(p.coverage, 4),
              "moved_px": None if px.get(k) is None else round(float(px[k]), 2),
              "used": p.measured} for k, p in enumerate(est.pairs)]
    return {"used": used, "reference": frames[est.reference].name, "tolerance_ev": round(tol_ev, 4),
            "response": labels.response, "slope": round(est.slope, 4), "frames": rows, "pairs": pairs,
            "moved_threshold_px": round(motion.threshold_px, 2)}


def warn_mislabelled(frames: list[Frame], exposures: np.ndarray, labels: LabelCheck, hint: str,
                     named_moved: bool = False) -> None:
    """One line per frame of the labels' verdicts
    (:func:`~hdrmerge_cli.core.exposure_estimate.label_verdicts`): a warning naming the label (or both of
    two frames, or the user's time), a frame that moved saying its label cannot be checked
    (unless ``named_moved``: said already), and a frame whose difference the response
    explains naming the response (``labels.used``, the one read; at info level for a response
    measured on the bracket, which leaves the user nothing to change)."""
    est = labels.est
    ref = frames[est.reference]
    for k, (verdict, why, j) in labels.verdicts.items():
        f = frames[k]
        given = next((g.time_source for g in (f, ref) if g.time_source != "its metadata"), None)
        if verdict == "moved":
            if not named_moved:
                warn_moved(frames, k, j, labels.motion, "the exposure labels cannot be checked")
        elif verdict == "pair":
            log.warning("%s and %s: labelled %s and %s%s, but the frames' ratio is %+.2f EV from theirs; two frames "
                        "cannot tell which label is wrong (check both)%s", ref.path, f.path, fmt_time(ref.exposure_time),
                        fmt_time(f.exposure_time), f" by {given}" if given else "", -est.difference_ev[k], hint)
        elif verdict == "given":
            log.warning("%s: %+.2f EV from the time %s gives it (%s), and %s; check %s", f.path,
                        -est.difference_ev[k], given, fmt_time(f.exposure_time), why, given)
        elif verdict == "response":
            measured = labels.used.name.startswith(("measured", "estimate-crf"))
            (log.info if measured else log.warning)(
                "%s: %+.2f EV from its label, but %s: the %s does not fit the frames, and the label is not at fault%s",
                f.path, -est.difference_ev[k], why,
                "response measured on the bracket" if measured else "camera response in use",
                " (the camera processed this frame differently, or the light changed)" if measured else
                "; measure the response on the bracket (no --crf) or with 'hdrmerge-cli estimate-crf'")
        else:
            t_est = float(np.exp(est.log_h[k]) * f.exposure_time / exposures[k])
            log.warning("%s: labelled %s%s, but the frames say %s (%+.2f EV, alike in shadows and highlights, as a "
                        "wrong label makes; measured against %s, labelled %s)%s", f.path, fmt_time(f.exposure_time),
                        f" by {f.time_source}" if f.time_source != "its metadata" else "", fmt_time(t_est),
                        -est.difference_ev[k], ref.name, fmt_time(ref.exposure_time), hint)


@dataclass
class CheckedExposures:
    """What :func:`resolve_exposures` returns: the frames and their exposures ``(P,)`` as
    the merge uses them (re-sorted by the estimates under ``--times estimate``), the
    ``--json`` report (None for a single frame), and the samples as compared (brought onto
    the reference where the alignment applies, in the frames' order)."""

    frames: list[Frame]
    exposures: np.ndarray
    report: dict | None
    samples: Samples | None


def resolve_exposures(frames: list[Frame], exposures: np.ndarray, crf: CRF, samples: Samples | None,
                      use_estimates: bool = False, alignment=None) -> CheckedExposures:
    """merge: measure the frames' exposures on ``samples`` (:func:`ordered_samples`, whose
    order is checked) and warn about labels more than 1/3 EV off; with ``use_estimates``
    (``--times estimate``) merge with the estimates instead (frames re-sorted by them, their
    ``exposure_time`` set to them).  With the merge's ``alignment``, the samples are brought
    onto the reference by its warps where it applies them and the pairs' motion is what it
    measured (:func:`~hdrmerge_cli.core.registration.warp_motion`); without, the pairs in
    question are registered on the samples
    (:func:`~hdrmerge_cli.core.exposure_estimate.check_exposures`).

    A single frame has nothing to compare: returned as it is, with no report."""
    if len(frames) < 2:
        if use_estimates:
            log.warning("--times estimate: a single frame has nothing to compare; its label is used")
        return CheckedExposures(frames, exposures, None, samples)
    given = user_times(frames)
    warps = None if alignment is None else [alignment.warp_of(f) for f in frames]
    applied = alignment is not None and alignment.applied
    s = samples.registered(warps) if applied else samples
    nothing = s.read_nothing()
    labels = check_exposures(exposures, s, crf, given, use_estimates, warps,
                             None if alignment is None else [f.path not in alignment.unaligned for f in frames],
                             applied, (frames[0].height, frames[0].width))
    est, motion = labels.est, labels.motion
    for j in sorted(motion.moved) if use_estimates else ():  # a pair that moved keeps its labels' ratio
        warn_moved(frames, j + 1, j, motion, "their exposures' ratio is not estimated (their labels' ratio is kept)")
    if labels.power_ev > LABEL_TOLERANCE_EV and not crf.assumed:  # a model the user named, of another power
        log.warning("%s: read through the response given (%s) the frames' ratios are %.0f %% %s than their labels', "
                    "%.2f EV at the ends of the bracket: it does not fit the frames (the labels are judged where a "
                    "response fitted on the bracket agrees); measure the response on the bracket (no --crf) or with "
                    "'hdrmerge-cli estimate-crf'", frames[0].path, labels.model, 100 * abs(est.model_slope - 1),
                    "larger" if est.model_slope > 1 else "smaller", labels.power_ev)
    if 0 < len(nothing) < len(frames):  # named once, merged with their labels (all: the merge says so)
        log.warning("%s: nothing but black (the floor) or clipped readings, no evidence for or against %s; "
                    "merged as labelled", ", ".join(frames[k].path for k in nothing),
                    "the labels" if len(nothing) > 1 else "the label")
    unmeasured = [k for k, p in enumerate(est.pairs) if not p.measured and not p.moved]
    for k in unmeasured:
        log.info("%s / %s: too few pixels both expose well (%d) to measure their ratio; their labels are kept",
                 frames[k].name, frames[k + 1].name, est.pairs[k].kept)
    for j, d in sorted(motion.px.items()):
        what = ("could not be registered (too little texture, or a weak correlation)" if d is None
                else f"{d:.2f} px apart ({'moved' if d > motion.threshold_px else 'still'}: threshold "
                     f"{motion.threshold_px:.1f} px)")
        log.info("%s / %s: on the samples, %s", frames[j].name, frames[j + 1].name, what)
    # --times estimate: the pairs that moved are out of the estimates already (named above)
    warn_mislabelled(frames, exposures, labels, "" if use_estimates else
                     "; merge with --times estimate to use the estimates", use_estimates)
    rep = report(frames, exposures, labels, "estimates" if use_estimates else "labels")
    if not use_estimates:
        return CheckedExposures(frames, exposures, rep, s)
    est_h = np.exp(est.log_h)
    for f, h, h_label in zip(frames, est_h, exposures):
        f.exposure_time = float(f.exposure_time * h / h_label)
    order = np.argsort(est_h, kind="stable")
    frames = [frames[i] for i in order]
    log.info("--times estimate: exposures %s (reference %s)",
             ", ".join(f"{f.name} {fmt_time(f.exposure_time)}" for f in frames), rep["reference"])
    return CheckedExposures(frames, est_h[order], rep, replace(s, v=[s.v[i] for i in order]))
