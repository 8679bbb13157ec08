"""The paper's simulated-scene experiment (Fig. 19), with the Cramer-Rao bound.

A real HDR scene from ../shared/data/hdr is rendered through the sensor model (16)-(18)
with the CRF gamma(x) = x^0.4 (``gamma:2.5`` here) into 4 lossless 8-bit TIFF frames, for
the paper's sweep sqrt(alpha) in {0.25, 0.5, 1, 2, 4} and sigma_o in {0.001, 0.5, 1, 2, 4,
8, 16} (8-bit code units of the linear signal), and merged with every weighting and both
estimators with the CRF and noise known.  Accuracy is the PSNR of log-irradiance against
the ground truth (peak = the log range), next to the PSNR of the Cramer-Rao bound: the
inverse Fisher information of log E carried by the 4 quantised, clipped codes,

    I(log E) = sum_j sum_z (d P_j(z | E) / d log E)^2 / P_j(z | E),

with ``P_j(z | E)`` the probability that frame j reads code z (a normal through the CRF's
code bins), evaluated on a grid of E and interpolated per pixel.

    python -m benchmarks.fig19 [--quick]   # writes benchmarks/results/fig19.md
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks import write_result
from benchmarks.accuracy import GAMMA, crb_log
from hdrmerge_cli.core.sensor import SensorModel
from hdrmerge_cli.io.images import read_exr
from hdrmerge_cli.pipeline.options import MergeOptions
from hdrmerge_cli.pipeline.run import merge
from hdrmerge_cli.pipeline.simulate import SimulateOptions, simulate

SCENE = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "hdr" / "ScanLines_Desk.exr"
GAINS = (0.25, 0.5, 1.0, 2.0, 4.0)
SIGMAS = (0.001, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0)
WEIGHTS = ("triangle", "mann", "deneve", "gaussian", "uniform", "probabilistic", "direct", "optimal", "bounded")
LINEAR_BITS = 12
SCALE = (2**LINEAR_BITS - 1) / 255.0  # 12-bit linear codes per 8-bit linear code


def run_config(gain: float, sigma_o: float, folder: Path, downscale: int, scale: float) -> dict:
    sensor = SensorModel(alpha=(gain * SCALE) ** 2, sigma_o2=max((sigma_o * SCALE) ** 2 - 1 / 12, 0.0), beta=0.0,
                         bits=LINEAR_BITS, black=0)
    meta = simulate(SimulateOptions(output_dir=folder, scene=str(SCENE), downscale=downscale, scale=scale, frames=4,
                                    sensor=sensor, fmt="tif", crf=f"gamma:{GAMMA}", out_bits=8, overwrite=True))
    truth, _ = read_exr(folder / "truth.exr")
    frames = [str(folder / n) for n in meta["frames"]]
    noise = f"sigma_o2={sigma_o**2 + 1 / 12 / SCALE**2:.9g},alpha={gain**2:.9g}"
    # the bound, per pixel, in the merge's units: truth * 255 / t_ref is E in 8-bit codes per second
    pos = truth > 0
    e_px = truth[pos] * 255.0 / meta["reference_exposure"]
    grid = np.geomspace(e_px.min(), e_px.max(), 400)
    crb_px = np.interp(np.log(e_px), np.log(grid), np.log(crb_log(grid, meta["exposure_times"], gain, sigma_o**2, 255.0, "jpeg")))
    ok = pos.copy()
    ok[pos] = np.exp(crb_px) < 1.0  # pixels the bracket measures (log-error sd below 1)
    crb = np.exp(crb_px[ok[pos]])
    log_t = np.log(truth[ok])
    peak2 = np.ptp(log_t) ** 2
    out = {"coverage": (float(ok.sum() / pos.sum()), 0.0)}
    for est in ("log", "ml"):
        for w in WEIGHTS:
            s = merge(frames, MergeOptions.from_fields(output=folder / "m.exr", overwrite=True, weights=w, crf=f"gamma:{GAMMA}",
                                           noise=noise, estimator=est, reference=str(meta["reference_exposure"])))
            est_img, _ = read_exr(folder / "m.exr")
            mse = np.mean((np.log(np.maximum(est_img[ok], 1e-30)) - log_t) ** 2)
            out[(w, est)] = (10 * np.log10(peak2 / mse), s["timing_seconds"]["merge"])
    out["crb"] = (10 * np.log10(peak2 / np.mean(crb)), 0.0)
    return out


def main(quick: bool = False, out: Path = Path(__file__).parent / "results" / "fig19.md") -> str:
    if not SCENE.exists():
        raise SystemExit(f"{SCENE} not found: the benchmark needs ../shared/data")
    gains, sigmas = ((1.0,), (1.0, 8.0)) if quick else (GAINS, SIGMAS)
    t0 = time.perf_counter()
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for g in gains:
            for s in sigmas:
                results[(g, s)] = run_config(g, s, Path(tmp) / "b", downscale=4, scale=200.0)
    keys = [(w, e) for e in ("log", "ml") for w in WEIGHTS]
    lines = ["# Fig. 19: simulated scene, CRF x^0.4, PSNR of log-irradiance (dB)", "",
             f"Scene {SCENE.name} (downscaled 4x), 4 lossless 8-bit TIFF frames, CRF and noise known; "
             f"{len(results)} (sqrt(alpha), sigma_o) pairs; {time.perf_counter() - t0:.0f} s.  "
             "'below CRB' = dB under the Cramer-Rao bound of the quantised, clipped codes.", "",
             "| weights | estimator | PSNR (mean) | below CRB (mean) | vs triangle/log | merge s (mean) |",
             "|---|---|---|---|---|---|"]
    crb = np.array([r["crb"][0] for r in results.values()])
    base = np.array([r[("triangle", "log")][0] for r in results.values()])
    for k in keys:
        ps = np.array([r[k][0] for r in results.values()])
        ts = np.array([r[k][1] for r in results.values()])
        lines.append(f"| {k[0]} | {k[1]} | {ps.mean():.2f} | {(crb - ps).mean():.2f} | {(ps - base).mean():+.2f} | "
                     f"{ts.mean():.3f} |")
    lines.append(f"| Cramer-Rao bound | | {crb.mean():.2f} | 0 | {(crb - base).mean():+.2f} | |")
    cov = np.array([r["coverage"][0] for r in results.values()])
    lines += ["", f"Pixels compared: those the bracket measures (CRB of log E below 1), {cov.mean():.1%} on average."]
    return write_result(out, lines)


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="two operating points only")
    print(main(ap.parse_args().quick))
