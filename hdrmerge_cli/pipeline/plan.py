"""plan: which bracket to shoot, from metering frames and the camera's noise per ISO.

The metering frames are merged as ``merge`` does; their merged irradiance gives the
scene's range per channel (:func:`scene_range`), the profile's calibrated ISOs (or the
noise measured on the metering frames) the settings' noise, and
:mod:`hdrmerge_cli.core.capture_hasinoff2010` the plan.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from hdrmerge_cli.core import capture_hasinoff2010 as capture
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.noise import NoiseParams
from hdrmerge_cli.core.reconstruct import FLAG_DARK, FLAG_SATURATED
from hdrmerge_cli.io.noisespec import iso_key, iso_of_key, noise_from_profile, per_channel

log = logging.getLogger("hdrmerge_cli")

#: side of the box (same-colour photosites) that averages the metered irradiance before
#: its percentiles are taken, so that the metering frames' own noise does not widen the range
SMOOTH = 3
#: 1-EV bins of the SNR-against-irradiance table
TABLE_STEP_EV = 1.0
#: bins (EV) of the histogram of the scene's photosites, and the share of a channel's
#: photosites a bin must hold to count in the worst case (which ignores rarer irradiances,
#: as it ignores the darkest --lose-dark and the brightest --lose-bright)
OCCUPIED_BIN_EV, OCCUPIED_SHARE = 1 / 12, 1e-3


@dataclass(frozen=True)
class PlanOptions:
    """``time``: budget (s); ``min_snr``: the worst-case SNR to reach (dB); ``frames``: at
    most this many; ``shutter_speeds``/``isos``: the settings allowed (None: the 1/3-stop
    series, the profile's calibrated ISOs); ``lose_dark``, ``lose_bright``: the shares (%)
    of each channel's darkest and brightest photosites the plan may lose (the range it
    protects lies between); the rest: the metering frames' inputs as in ``merge``."""

    time: float | None = None
    min_snr: float | None = None
    frames: int = 10
    shutter_speeds: tuple | None = None
    isos: tuple | None = None
    lose_dark: float = 1.0
    lose_bright: float = 0.1
    profile: str | None = None
    crf: str | None = None
    times: list | None = None
    times_file: str | None = None
    noise_cache: bool = True
    search_time: float = capture.TIME_LIMIT


@dataclass
class Metering:
    """The metered scene: ``scene`` (:class:`~capture.SceneRange`), the channel names, the
    reference ISO (that of the metering frame of shortest exposure, which the merge's
    units refer to; None when the files state none), the full scale per channel (code
    values), the noise per ISO (key None: measured on the metering frames, at their ISO),
    the metering frames' own settings (``(time, iso)`` per frame) and the fraction of
    photosites clipped in every frame."""

    scene: capture.SceneRange
    channels: list[str]
    reference_iso: float | None
    y_full: tuple[float, ...]
    noise: dict[float | None, tuple[NoiseParams, ...]]
    own: list[tuple[float, float | None]]
    clipped: float
    camera: str
    source: str


def channel_planes(r: np.ndarray, flags: np.ndarray, cell: np.ndarray | None, n_channels: int) -> list[list]:
    """Per channel, its photosites as 2-D planes ``(irradiance, flags)``: an image's
    channel, or each position of a mosaic's 2 x 2 CFA ``cell`` (channel indices)."""
    if cell is None:
        return [[(r[..., c], flags[..., c])] for c in range(n_channels)]
    out = [[] for _ in range(n_channels)]
    for i in range(cell.shape[0]):
        for j in range(cell.shape[1]):
            out[cell[i, j]].append((r[i::cell.shape[0], j::cell.shape[1]], flags[i::cell.shape[0], j::cell.shape[1]]))
    return out


def scene_range(planes: list[list], lose_dark: float, lose_bright: float, names: list[str]) -> capture.SceneRange:
    """Per channel, the range a plan protects: ``lo`` and ``hi`` the ``lose_dark`` and
    ``100 - lose_bright`` percentiles of the photosites' irradiance, each averaged over
    :data:`SMOOTH` x :data:`SMOOTH` same-colour photosites (a photosite dark in every frame
    counts as 0; the box keeps the metering frames' own noise out of both ends); the
    intervals of ``[lo, hi]`` the photosites hold (:func:`_occupied`); and the photosites
    themselves in :data:`OCCUPIED_BIN_EV` bins (:attr:`~capture.SceneRange.photosites`).

    planes : :func:`channel_planes`, irradiance in code values per second at the
        reference ISO
    """
    from scipy.ndimage import uniform_filter

    lo, hi, occupied, photosites = [], [], [], []
    for c, chan in enumerate(planes):
        v = np.concatenate([uniform_filter(np.where(f == FLAG_DARK, 0.0, p).astype(np.float64), SMOOTH,
                                           mode="nearest").ravel() for p, f in chan])
        low, top = (float(x) for x in np.percentile(v, [lose_dark, 100.0 - lose_bright]))
        if not low > 0:
            raise HdrMergeError(f"the darkest {lose_dark:g} % of the {names[c]} photosites read no light in the "
                                "metering frames; meter with a longer frame, or raise --lose-dark")
        lo.append(low)
        hi.append(max(top, low))
        r, counts = _histogram(v, low)
        photosites.append((r, counts / v.size))
        half = 2.0 ** (OCCUPIED_BIN_EV / 2)
        inside = (r * half > low) & (r / half < hi[-1])
        occupied.append(_occupied(r[inside], counts[inside] >= OCCUPIED_SHARE * v.size, low, hi[-1]))
    return capture.SceneRange(tuple(lo), tuple(hi), tuple(occupied), tuple(photosites))


def _histogram(v: np.ndarray, anchor: float) -> tuple[np.ndarray, np.ndarray]:
    """The irradiances ``v`` in :data:`OCCUPIED_BIN_EV` bins of log2 r, one edge at
    ``anchor``: the occupied bins' centres (irradiance; 0 for the photosites that read no
    light) and their counts."""
    lit = v[v > 0]
    k = np.floor((np.log2(lit) - np.log2(anchor)) / OCCUPIED_BIN_EV).astype(np.int64)
    bins, counts = np.unique(k, return_counts=True)
    r = anchor * 2.0 ** ((bins + 0.5) * OCCUPIED_BIN_EV)
    if lit.size < v.size:
        r, counts = np.r_[0.0, r], np.r_[v.size - lit.size, counts]
    return r, counts.astype(np.float64)


def _occupied(r: np.ndarray, held: np.ndarray, lo: float, hi: float) -> list[tuple[float, float]]:
    """The intervals (irradiance) of the bins centred at ``r`` (of :data:`OCCUPIED_BIN_EV`)
    that hold enough photosites (``held``), runs merged, within ``[lo, hi]``."""
    half = 2.0 ** (OCCUPIED_BIN_EV / 2)
    out = []
    for centre in r[held]:
        a, b = max(centre / half, lo), min(centre * half, hi)
        if out and out[-1][1] >= a * (1 - 1e-9):
            out[-1] = (out[-1][0], b)
        else:
            out.append((a, b))
    return out


def _noise_per_iso(profile_path: str | None, channels: list[str], measured) -> dict:
    """ISO -> per-channel noise: every ISO of the profile, else the merge's noise at the
    metering frames' ISO (key None)."""
    if profile_path:
        from hdrmerge_cli.io.profile import load_profile

        prof = load_profile(profile_path)
        isos = [iso for iso in map(iso_of_key, prof.get("noise") or {}) if iso is not None]
        if isos:
            return {iso: tuple(per_channel(noise_from_profile(prof, iso, profile_path), channels)) for iso in isos}
        log.info("%s: the profile has no noise parameters per ISO; using the noise measured on the metering frames",
                 profile_path)
    if not measured:
        raise HdrMergeError("no noise model: the metering frames' noise could not be measured; give a --profile "
                            "from calibrate-noise")
    return {None: tuple(per_channel(measured, channels))}


def meter(paths: list[str], opts: PlanOptions) -> Metering:
    """Merge the metering frames (``merge``'s defaults) and read the scene off the result."""
    from hdrmerge_cli.io.metadata import sample_pattern
    from hdrmerge_cli.pipeline.run import merge_bracket
    from hdrmerge_cli.pipeline.options import InputOptions, MergeOptions, OutputOptions

    if not paths:
        raise HdrMergeError("no metering frames (give one or more frames of the scene)")
    merged = merge_bracket(list(paths), MergeOptions(
        inputs=InputOptions(profile=opts.profile, crf=opts.crf, times=opts.times, times_file=opts.times_file),
        io=OutputOptions(noise_cache=opts.noise_cache)))
    first = merged.first
    names = list(first.channel_names)
    # each channel's 1.0 is its own full scale at h_ref: code values per second at the reference ISO
    y_full = tuple(float(v) for v in np.broadcast_to(first.white - first.black, (len(names),)))
    rec = merged.reconstruction
    cell = None if rec.result.ndim == 3 else sample_pattern(first)
    planes = [[(p * np.float32(y_full[c] / merged.h_ref), f) for p, f in chan]
              for c, chan in enumerate(channel_planes(rec.result, rec.flags, cell, len(names)))]
    scene = scene_range(planes, opts.lose_dark, opts.lose_bright, names)
    clipped = float(np.mean(rec.flags == FLAG_SATURATED))
    if clipped > 0:
        log.warning("%.3g %% of the photosites are clipped in every metering frame: the plan takes them at the "
                    "clipping level, a lower bound; add a shorter metering frame", 100 * clipped)
    noise = _noise_per_iso(opts.profile, names, merged.bracket.models.noise)
    return Metering(scene, names, first.iso, y_full, noise, [(f.exposure_time, f.iso) for f in merged.bracket.frames],
                    clipped, first.camera or "unknown camera", str(first.path))


def settings_for(metering: Metering, opts: PlanOptions) -> list[capture.Setting]:
    """The (time, ISO) settings a plan may use: ``--shutter-speeds`` (or the 1/3-stop
    series) at each ISO of ``--isos`` that the profile calibrates (or all of them)."""
    times = tuple(sorted(opts.shutter_speeds or capture.SHUTTER_THIRD_STOPS))
    noise_at = metering.noise
    if None in noise_at:  # measured on the metering frames: their ISO only
        iso = metering.reference_iso
        if opts.isos and (len(opts.isos) > 1 or iso is None or float(opts.isos[0]) != float(iso)):
            raise HdrMergeError(f"--isos: the noise is known only at the metering frames' ISO "
                                f"({iso:g}); give a --profile that calibrates the others" if iso else
                                "--isos: the metering frames state no ISO and the noise is known only for them; "
                                "give a --profile from calibrate-noise")
        reference = iso or 1.0
        noise_at = {reference: noise_at[None]}
    else:
        if metering.reference_iso is None:
            raise HdrMergeError(f"{metering.source}: states no ISO, so its irradiance cannot be related to the "
                                "profile's ISOs")
        lacking = sorted({iso for _, iso in metering.own if iso is not None and float(iso) not in noise_at})
        if lacking:
            raise HdrMergeError(f"{opts.profile}: calibrates no {iso_key(float(lacking[0]))}, the ISO of metering "
                                f"frames (it has {', '.join(iso_key(i) for i in sorted(noise_at))}); meter at one of "
                                "those, or run calibrate-noise there")
        if opts.isos:
            missing = [i for i in opts.isos if float(i) not in noise_at]
            if missing:
                raise HdrMergeError(f"--isos: the profile calibrates no {iso_key(float(missing[0]))} (it has "
                                    f"{', '.join(iso_key(i) for i in sorted(noise_at))}); run calibrate-noise there")
            noise_at = {float(i): noise_at[float(i)] for i in opts.isos}
        reference = metering.reference_iso
    return capture.make_settings(times, sorted(noise_at), noise_at, reference, metering.y_full)


def check_options(opts: PlanOptions) -> None:
    """What can be refused before the metering frames are read."""
    shortest = min(opts.shutter_speeds or capture.SHUTTER_THIRD_STOPS)
    if opts.time is not None and opts.time < shortest:
        raise HdrMergeError(f"--time {opts.time:g}: shorter than the shortest shutter time ({shortest:g} s)")


def solve(metering: Metering, opts: PlanOptions) -> dict:
    """The plan and its comparisons, as the JSON summary of ``plan``.  With ``--time``
    the conventional brackets of that time are found first: the plan's worst case is never
    below theirs (:func:`capture.best_plan`'s ``at_least_db``)."""
    settings = settings_for(metering, opts)
    metering = replace(metering, scene=measurable(metering.scene, settings, metering.channels))
    scene = metering.scene
    base = min(s.iso for s in settings)
    at = f"at ISO {base:g}" if metering.reference_iso else "at the metering frames' ISO"

    def conventional_of(budget):
        return {step: capture.best_conventional(settings, scene, step, opts.frames, budget) for step in (1, 2)}

    if opts.min_snr is not None:
        plan = capture.shortest_plan(settings, scene, opts.min_snr, opts.frames, opts.time, opts.search_time)
        if plan is None:
            budget = opts.time if opts.time is not None else opts.frames * max(s.time for s in settings)
            reach = capture.best_plan(settings, scene, budget, opts.frames, opts.search_time)
            within = f"in {opts.time:g} s" if opts.time is not None else "with the longest shutter time"
            raise HdrMergeError(f"--min-snr {opts.min_snr:g}: impossible; {opts.frames} frames {within} reach at most "
                                f"{reach.worst_snr_db:.1f} dB (allow more --frames or --time, or a lower --min-snr)")
        budget, floor = plan.total_time, float("-inf")
        conventional = conventional_of(budget)
    else:
        budget = opts.time
        conventional = conventional_of(budget)
        floor = max((p.worst_snr_db for p in conventional.values() if p is not None), default=float("-inf"))
        plan = capture.best_plan(settings, scene, budget, opts.frames, opts.search_time, at_least_db=floor)
    compare = {}
    if len({s.iso for s in settings}) > 1:
        fixed = (capture.shortest_plan([s for s in settings if s.iso == base], scene, opts.min_snr, opts.frames,
                                       opts.time, opts.search_time) if opts.min_snr is not None else
                 plan.lowest_iso or capture.best_plan([s for s in settings if s.iso == base], scene, budget,
                                                      opts.frames, opts.search_time, at_least_db=floor))
        compare[f"plan {at} only"] = fixed
    for step in (1, 2):
        compare[f"conventional {step}-EV bracket {at}"] = conventional[step]
        compare[f"conventional {step}-EV bracket {at}, same SNR"] = capture.best_conventional(
            settings, scene, step, 64, None, plan.worst_snr_db - 1e-9)
    return summary(metering, plan, compare, opts)


def measurable(scene: capture.SceneRange, settings: list, names: list[str]) -> capture.SceneRange:
    """``scene`` with each channel's brightest irradiance lowered to what the shortest,
    least amplified setting still measures (with a warning): no plan measures more."""
    top = [max(s.clipping_point(c) for s in settings) for c in range(scene.channels)]
    over = [c for c in range(scene.channels) if scene.hi[c] > top[c]]
    if not over:
        return scene
    c = over[0]
    log.warning("channel %s: the scene's brightest photosites clip even in the shortest frame allowed (%.2f EV "
                "over); the plan measures up to the brightest it can", names[c], np.log2(scene.hi[c] / top[c]))
    return replace(scene, hi=tuple(min(h, t) for h, t in zip(scene.hi, top)),
                   lo=tuple(min(lo, t) for lo, t in zip(scene.lo, top)))


def _frames_json(plan: capture.Plan, iso_known: bool = True) -> list[dict]:
    """The plan's frames, one entry per frame shot; ``iso`` None where the metering frames
    state none (the plan then keeps theirs)."""
    return [{"time": s.time, "iso": s.iso if iso_known else None} for s, n in plan.frames for _ in range(n)]


#: points per EV at which the SNR curves are evaluated (the table's bins take their minimum)
CURVE_POINTS_PER_EV = 24


def snr_curve(plan: capture.Plan, scene: capture.SceneRange, log2_r: np.ndarray) -> np.ndarray:
    """The plan's SNR (dB) at irradiances ``2 ** log2_r``, the lowest over the channels
    (each channel only at the irradiances its photosites hold, :meth:`SceneRange.intervals`;
    inf where none does, -inf where no frame measures it)."""
    r = 2.0 ** np.asarray(log2_r, dtype=np.float64)
    out = np.full(r.shape, np.inf)
    for c in range(scene.channels):
        inside = np.zeros(r.shape, bool)
        for a, b in scene.intervals(c):
            inside |= (r >= a) & (r <= b)
        out = np.where(inside, np.minimum(out, capture.snr_db(r, plan.frames, c)), out)
    return out


def snr_table(metering: Metering, plans: dict) -> list[dict]:
    """Rows of the SNR against irradiance: per 1-EV bin of the scene's range (log2 of the
    irradiance, code values per second at the reference ISO), the share of the scene's
    photosites in it and each plan's lowest SNR (dB) in the bin, over the channels."""
    scene = metering.scene
    edges = np.arange(np.floor(np.log2(min(scene.lo))), np.ceil(np.log2(max(scene.hi))) + TABLE_STEP_EV,
                      TABLE_STEP_EV)
    counts = np.zeros(len(edges) - 1)
    for c in range(scene.channels):
        r, w = scene.population(c, protected=True)
        counts += np.histogram(np.log2(r), edges, weights=w)[0]
    share = counts / max(counts.sum(), 1)
    fine = np.linspace(edges[0], edges[-1], int(round((edges[-1] - edges[0]) * CURVE_POINTS_PER_EV)) + 1)
    bins = np.clip(np.searchsorted(edges, fine, side="right") - 1, 0, len(counts) - 1)
    curves = {name: snr_curve(p, scene, fine) for name, p in plans.items() if p is not None}
    rows = []
    for k in range(len(counts)):
        row = {"log2_irradiance": float((edges[k] + edges[k + 1]) / 2), "share": float(share[k])}
        for name, curve in curves.items():
            v = curve[bins == k]
            row[name] = float(v.min()) if v.size and np.isfinite(v.min()) else None
        rows.append(row)
    return rows


def snr_curves(scene: capture.SceneRange, plans: dict) -> dict:
    """Each plan's :func:`snr_curve` on a grid of :data:`CURVE_POINTS_PER_EV` points per EV
    over the scene's range: ``{name: [log2 r, SNR dB or None]}``."""
    lo, hi = np.log2(min(scene.lo)), np.log2(max(scene.hi))
    x = np.linspace(lo, hi, max(2, int(round((hi - lo) * CURVE_POINTS_PER_EV)) + 1))
    return {name: [[float(a), float(b) if np.isfinite(b) else None] for a, b in zip(x, snr_curve(p, scene, x))]
            for name, p in plans.items() if p is not None}


def _finite(v: float) -> float | None:
    """``v``, or None where no frame measures some irradiance (JSON has no infinity)."""
    return float(v) if np.isfinite(v) else None


def _stats(p: capture.Plan) -> dict:
    """A plan's predicted statistics (dB; None where some irradiance goes unmeasured)."""
    return {"predicted_worst_snr_db": _finite(p.worst_snr_db), "predicted_mean_snr_db": _finite(p.mean_snr_db),
            "predicted_low_snr_db": _finite(p.low_snr_db)}


def summary(metering: Metering, plan: capture.Plan, compare: dict, opts: PlanOptions) -> dict:
    shown = {"plan": plan} | {k: v for k, v in compare.items() if "same SNR" not in k}
    known = metering.reference_iso is not None
    out = {
        "camera": metering.camera,
        "metering_frames": [{"time": t, "iso": i} for t, i in metering.own],
        "reference_iso": metering.reference_iso,
        "worst_case": {"definition": "the lowest SNR (dB, the squared irradiance over its variance after the "
                                     "merge) over the irradiances each channel's photosites hold, between its "
                                     "darkest lose_dark % and its brightest lose_bright % (1/12-EV bins with at "
                                     "least 0.1 % of them, and both ends)",
                       "mean": "the SNR of the mean squared error of log E over those photosites: -10 log10 of "
                               "the mean of 1 / SNR",
                       "low": f"the SNR that all but {capture.LOW_PERCENTILE:g} % of all the photosites reach",
                       "lose_dark": opts.lose_dark, "lose_bright": opts.lose_bright,
                       "margin_db": capture.MARGIN_DB,
                       "range": {c: [lo, hi] for c, lo, hi in zip(metering.channels, metering.scene.lo,
                                                                 metering.scene.hi)}},
        "frames": _frames_json(plan, known),
        "total_time": plan.total_time,
        **_stats(plan),
        "solver": {"optimal": plan.optimal, "gap_db": float(-10 * np.log10(max(1 - plan.gap, 1e-12)))},
        "compared": {name: None if p is None else {"frames": _frames_json(p, known), "total_time": p.total_time,
                                                   **_stats(p)}
                     for name, p in compare.items()},
        "snr_table": snr_table(metering, shown),
        "snr_curves": snr_curves(metering.scene, shown),
        "clipped_in_metering": metering.clipped,
    }
    return out


# ---------------------------------------------------------------- reports
def shutter_label(t: float) -> str:
    """A shutter time as cameras list it: ``1/250`` under 1 s where 1/t is within 2 % of
    a whole number (tenths such as ``0.3`` or ``0.5`` stay decimal), else ``0.4``,
    ``1.3``, ``30``."""
    n = round(1 / t)
    tenth = t >= 0.3 - 1e-9 and abs(t - round(t, 1)) < 1e-9
    if t < 1 and n >= 2 and abs(1 / t - n) <= 0.02 * n and not tenth:
        return f"1/{n}"
    return f"{t:.2g}" if t < 1 else f"{t:.4g}"


def _iso(v) -> str:
    return "-" if v is None else f"{v:g}"


def format_plan(s: dict) -> str:
    """The plan as text tables (stdout of ``plan``)."""
    wc = s["worst_case"]
    n = len(s["frames"])
    lines = [f"plan for {s['camera']}: {n} frame{'s' if n != 1 else ''}, {s['total_time']:.4g} s in all, "
             f"predicted worst-case SNR {_db(s['predicted_worst_snr_db'])}, mean {_db(s['predicted_mean_snr_db'])}",
             f"(worst case: the lowest SNR over the irradiances the scene holds, between its {wc['lose_dark']:g} % "
             f"darkest and {wc['lose_bright']:g} % brightest photosites; mean: of the squared error over them; "
             f"{capture.LOW_PERCENTILE:g} %: the SNR all but the lowest {capture.LOW_PERCENTILE:g} % of the "
             "photosites reach"
             + ("" if s["solver"]["optimal"] else f"; the search stopped within {s['solver']['gap_db']:.2f} dB of "
                                                    "the best plan") + ")",
             "", f"{'frame':>5}  {'time':>8}  {'ISO':>6}"]
    lines += [f"{k + 1:>5}  {shutter_label(f['time']):>8}  {_iso(f['iso']):>6}" for k, f in enumerate(s["frames"])]
    width = max(len(name) for name in ["plan", *s["compared"]])
    lines += ["", f"{'':<{width}} {'frames':>6} {'time':>9} {'worst case':>11} {'mean':>11} "
                  f"{f'{capture.LOW_PERCENTILE:g} %':>11}"]
    for name, p in {"plan": s, **s["compared"]}.items():
        if p is None:
            lines.append(f"{name:<{width}} {'none':>6}")
        else:
            lines.append(f"{name:<{width}} {len(p['frames']):>6} {p['total_time']:>8.4g}s "
                         + " ".join(f"{_db(p[k]):>11}" for k in ("predicted_worst_snr_db", "predicted_mean_snr_db",
                                                                  "predicted_low_snr_db")))
    cols = [k for k in s["snr_table"][0] if k not in ("log2_irradiance", "share")] if s["snr_table"] else []
    lines += ["", "SNR (dB, lowest channel) against irradiance (log2 of code values per second at ISO "
              f"{_iso(s['reference_iso'])}); share of the scene's photosites per 1-EV bin",
              f"{'log2 r':>7} {'share':>7} " + " ".join(f"{_short(c):>12}" for c in cols)]
    for row in s["snr_table"]:
        lines.append(f"{row['log2_irradiance']:>7.1f} {100 * row['share']:>6.2f}% "
                     + " ".join(f"{row[c]:>12.1f}" if row.get(c) is not None else f"{'-':>12}" for c in cols))
    return "\n".join(lines)


def _db(v: float | None) -> str:
    return "no measure" if v is None else f"{v:.1f} dB"


def _short(name: str) -> str:
    if name == "plan":
        return "plan"
    if name.startswith("plan at ISO"):
        return "ISO " + name.split()[3] + " only"
    if name.startswith("plan at"):
        return "ISO fixed"
    return name.split()[1] + " bracket"


def gphoto2_script(s: dict) -> str:
    """A POSIX shell script that shoots the plan with gphoto2 (tethered camera in manual
    exposure mode), one file per frame, ``plan_01.<suffix>`` ..."""
    lines = ["#!/bin/sh",
             f"# The bracket planned by hdrmerge-cli for {s['camera']}: {len(s['frames'])} frames, "
             f"{s['total_time']:.4g} s in all,",
             f"# predicted worst-case SNR {_db(s['predicted_worst_snr_db'])}.  Needs gphoto2 (Debian package gphoto2) "
             "and the camera",
             "# in manual exposure mode (M), RAW, the focus and aperture of the metering frames (all alike).  The values must",
             "# be in the camera's lists: gphoto2 --get-config shutterspeed; gphoto2 --get-config iso",
             "set -e"]
    for k, f in enumerate(s["frames"]):
        iso = "" if f["iso"] is None else f" --set-config-value iso={f['iso']:g}"
        lines.append(f"gphoto2{iso} --set-config-value shutterspeed={shutter_label(f['time'])} "
                     f"--capture-image-and-download --filename \"plan_{k + 1:02d}.%C\"")
    return "\n".join(lines) + "\n"


def plot_snr(s: dict):
    """The predicted SNR against irradiance of the plan and its comparisons, over the
    scene's histogram."""
    from hdrmerge_cli.io.plots import pyplot

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8, 4.5))
    rows = s["snr_table"]
    share = ax.twinx()
    share.bar([r["log2_irradiance"] for r in rows], [100 * r["share"] for r in rows], width=0.9, color="0.88", zorder=0)
    share.set_ylabel("photosites (%)")
    ax.set_zorder(share.get_zorder() + 1)
    ax.patch.set_visible(False)
    for name, curve in s["snr_curves"].items():
        ax.plot([a for a, _ in curve], [np.nan if b is None else b for _, b in curve], label=name,
                lw=2 if name == "plan" else 1)
    if s["predicted_worst_snr_db"] is not None:
        ax.axhline(s["predicted_worst_snr_db"], color="k", ls=":", lw=1, label="plan's worst case")
    ax.set_xlabel(f"log2 irradiance (code values per second at ISO {_iso(s['reference_iso'])})")
    ax.set_ylabel("predicted SNR (dB)")
    ax.set_title(f"{s['camera']}: {len(s['frames'])} frames, {s['total_time']:.3g} s")
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    return fig


def write_outputs(summary: dict | None, plot: Path | None, script: Path | None, overwrite: bool,
                  check_only: bool = False) -> None:
    """``--plot`` and ``--gphoto2``: checked before any work (``check_only``), then written
    together (neither is left without the other)."""
    from hdrmerge_cli.io.atomic import check_writable, write_text, write_together
    from hdrmerge_cli.io.plots import check_figure_path, figure_writer

    if check_only:
        if plot:
            check_figure_path(plot, overwrite)
        if script:
            check_writable(script, overwrite)
        return
    def shell_script(tmp: str) -> None:
        write_text(tmp, gphoto2_script(summary))
        Path(tmp).chmod(0o755)

    write_together(([(script, shell_script)] if script else [])
                   + ([(plot, figure_writer(plot_snr(summary), plot))] if plot else []), overwrite)


# ---------------------------------------------------------------- a bracket's own SNR (info --snr)
def bracket_snr(paths: list[str], opts: PlanOptions) -> dict:
    """A bracket's predicted worst-case SNR (its frames as shot, merged; None where its
    frames leave some irradiance of the scene unmeasured, e.g. its brightest photosites
    clipped) and what the best plan of the same total time reaches with
    ``max(opts.frames, frames in the bracket)`` frames."""
    metering = meter(paths, opts)
    settings = settings_for(metering, opts)
    by_iso = {s.iso: s for s in settings}
    measured = None in metering.noise
    isos = {iso for _, iso in metering.own}
    if measured and len(isos) > 1:
        raise HdrMergeError(f"{metering.source}: the frames differ in ISO; their SNR needs the noise at each ISO "
                            "(give a --profile from calibrate-noise)")
    own = []
    for t, iso in metering.own:
        s = by_iso[min(by_iso)] if measured else by_iso.get(iso)
        if s is None:
            raise HdrMergeError(f"{metering.source}: no noise for a frame of ISO {_iso(iso)} in the profile; the "
                                "bracket's SNR needs every frame's ISO")
        own.append((replace(s, time=float(t)), 1))
    scene = measurable(metering.scene, settings, metering.channels)
    shot = capture.evaluate(own, scene)
    best = capture.best_plan(settings, scene, shot.total_time, max(opts.frames, len(own)), opts.search_time,
                             at_least_db=shot.worst_snr_db)
    return {**_stats(shot), "total_time": shot.total_time, "lose_dark": opts.lose_dark,
            "lose_bright": opts.lose_bright,
            "plan_of_the_same_time": {"frames": _frames_json(best, metering.reference_iso is not None), **_stats(best)}}
