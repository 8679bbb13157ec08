"""calibrate-noise: fit the noise model (17) per ISO and channel into a profile."""
from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from hdrmerge_cli.core.calibrate import binned_variance, fit_noise_model, window_statistics, WindowStats
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.io.atomic import check_writable
from hdrmerge_cli.io.frames import load_codes, raw_channel_map, read_frame
from hdrmerge_cli.io.profile import new_profile, save_profile
from hdrmerge_cli.pipeline.merge import choose_crf

log = logging.getLogger("hdrmerge_cli")


def _planes(frame, codes, crf):
    """(name, plane in code values above black, lo, hi) per channel."""
    if frame.kind == "raw":
        names = frame.channel_names
        cmap = raw_channel_map(frame.path)
        for k in range(4):
            ys, xs = np.nonzero(cmap[:2, :2] == k)
            if ys.size == 0:
                continue
            plane = codes[ys[0]::2, xs[0]::2].astype(np.float64) - frame.black[k]
            yield names[k], plane, -frame.black[k], frame.white[k] - frame.black[k]
        return
    full = frame.n_codes - 1.0
    for c in range(frame.channels):
        lin = crf.inverse(codes[..., c] / full, c) * full
        yield frame.channel_colors[c], lin, crf.inverse(np.array([0.5 / full]), c)[0] * full, crf.inverse(
            np.array([(full - 0.5) / full]), c)[0] * full


def calibrate_noise(paths, output: Path, crf_spec=None, window: int = 7, bins: int = 64,
                    overwrite: bool = False) -> dict:
    t0 = time.perf_counter()
    check_writable(output, overwrite)
    frames = [read_frame(p) for p in paths]
    first = frames[0]
    for f in frames[1:]:
        if f.kind != first.kind or f.camera != first.camera:
            raise HdrMergeError(f"{f.path}: a different camera or file type than {first.path}")
    crf = choose_crf(frames, crf_spec)
    pooled: dict[str, dict[str, list[WindowStats]]] = {}
    for f in frames:
        codes = load_codes(f)
        iso = f"ISO{f.iso:g}" if f.iso else "ISO_unknown"
        for name, plane, lo, hi in _planes(f, codes, crf):
            pooled.setdefault(iso, {}).setdefault(name, []).append(window_statistics(plane, lo, hi, window))
    noise = {}
    for iso, chans in pooled.items():
        noise[iso] = {}
        for name, parts in chans.items():
            ws = WindowStats(*(np.concatenate([getattr(p, k) for p in parts]) for k in ("mean", "var", "texture")))
            try:
                fit = fit_noise_model(*binned_variance(ws, bins=bins))
            except HdrMergeError as exc:
                raise HdrMergeError(f"{first.path} ({iso}, channel {name}): {exc}") from None
            noise[iso][name] = fit.as_dict() | {"method": "local-statistics", "window": window}
            log.info("%s %s: sigma_o2=%.4g alpha=%.4g beta=%.3g (%s, %d levels)", iso, name, fit.sigma_o2,
                     fit.alpha, fit.beta, fit.model, fit.points)
    profile = new_profile({"make": first.make, "model": first.model}, first.bits, crf, [f.path for f in frames],
                          "calibrate-noise")
    profile["noise"] = noise
    profile["noise_units"] = ("code values above black (RAW) or linearised code values at the image's bit depth; "
                              "x in photo-electrons, Var[y] = sigma_o2 + alpha x + beta x^2")
    save_profile(output, profile, overwrite)
    return {"output": str(output), "noise": noise, "seconds": round(time.perf_counter() - t0, 4)}
