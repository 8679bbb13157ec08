"""estimate-crf: recover the inverse camera response of a bracket into a profile."""
from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from hdrmerge_cli.core.crf import CRF, table_crf
from hdrmerge_cli.core.crf_estimate import CRF_ESTIMATORS, inverse_from_log, sample_pixels
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.io.frames import load_codes
from hdrmerge_cli.io.profile import new_profile, save_profile
from hdrmerge_cli.io.atomic import check_writable
from hdrmerge_cli.pipeline.merge import exposure_values, read_bracket

log = logging.getLogger("hdrmerge_cli")


def check_brightness_order(frames, codes) -> None:
    """Frames must get brighter with exposure: name the first pair that does not."""
    means = [float(np.mean(c)) for c in codes]
    for k in range(1, len(frames)):
        if means[k] + 0.5 < means[k - 1]:
            raise HdrMergeError(
                f"{frames[k].path}: darker (mean code {means[k]:.1f}) than the shorter exposure "
                f"{frames[k - 1].path} ({means[k - 1]:.1f}); check the exposure times"
            )


def estimate_crf(paths, output: Path, method: str = "debevec", smoothing: float = 30.0, samples: int = 1000,
                 times=None, times_file=None, seed: int = 0, force: bool = False, overwrite: bool = False) -> dict:
    t0 = time.perf_counter()
    check_writable(output, overwrite)
    frames = read_bracket(list(paths), times, times_file)
    first = frames[0]
    if first.kind == "raw" and not force:
        log.info("RAW data is linear: no CRF to estimate; writing an identity (linear) CRF (use --force to fit one)")
        crf, changed = CRF("linear"), False
    else:
        if len(frames) < 2:
            raise HdrMergeError(f"{first.path}: estimating a CRF needs at least two exposures")
        codes = [load_codes(f) for f in frames]
        if first.kind == "raw":
            codes = [c[..., None] for c in codes]
        check_brightness_order(frames, codes)
        log_h = np.log(exposure_values(frames))
        rng = np.random.default_rng(seed)
        mid = len(frames) // 2
        tables, changed = [], False
        for c in range(codes[0].shape[-1]):
            idx = sample_pixels(codes[mid][..., c], samples, rng)
            z = np.stack([fr[..., c].ravel()[idx] for fr in codes], axis=1)
            usable = np.count_nonzero(np.all((z > 0) & (z < first.n_codes - 1), axis=1))
            if usable < 10:
                raise HdrMergeError(f"{first.path}: too few pixels unclipped in every frame ({usable}) to fit a CRF")
            g = CRF_ESTIMATORS[method](z, log_h, first.n_codes, smoothing)
            inv, fixed = inverse_from_log(g)
            changed |= fixed
            tables.append(inv)
        if changed:
            log.warning("the %s fit was not monotone; it was made non-decreasing", method)
        crf = table_crf(np.stack(tables), f"estimate-crf:{method}")
    profile = new_profile({"make": first.make, "model": first.model}, first.bits, crf,
                          [f.path for f in frames], f"estimate-crf --method {method}")
    profile["crf"].update({"method": method, "lambda": smoothing, "samples": samples,
                           "channels": first.channel_colors if first.kind != "raw" else "linear"})
    save_profile(output, profile, overwrite)
    return {
        "output": str(output), "method": method, "frames": [f.summary() for f in frames],
        "crf": crf.describe(), "made_monotone": changed, "seconds": round(time.perf_counter() - t0, 4),
    }
