"""calibrate-noise: fit the noise model (17) per ISO and channel into a profile, from
ordinary photographs (local statistics and exposure pairs) and/or from dark and flat
frames (photon transfer, the reference when available)."""
from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hdrmerge_cli.core.calibrate import ChannelFit, fit_channel, read_noise_split, rounded, unusable_reason
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.photon_transfer import PTCResult, photon_transfer
from hdrmerge_cli.io.atomic import check_writable, write_together
from hdrmerge_cli.io.frames import Frame, cfa_corner, list_frames, load_codes, read_frame
from hdrmerge_cli.io.noisespec import iso_key, iso_of_key
from hdrmerge_cli.io.plots import check_figure_path, figure_writer, pyplot
from hdrmerge_cli.io.profile import crf_from_json, load_profile, new_profile, profile_writer
from hdrmerge_cli.pipeline.bracket import choose_crf
from hdrmerge_cli.pipeline.noise import channel_planes

log = logging.getLogger("hdrmerge_cli")

NOISE_UNITS = ("code values above black (RAW) or linearised code values at the image's bit depth; "
               "x in photo-electrons, Var[y] = sigma_o2 + alpha x + beta x^2")


@dataclass
class CalibrateOptions:
    output: Path | None = None
    darks: str | None = None
    flats: str | None = None
    crf: str | None = None
    profile: str | None = None
    plot: Path | None = None
    window: int = 7
    bins: int = 64
    overwrite: bool = False


def _read_group(frames: list[Frame], crf, what: str, load=load_codes) -> list[tuple[Frame, list]]:
    """[(frame, its :func:`channel_planes`)] of the usable frames, in the order of
    ``frames``; photographs that are all clipped or black are skipped with a warning.
    Frames are decoded two at a time (both cores)."""
    # one camera (checked): the CFA layout is read once, not by a second decode per frame
    corner = cfa_corner(frames[0]) if frames and frames[0].kind == "raw" else None

    def read(f):
        planes = list(channel_planes(f, load(f), crf, corner))
        if what != "images":
            return None, planes
        return unusable_reason([p[1:] for p in planes], f.width * f.height), planes

    with ThreadPoolExecutor(2) as pool:
        results = list(pool.map(read, frames))
    for f, (reason, _) in zip(frames, results):
        if reason:
            log.warning("%s: skipped, %s", f.path, reason)
    return [(f, planes) for f, (reason, planes) in zip(frames, results) if not reason]


def _by_channel(read: list[tuple[Frame, list]]) -> dict[str, list]:
    """{channel: [(plane, lo, hi, frame) per frame]} from :func:`_read_group`'s list."""
    out: dict[str, list] = {}
    for f, planes in read:
        for name, plane, lo, hi in planes:
            out.setdefault(name, []).append((plane, lo, hi, f))
    return out


def _fit_channels(read: list[tuple[Frame, list]], iso: str, window: int = 7,
                  bins: int = 64) -> dict[str, ChannelFit]:
    """:func:`~hdrmerge_cli.core.calibrate.fit_channel` per channel of the frames (sorted by exposure).  Errors name
    the first frame, the ISO and the channel."""
    def fit(name, items):
        try:
            return name, fit_channel([p for p, *_ in items], items[0][1], items[0][2],
                                     [f.exposure_time for *_, f in items], window, bins)
        except HdrMergeError as exc:
            raise HdrMergeError(f"{items[0][3].path} ({iso}, channel {name}): {exc}") from None

    with ThreadPoolExecutor(2) as pool:  # SciPy's filters and NumPy's sorts release the GIL: both cores
        return dict(pool.map(fit, *zip(*_by_channel(read).items())))


def frame_report(frame: Frame, planes, params: dict[str, dict]) -> dict:
    """Whether a frame is photon- or offset-noise limited: the SNR breaking point is where
    the photon noise alpha x equals the read noise sigma_o^2, x* = sigma_o^2 / alpha
    electrons, i.e. E* = sigma_o^2 / (alpha t) electrons per second and
    y* = sigma_o^2 / sqrt(alpha) code values; pixels above it are photon-noise limited."""
    above, total, breaks = 0, 0, {}
    for name, plane, lo, hi in planes:
        p = params.get(name)
        if not p:
            continue
        y_star = p["sigma_o2"] / np.sqrt(p["alpha"])
        ok = (plane > lo) & (plane < hi)
        above += int(np.count_nonzero(plane[ok] > y_star))
        total += int(np.count_nonzero(ok))
        breaks[name] = {"code_value": round(float(y_star), 4),
                        "electrons_per_second": (float(p["sigma_o2"] / (p["alpha"] * frame.exposure_time))
                                                 if frame.exposure_time else None)}
    frac = above / max(total, 1)
    return {"path": frame.path, "exposure_time": frame.exposure_time, "iso": frame.iso,
            "limited": "photon" if frac >= 0.5 else "offset", "photon_limited_fraction": round(frac, 4),
            "break_point": breaks}


#: local statistics measure a parameter when it is at least this many of its standard
#: errors (a relative error of at most 25 %); a gain below that is scene texture read as noise
PINNED_STDERRS = 4.0


def _check_pinned(fits: dict[str, dict], frames: list[Frame]) -> None:
    """Noise from local statistics alone (no exposure pair to check them against): refuse
    a gain (alpha) within :data:`PINNED_STDERRS` standard errors of 0 on some channel
    (scene texture read as noise), and name a read noise that is not pinned."""
    if any(e["method"]["alpha"] != "local statistics" for e in fits.values()):
        return

    def weak(p):
        return [f"{c}: {p} {e[p]:.3g} +/- {e['stderr'][p]:.2g}" for c, e in fits.items()
                if not e[p] >= PINNED_STDERRS * e["stderr"][p]]

    if weak("alpha"):
        raise HdrMergeError(f"{frames[0].path}: its local statistics do not pin the noise ({'; '.join(weak('alpha')[:3])}"
                            "): scene texture is read as noise; give two or more exposures of a still scene, or "
                            "--flats and --darks")
    if weak("sigma_o2"):
        log.warning("%s: its local statistics do not pin the read noise (%s); --darks measure it", frames[0].path,
                    "; ".join(weak("sigma_o2")))


def _ptc_entry(r: PTCResult) -> dict:
    return {
        "sigma_o2": r.sigma_o2, "alpha": r.alpha, "beta": r.beta, "model": r.model,
        "points": int(np.count_nonzero(r.used)), "residual_rms": r.residual_rms,
        "z_statistic": r.z_statistic, "p_value": r.p_value, "stderr": {"sigma_o2": round(r.sigma_o2_stderr, 4)},
        "dark_offset": r.dark_offset, "dsnu2": r.dsnu2,
        "method": {"sigma_o2": "photon transfer: darks" if r.dark_offset is not None
                   else "photon transfer: intercept of the flats",
                   "alpha": "photon transfer: flats", "beta": "photon transfer: averaged flats"},
        "levels": {"mean": r.mean.tolist(), "temporal_variance": r.temporal.tolist(),
                   "spatial_variance": r.spatial.tolist(), "in_linear_range": r.used.tolist()},
    }


def _combine(image: dict | None, ptc: dict | None) -> dict:
    """Each parameter from its best source: sigma_o^2 from darks, else the photographs,
    else the flats' intercept; alpha and beta from the flats, else the photographs."""
    if ptc is None:
        return image
    if image is None:
        return ptc
    out = ptc | {"from_photographs": {k: image[k] for k in ("sigma_o2", "alpha", "beta", "model", "stderr",
                                                            "achievable_stderr") if k in image}}
    if ptc["dark_offset"] is None:
        out["sigma_o2"] = image["sigma_o2"]
        out["method"] = ptc["method"] | {"sigma_o2": image["method"]["sigma_o2"]}
    return out


def _check_sizes(frames: list[Frame], what: str) -> None:
    """One size for frames compared pixel by pixel (a bracket's exposure pairs; darks and
    flats), refused before they are compared."""
    for f in frames[1:]:
        if (f.width, f.height) != (frames[0].width, frames[0].height):
            raise HdrMergeError(f"{f.path}: size {f.width}x{f.height} differs from {frames[0].width}x"
                                f"{frames[0].height} of {frames[0].path}; the {what} are compared pixel by pixel")


def _check_group(frames: list[Frame], what: str) -> None:
    """One camera and file type; ISO known for all frames or for none."""
    ref = frames[0]
    for f in frames:
        if f.kind != ref.kind or f.camera != ref.camera:
            raise HdrMergeError(f"{f.path}: a different camera or file type than {ref.path}")
    isos = {f.iso is None for f in frames}
    if len(isos) > 1:
        missing = next(f for f in frames if f.iso is None)
        raise HdrMergeError(f"{missing.path}: no ISO in the metadata while other {what} have one; "
                            "calibrate frames of unknown ISO separately")


def _calibration_frames(folder: str | None, what: str) -> list[Frame]:
    if folder is None:
        return []
    frames = [read_frame(p) for p in list_frames(folder)]
    if not frames:
        raise HdrMergeError(f"{folder}: no image or RAW files among the {what}")
    return frames


def _check_request(paths, opts: CalibrateOptions) -> tuple[Path, bool]:
    """The profile path to write and whether it updates --profile in place; a request that cannot run is refused."""
    output = opts.output or (Path(opts.profile) if opts.profile else None)
    if output is None:
        raise HdrMergeError("give -o/--output (or --profile to update a profile in place)")
    updating = opts.profile is not None and Path(opts.profile).resolve() == Path(output).resolve()
    check_writable(output, opts.overwrite or updating)
    if opts.plot:
        check_figure_path(opts.plot, opts.overwrite)
    if not paths and not opts.flats and not opts.darks:
        raise HdrMergeError("give photographs (IMAGES), or calibration frames with --flats (and --darks)")
    if opts.darks and not opts.flats and not paths:
        raise HdrMergeError("--darks measure the read noise only: add --flats or photographs for the gain")
    return output, updating


def _read_inputs(paths, opts: CalibrateOptions, base: dict | None) -> tuple[list[Frame], list[Frame], list[Frame]]:
    """The photographs, darks and flats, checked to be of one camera (and of the profile's, if any)."""
    images = [read_frame(p) for p in paths]
    darks = _calibration_frames(opts.darks, "darks")
    flats = _calibration_frames(opts.flats, "flats")
    everything = images + darks + flats
    first = everything[0]
    _check_group(everything, "frames")
    if base and base.get("camera") and base["camera"].get("model") and \
            (base["camera"].get("make"), base["camera"].get("model")) != (first.make, first.model):
        raise HdrMergeError(f"{opts.profile}: a profile of {base['camera'].get('make')} {base['camera'].get('model')}, "
                            f"not of {first.camera} ({first.path})")
    return images, darks, flats


def _photograph_fits(read: list[tuple[Frame, list]], iso: str, opts: CalibrateOptions,
                     plot_data: dict[str, dict]) -> dict[str, dict]:
    """{channel: profile entry} fitted from the photographs at one ISO (each fit also noted in ``plot_data``)."""
    fits: dict[str, dict] = {}
    for name, fit in _fit_channels(read, iso, opts.window, opts.bins).items():
        fits[name] = fit.entry(opts.window)
        plot_data.setdefault(iso, {})[name] = {"fit": fit.fit}
    return fits


def _calibrate_iso(iso: str, images: list[Frame], darks: list[Frame], flats: list[Frame], crf,
                   opts: CalibrateOptions, plot_data: dict[str, dict]) -> tuple[dict | None, list[dict]]:
    """{channel: noise entry} at one ISO (None when nothing there is usable) and its photographs' reports."""
    group = sorted((f for f in images if iso_key(f.iso) == iso), key=lambda f: f.exposure_time or 0.0)
    _check_sizes([f for f in darks + flats if iso_key(f.iso) == iso], "darks and flats")
    read = _read_group(group, crf, "images")
    _check_sizes([f for f, _ in read], "photographs")  # those kept: a black frame is skipped as such
    if group and not read:
        raise HdrMergeError(f"{group[0].path}: no usable frame at {iso} (the warnings above say why)")
    fits = _photograph_fits(read, iso, opts, plot_data)
    ptcs = _photon_transfer(iso, [f for f in darks if iso_key(f.iso) == iso],
                            [f for f in flats if iso_key(f.iso) == iso], crf)
    if not fits and not ptcs:
        return None, []
    if not ptcs:
        _check_pinned(fits, group)
    if ptcs and not fits and all(e["dark_offset"] is None for e in ptcs.values()):
        log.warning("%s: without --darks the read noise is the intercept of the photon-transfer line (%s: %s); "
                    "darks measure it directly", opts.flats, iso, ", ".join(
                        f"{c} {e['sigma_o2']:.3g} +/- {e['stderr']['sigma_o2']:.2g}" for c, e in ptcs.items()))
    entries = {name: _combine(fits.get(name), ptcs.get(name)) for name in sorted(set(fits) | set(ptcs))}
    for name, e in entries.items():
        plot_data.setdefault(iso, {}).setdefault(name, {})["levels"] = e.get("levels")
        log.info("%s %s: sigma_o2=%.4g alpha=%.4g beta=%.3g (%s; %s)", iso, name, e["sigma_o2"], e["alpha"],
                 e["beta"], e["model"], ", ".join(f"{k} from {v}" for k, v in e["method"].items()))
    reports = []
    for f, planes in read:
        rep = frame_report(f, planes, entries)
        reports.append(rep)
        log.info("%s: %s-noise limited (%.0f %% of pixels above the SNR breaking point)", f.name, rep["limited"],
                 100 * rep["photon_limited_fraction"])
    return entries, reports


def _updated_profile(base: dict | None, noise: dict[str, dict], frames: list[Frame], crf) -> tuple[dict, dict]:
    """The profile to write (``base`` with ``noise`` merged in, or a new one) and its read-noise split ({} if none)."""
    if base is not None:
        profile = base
        for iso, entries in noise.items():
            profile.setdefault("noise", {}).setdefault(iso, {}).update(entries)
        profile.setdefault("provenance", {})["noise_command"] = "calibrate-noise"
    else:
        first = frames[0]
        profile = new_profile({"make": first.make, "model": first.model}, first.bits, crf,
                              [f.path for f in frames], "calibrate-noise")
        profile["noise"] = noise
    profile["noise_units"] = NOISE_UNITS
    split = read_noise_split_entry(profile["noise"])
    if split:
        profile["read_noise_split"] = split
    else:
        profile.pop("read_noise_split", None)
    return profile, split


def calibrate_noise(paths, opts: CalibrateOptions) -> dict:
    t0 = time.perf_counter()
    output, updating = _check_request(paths, opts)
    base = load_profile(opts.profile) if opts.profile else None
    images, darks, flats = _read_inputs(paths, opts, base)
    everything = images + darks + flats
    crf = _choose_crf(everything[0], opts, base)

    noise: dict[str, dict] = {}
    reports: list[dict] = []
    plot_data: dict[str, dict] = {}
    for iso in sorted({iso_key(f.iso) for f in everything}):
        entries, iso_reports = _calibrate_iso(iso, images, darks, flats, crf, opts, plot_data)
        if entries is not None:
            noise[iso] = entries
            reports += iso_reports
    if not noise:
        raise HdrMergeError("no usable frames to calibrate")

    profile, split = _updated_profile(base, noise, everything, crf)
    writers = [(output, profile_writer(profile, output))]
    if opts.plot:
        writers.append((opts.plot, figure_writer(noise_figure(noise, plot_data), opts.plot)))
    write_together(writers, opts.overwrite or updating)
    return {"output": str(output), "noise": noise, "read_noise_split": split or None, "frames": reports,
            "plot": str(opts.plot) if opts.plot else None, "seconds": round(time.perf_counter() - t0, 4)}


def read_noise_split_entry(noise: dict) -> dict:
    """Per channel calibrated at two or more ISOs (of different gains), the read noise
    split into its parts before and after the ISO amplifier
    (:func:`~hdrmerge_cli.core.calibrate.read_noise_split`: ``sigma_o2 = pre alpha + post``
    across ISOs): ``{channel: {"pre_amp_electrons2", "post_amp_codes2", "stderr",
    "weighted", "isos"}}``, weighted by the entries' ``stderr`` when every entry states
    them; empty when no channel has two ISOs."""
    points: dict[str, list] = {}
    for key, entries in noise.items():
        iso = iso_of_key(key)
        if iso is None or not isinstance(entries, dict):
            continue
        for name, e in entries.items():
            if isinstance(e, dict) and all(isinstance(e.get(k), (int, float)) for k in ("alpha", "sigma_o2")):
                points.setdefault(name, []).append((iso, e))
    out = {}
    for name, items in sorted(points.items()):
        items.sort(key=lambda item: item[0])
        alpha = [e["alpha"] for _, e in items]
        if len(items) < 2 or max(alpha) <= min(alpha) * (1 + 1e-9):
            continue
        se = [e.get("stderr") or {} for _, e in items]
        weighted = all(isinstance(s.get(k), (int, float)) and s[k] > 0 for s in se for k in ("alpha", "sigma_o2"))
        try:
            fit = read_noise_split(alpha, [e["sigma_o2"] for _, e in items],
                                   [s["alpha"] for s in se] if weighted else None,
                                   [s["sigma_o2"] for s in se] if weighted else None)
        except HdrMergeError as exc:
            log.warning("channel %s: no read-noise split (%s)", name, exc)
            continue
        out[name] = {"pre_amp_electrons2": rounded(fit.pre), "post_amp_codes2": rounded(fit.post),
                     "stderr": {"pre_amp_electrons2": rounded(fit.pre_stderr),
                                "post_amp_codes2": rounded(fit.post_stderr)},
                     "weighted": fit.weighted, "isos": [int(iso) if iso.is_integer() else iso for iso, _ in items]}
        log.info("channel %s: read noise %.4g electrons^2 before the ISO amplifier, %.4g code values^2 after it "
                 "(ISO %s)", name, fit.pre, fit.post, ", ".join(f"{iso:g}" for iso, _ in items))
    return out


def _choose_crf(first: Frame, opts: CalibrateOptions, base: dict | None):
    """RAW is linear; JPEG/TIFF/PNG need their response: --crf (as merge reads it), else
    the profile's; no sRGB guess, since the noise would be measured on a wrong scale."""
    if first.kind in ("raw", "linear") or opts.crf:
        return choose_crf([first], opts.crf)
    if base is not None:
        return crf_from_json(base["crf"])
    raise HdrMergeError(f"{first.path}: the noise of JPEG/TIFF/PNG frames is measured on linear values; give their "
                        "camera response with --crf (linear for linear TIFFs, or a profile from estimate-crf)")


#: a dark frame's mean lies within this many of its own noise sigmas of black (or within
#: DARK_FRACTION of full scale), and below half the mean of the dimmest flats
DARK_SIGMAS, DARK_FRACTION = 5.0, 0.01


def _check_flats(levels: list[dict[str, list]]) -> None:
    """Refuse --flats that read no light (dark frames given as flats): a flat's mean must
    lie above black by more than a dark frame's may (:data:`DARK_SIGMAS`, :data:`DARK_FRACTION`)."""
    for level in levels:
        for name, items in level.items():
            for plane, _, hi, f in items:
                mean, sigma = float(np.mean(plane)), float(np.std(plane))
                if mean <= max(DARK_SIGMAS * sigma, DARK_FRACTION * hi):
                    raise HdrMergeError(f"{f.path}: not a flat field: its mean lies {mean:.4g} above the black level "
                                        f"(channel {name}), within {DARK_SIGMAS:g} times its noise, as a dark frame's; "
                                        "give frames of a uniformly lit field as --flats")


def _check_darks(dark_planes: dict[str, list], levels: list[dict[str, list]]) -> None:
    """Refuse --darks that are not dark (flat fields or photographs given as darks would
    make their photon noise the read noise): per channel, a dark frame's mean must lie
    near the black level and well below the dimmest flats."""
    for name, items in dark_planes.items():
        flat_means = [np.mean([np.mean(p) for p, *_ in level[name]]) for level in levels if name in level]
        dimmest = min(flat_means, default=np.inf)
        for plane, _, hi, f in items:
            mean, sigma = float(np.mean(plane)), float(np.std(plane))
            if mean > max(DARK_SIGMAS * sigma, DARK_FRACTION * hi):
                raise HdrMergeError(f"{f.path}: not a dark frame: its mean lies {mean:.4g} above the black level "
                                    f"(channel {name}), {mean / max(sigma, 1e-12):.3g} times its noise (a dark "
                                    f"frame's lies within {DARK_SIGMAS:g}); give frames taken without light as --darks")
            if mean >= 0.5 * dimmest:
                raise HdrMergeError(f"{f.path}: not a dark frame: its mean ({mean:.4g} above black, channel {name}) "
                                    f"is not well below the dimmest flats' ({dimmest:.4g}); give frames taken "
                                    "without light as --darks")


def _photon_transfer(iso: str, darks: list[Frame], flats: list[Frame], crf) -> dict[str, dict]:
    if not flats:
        if darks:
            log.warning("%s: darks without flats are ignored for %s (the gain needs flats)", darks[0].path, iso)
        return {}
    dark_planes = _by_channel(_read_group(darks, crf, "darks"))
    by_time: dict[float, list[Frame]] = {}
    for f in flats:
        if not f.exposure_time:
            raise HdrMergeError(f"{f.path}: no exposure time in the metadata (flats are grouped by exposure time)")
        by_time.setdefault(f.exposure_time, []).append(f)
    for t, fs in by_time.items():
        if len(fs) < 2:
            log.warning("%s: the only flat at %g s; photon transfer needs pairs, skipped", fs[0].path, t)
    levels = [_by_channel(_read_group(fs, crf, "flats")) for _, fs in sorted(by_time.items()) if len(fs) >= 2]
    _check_flats(levels)
    _check_darks(dark_planes, levels)
    out = {}
    for name in (levels[0] if levels else {}):
        lv = [[p for p, *_ in level[name]] for level in levels]
        full = levels[0][name][0][2]
        try:
            r = photon_transfer([p for p, *_ in dark_planes[name]] if name in dark_planes else None, lv, full)
        except HdrMergeError as exc:
            raise HdrMergeError(f"{flats[0].path} ({iso}, channel {name}): {exc}") from None
        out[name] = _ptc_entry(r)
    if not out:
        raise HdrMergeError(f"{flats[0].path}: photon transfer needs at least two flats per exposure time")

    return out


def noise_figure(noise: dict, plot_data: dict):
    """Like the paper's Fig. 22: per ISO and channel, the measured noise variance against
    the mean (log-log) with the fitted curve (17); exposure-pair points are scaled to one
    frame by the model ratio, photon-transfer levels are drawn as measured."""
    rows = [(iso, name) for iso in noise for name in noise[iso]]
    cols = min(4, len(rows))
    nrows = -(-len(rows) // cols)
    fig, axes = pyplot().subplots(nrows, cols, figsize=(3.8 * cols, 3.4 * nrows), dpi=110, squeeze=False)
    for ax, (iso, name) in zip(axes.ravel(), rows):
        e = noise[iso][name]
        coef = np.array([e["sigma_o2"], np.sqrt(e["alpha"]), e["beta"] / e["alpha"]])
        data = plot_data.get(iso, {}).get(name, {})
        fit, levels = data.get("fit"), data.get("levels")
        xs = []
        if fit is not None and fit.data is not None and fit.data.mean.size:
            d = fit.data
            single = coef[0] + coef[1] * d.mean + coef[2] * d.mean**2
            scaled = d.var * single / np.maximum(d.design @ coef, 1e-12)
            for kind, marker, label in (("local", "o", "local statistics"), ("pair", "^", "exposure pairs")):
                k = (d.kind == kind) & (d.mean > 0)
                if np.any(k):
                    ax.plot(d.mean[k], scaled[k], marker, ms=3, alpha=0.6, label=label)
                    xs.append(d.mean[k])
        if levels is not None:
            m = np.asarray(levels["mean"])
            ax.plot(m[m > 0], np.asarray(levels["temporal_variance"])[m > 0], "s", ms=4, label="flats (temporal)")
            xs.append(m[m > 0])
        x = np.concatenate(xs) if xs else np.array([1.0, 1e4])
        grid = np.geomspace(max(x.min(), 1e-3), x.max(), 200)
        ax.plot(grid, coef[0] + coef[1] * grid + coef[2] * grid**2, "k-", lw=1.2,
                label=f"fit ({e['model']})")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("local mean (code values above black)")
        ax.set_ylabel("noise variance")
        ax.set_title(f"{iso} {name}: sigma_o2={e['sigma_o2']:.3g}, alpha={e['alpha']:.3g}, beta={e['beta']:.2g}",
                     fontsize=8)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    for ax in axes.ravel()[len(rows):]:
        ax.set_visible(False)
    fig.tight_layout()
    return fig


