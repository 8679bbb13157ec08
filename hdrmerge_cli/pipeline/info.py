"""info: what a bracket holds, and whether it covers its scene."""
from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from hdrmerge_cli.core.coverage import Coverage, clip_classes
from hdrmerge_cli.core.samples import Samples
from hdrmerge_cli.io.frames import Frame, cfa_corner, load_codes, read_frame
from hdrmerge_cli.io.metadata import exposure_values, fmt_time, sample_pattern
from hdrmerge_cli.io.times import apply_times
from hdrmerge_cli.pipeline import exposure_check


#: share of the pixels a bracket may leave unmeasured and still cover its scene: a bulb's
#: filament or a speck of shadow (0.1 %, 24,000 pixels of 24 MP); below it the share is
#: reported without the verdict
UNCOVERED_TOLERATED = 1e-3


def bracket_info(paths, times=None, times_file: str | None = None, crf_spec: str | None = None) -> dict:
    """Per frame: camera, exposure time, ISO, bit depth, black/white levels and the
    fractions of clipped and dark samples (:func:`~hdrmerge_cli.core.coverage.clip_classes`);
    for the bracket (frames of one layout with exposure times): whether some frame measures
    every pixel (:class:`~hdrmerge_cli.core.coverage.Coverage`) and what to add if not.
    Each frame is decoded once, two at a time: its clip classes are kept, and, for a
    bracket, the samples the exposures are measured on."""
    frames = [read_frame(p) for p in paths]
    if times is not None or times_file is not None:  # as merge and estimate-crf take them
        apply_times(frames, times, times_file)
    timed = all(f.exposure_time for f in frames)
    if timed:  # shortest exposure (time x ISO gain, as merge sorts) first, as "too bright" needs
        frames = [frames[i] for i in np.argsort(exposure_values(frames), kind="stable")]
    comparable = timed and len({f.layout for f in frames}) == 1
    coverage = Coverage() if comparable else None
    position = {id(f): k for k, f in enumerate(frames)}
    found: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # decoded out of order, taken in order
    rows: list[dict] = []
    lock = threading.Lock()

    def classes(frame, codes=None):
        codes = load_codes(frame) if codes is None else codes
        both = clip_classes(codes, sample_pattern(frame), frame.black, frame.white)
        with lock:
            found[position[id(frame)]] = both
            while len(rows) in found:  # Coverage takes the frames in order
                f = frames[len(rows)]
                clipped, dark = found.pop(len(rows))
                rows.append(f.summary() | {"width": f.width, "height": f.height, "clipped_fraction":
                                           float(np.mean(clipped)), "dark_fraction": float(np.mean(dark))})
                if coverage is not None:
                    coverage.add(clipped, dark)

    samples = None
    if comparable and len(frames) > 1:  # the exposures' samples and the classes from one decode
        samples = exposure_check.ordered_samples(frames, exposure_values(frames), load_codes,
                                                 cfa_corner(frames[0]) if frames[0].kind == "raw" else None, classes)
    else:
        with ThreadPoolExecutor(2) as pool:
            list(pool.map(classes, frames))
    out = {"frames": rows, "bracket": _bracket_summary(frames, coverage, timed)}
    if samples is not None:
        out["exposure_estimates"] = _estimates(frames, samples, crf_spec)
        for row, est in zip(rows, out["exposure_estimates"]["frames"]):
            row["estimated_exposure_time"] = est["estimate_seconds"]
    return out


def _estimates(frames: list[Frame], s: Samples, crf_spec: str | None) -> dict:
    """The exposures measured on the frames (as merge checks them), through ``crf_spec``
    (``--crf``; a profile JSON's CRF) or, for images without it, a response fitted on the
    bracket; a label more than 1/3 EV off is also a warning."""
    from hdrmerge_cli.core.crf import CRF
    from hdrmerge_cli.io.crfspec import resolve_crf

    if frames[0].kind in ("raw", "linear"):
        crf = CRF("linear")
    elif crf_spec:
        crf = resolve_crf(crf_spec)
    else:
        crf = CRF("srgb", assumed=True)  # unverified: the check fits its own response on the bracket
    return exposure_check.check_labels(frames, exposure_values(frames), s, crf, "; merge with --times estimate to use the estimates")


def _bracket_summary(frames: list[Frame], coverage: Coverage | None, timed: bool) -> dict:
    out = {"frames": len(frames)}
    if timed:
        t = [f.exposure_time for f in frames]
        out["exposure_range_ev"] = float(np.log2(t[-1] / t[0]))
    if coverage is None:
        out["covers_scene"] = None
        out["advice"] = ("give every frame an exposure time to judge the coverage" if not timed else
                         "the frames differ in type, size, channels or camera: not one bracket")
        return out
    out |= {"covers_scene": coverage.uncovered <= UNCOVERED_TOLERATED, "uncovered_fraction": coverage.uncovered,
            "too_bright_fraction": coverage.too_bright, "too_dark_fraction": coverage.too_dark,
            "gap_fraction": coverage.gap}
    advice = []
    if coverage.too_bright:
        advice.append(f"{100 * coverage.too_bright:.3g} % of pixels are clipped in every frame: add an exposure "
                      f"shorter than {fmt_time(frames[0].exposure_time)}")
    if coverage.too_dark:
        advice.append(f"{100 * coverage.too_dark:.3g} % of pixels are dark in every frame: add an exposure "
                      f"longer than {fmt_time(frames[-1].exposure_time)}")
    if coverage.gap:
        advice.append(f"{100 * coverage.gap:.3g} % of pixels are dark in one frame and clipped in the next: "
                      "add exposures between them")
    out["advice"] = "; ".join(advice) or "every pixel is measured by some frame"
    if advice and out["covers_scene"]:
        out["advice"] += f"; within the {100 * UNCOVERED_TOLERATED:g} % of pixels tolerated"
    return out


def format_info(summary: dict) -> str:
    """The human-readable table of :func:`bracket_info` (one line per frame, then the
    bracket)."""
    head = ("file", "camera", "exposure", "estimate", "ISO", "bits", "black", "white", "clipped", "dark")
    lines = []
    for r in summary["frames"]:
        black = sorted(set(r["black"]))
        white = sorted(set(r["white"]))
        lines.append((
            r["path"].rsplit("/", 1)[-1], r["camera"] or "-",
            fmt_time(r["exposure_time"]) if r["exposure_time"] else "-",
            fmt_time(r["estimated_exposure_time"]) if r.get("estimated_exposure_time") else "-",
            f"{r['iso']:g}" if r["iso"] else "-", str(r["bits"]),
            "/".join(f"{b:g}" for b in black), "/".join(f"{w:g}" for w in white),
            f"{100 * r['clipped_fraction']:.2f} %", f"{100 * r['dark_fraction']:.2f} %",
        ))
    widths = [max(len(row[i]) for row in [head, *lines]) for i in range(len(head))]
    text = ["  ".join(c.ljust(w) for c, w in zip(row, widths)).rstrip() for row in [head, *lines]]
    b = summary["bracket"]
    span = f", {b['exposure_range_ev']:.1f} EV" if "exposure_range_ev" in b else ""
    verdict = {True: "covers the scene", False: "does not cover the scene", None: "coverage unknown"}[b["covers_scene"]]
    text.append(f"bracket: {b['frames']} frame{'s' if b['frames'] != 1 else ''}{span}; {verdict} ({b['advice']})")
    if "snr" in summary:
        s = summary["snr"]
        p = s["plan_of_the_same_time"]
        own = ("its frames leave some of the scene unmeasured (clipped in the shortest)"
               if s["predicted_worst_snr_db"] is None else f"{s['predicted_worst_snr_db']:.1f} dB")
        text.append(f"predicted worst-case SNR: {own} (between the {s['lose_dark']:g} % darkest and the "
                    f"{s['lose_bright']:g} % brightest photosites); a plan of the same {s['total_time']:.4g} s reaches "
                    f"{p['predicted_worst_snr_db']:.1f} dB with {len(p['frames'])} frames ('hdrmerge-cli plan')")
    return "\n".join(text)
