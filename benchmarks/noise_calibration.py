"""Accuracy of calibrate-noise on simulated DNG brackets with known (17).

For the paper's gain/offset sweep values (sqrt(alpha) in {0.25 .. 4}, sigma_o in
{1 .. 16}) taken in the 14-bit RAW codes of the simulated DNGs (full well 65 000 to
4 000 electrons, read noise 0.25 to 64 electrons; the paper's 8-bit units scaled by 64
would put the read noise beyond the black level), with and without gain FPN (beta / alpha = 1e-4, a 1 % pixel-gain spread), on the built-in scene
and the scenes of ../shared/data/hdr, through the same code as the CLI:

- a *single bracket*: 5 DNG frames 2 EV apart (``simulate``), ``calibrate-noise IMAGES``;
- *calibration frames*: 4 darks and flats (2 frames at 6 levels), 512 x 512,
  ``calibrate-noise --darks --flats``;
- the *cost of not knowing the camera*: log-irradiance PSNR of ``merge --cfa`` (default
  triangle weights, ml estimator) with the true parameters, with the parameters it measures
  on the bracket itself (no profile), and with photon-noise weights only.

Relative errors are against sigma_o^2 + 1/12 (the quantisation the model lumps in),
alpha, and beta (when beta > 0).  Next to them, what the bracket allows: the Cramer-Rao
standard error of sigma_o^2 and alpha from the exposure contrasts of every pixel
(``core.calibrate.achievable_errors``, at the true parameters, every pixel's irradiance
unknown), and the error in units of that standard error (an efficient estimator gives
a median of 0.67 and a 90th percentile of 1.64): a large error with a small ratio is a
parameter the bracket does not identify, a large ratio an estimator failure.  "target
reachable" is the fraction of channels where 1.64 standard errors fit in the
target (sigma_o^2 5 %, alpha 2 %: :data:`TARGETS`), "within target" where the error does.  A bracket
does not measure beta (texture and gain FPN look alike in photographs): its beta column is
"not measured", and "beta kept" is the fraction of its channels reporting none (all, by
construction).  For the flats, "model picked" is the fraction of runs where the z-test kept
beta exactly when it is > 0.  Also the fit on the real DNG of ../shared/data/raw.

    python -m benchmarks.noise_calibration [--quick]   # benchmarks/results/noise_calibration.md
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks import write_result
from hdrmerge_cli.core.calibrate import achievable_errors, exposure_ratio
from hdrmerge_cli.core.cfa import mosaic
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.sensor import SensorModel, auto_exposure_times
from hdrmerge_cli.io.images import read_exr
from hdrmerge_cli.io.frames import read_frame
from hdrmerge_cli.pipeline.calibrate import CalibrateOptions, _by_channel, _read_group, calibrate_noise
from hdrmerge_cli.pipeline.options import MergeOptions
from hdrmerge_cli.pipeline.run import merge
from hdrmerge_cli.pipeline.simulate import SimulateOptions, load_scene, simulate

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
GAINS = (0.25, 0.5, 1.0, 2.0, 4.0)
SIGMAS = (1.0, 2.0, 4.0, 8.0, 16.0)
PRNU2 = 1e-4  # beta / alpha
CHANNELS = ("R", "G", "B", "G2")
TARGETS = {"sigma_o2": 0.05, "alpha": 0.02}  # relative error a calibration should reach


def achievable(frames: list[str], truth: dict) -> dict[str, dict]:
    """{channel: {"sigma_o2", "alpha"}}: Cramer-Rao relative standard errors of the
    bracket's exposure contrasts at the true parameters (the frames read as calibrate-noise
    reads them, the ratios measured as it measures them)."""
    read = _read_group(sorted((read_frame(f) for f in frames), key=lambda f: f.exposure_time or 0.0), None, "images")
    coef = (truth["sigma_o2"], np.sqrt(truth["alpha"]))
    out = {}
    for ch, items in _by_channel(read).items():
        planes, lo, hi = [p for p, *_ in items], items[0][1], items[0][2]
        ratios = []
        for s, g in zip(planes[:-1], planes[1:]):
            try:
                ratios.append(exposure_ratio(s, g, lo, hi))
            except HdrMergeError:
                ratios.append(None)
        se0, sea = achievable_errors(planes, lo, hi, ratios, coef)
        out[ch] = {"sigma_o2": se0 / truth["sigma_o2"], "alpha": sea / truth["alpha"]}
    return out


def scenes(quick: bool) -> dict[str, tuple[str, float]]:
    out = {"builtin": ("builtin", 1.0)}
    names = ("Desk",) if quick else ("Desk", "StillLife", "MtTamWest")
    for n in names:
        path = SHARED / "hdr" / f"ScanLines_{n}.exr"
        if path.exists():
            out[n] = (str(path), 1000.0)
    return out


def log_psnr(est: np.ndarray, truth: np.ndarray) -> float:
    ok = truth > 0
    lt = np.log(truth[ok])
    mse = np.mean((np.log(np.maximum(est[ok], 1e-30)) - lt) ** 2)
    return float(10 * np.log10(np.ptp(lt) ** 2 / mse))


def run_config(scene: str, scale: float, gain: float, sigma_o: float, beta_on: bool, tmp: Path) -> dict:
    alpha = gain**2
    sensor = SensorModel(alpha=alpha, sigma_o2=sigma_o**2, beta=PRNU2 * alpha if beta_on else 0.0)
    truth = {"sigma_o2": sensor.sigma_o2_total, "alpha": alpha, "beta": sensor.beta}
    opts = SimulateOptions(output_dir=tmp / "b", scene=scene, scale=scale, sensor=sensor, overwrite=True, seed=1)
    irr, _ = load_scene(opts)
    t_mid = auto_exposure_times(mosaic(irr, "RGGB"), sensor, 1)[0]
    opts.times = list(t_mid * 4.0 ** np.arange(-2, 3))
    meta = simulate(opts)
    frames = [str(tmp / "b" / n) for n in meta["frames"]]
    out = {}
    t0 = time.perf_counter()
    s = calibrate_noise(frames, CalibrateOptions(output=tmp / "n.json", overwrite=True))
    out["bracket_seconds"] = time.perf_counter() - t0
    out["bracket"] = s["noise"]["ISO100"]
    out["achievable"] = achievable(frames, truth)
    simulate(SimulateOptions(output_dir=tmp / "d", scene="dark", width=512, height=512, frames=4, sensor=sensor,
                             overwrite=True, seed=2))
    simulate(SimulateOptions(output_dir=tmp / "f", scene="flat", scale=1000.0, width=512, height=512, frames=6,
                             repeat=2, sensor=sensor, overwrite=True, seed=3))
    s = calibrate_noise([], CalibrateOptions(output=tmp / "p.json", darks=str(tmp / "d"), flats=str(tmp / "f"),
                                             overwrite=True))
    out["flats"] = s["noise"]["ISO100"]
    t_mosaic = mosaic(read_exr(tmp / "b" / "truth.exr")[0], "RGGB")
    common = dict(output=tmp / "m.exr", overwrite=True, cfa=True, reference=str(meta["reference_exposure"]))
    for label, extra in (("true", {"noise": f"sigma_o2={truth['sigma_o2']:.9g},alpha={alpha:.9g},beta={sensor.beta:.9g}"}),
                         ("measured", {}), ("photon", {"variance": "photon"})):
        merge(frames, MergeOptions.from_fields(**common, **extra))
        out[f"psnr_{label}"] = log_psnr(read_exr(tmp / "m.exr")[0][..., 0], t_mosaic)
    out["truth"] = truth
    out["config"] = {"sqrt_alpha": gain, "sigma_o": sigma_o, "beta": beta_on}
    return out


def rel_errors(results, source, key):
    errs = []
    for r in results:
        if key == "beta" and r["truth"]["beta"] == 0:
            continue
        for ch in CHANNELS:
            errs.append(abs(r[source][ch][key] / r["truth"][key] - 1))
    return np.array(errs)


def achievable_cells(results, key):
    """(achievable relative s.e., |error| / s.e., fraction reachable, fraction within) of
    the one-bracket estimates, over configurations and channels."""
    se = np.array([r["achievable"][ch][key] for r in results for ch in CHANNELS])
    err = rel_errors(results, "bracket", key)
    return se, err / se, np.mean(1.645 * se <= TARGETS[key]), np.mean(err <= TARGETS[key])


def picks(results, source):
    """Flats: the fraction of channels whose model is quadratic exactly where beta > 0; a
    bracket: the fraction reporting no beta (it does not measure it)."""
    if source == "bracket":
        return float(np.mean([r[source][ch]["beta"] == 0 for r in results for ch in CHANNELS]))
    ok = [(r[source][ch]["model"] == "quadratic") == (r["truth"]["beta"] > 0) for r in results for ch in CHANNELS]
    return float(np.mean(ok))


def real_dng(tmp: Path) -> list[str]:
    dng = SHARED / "raw" / "colorchart.dng"
    if not dng.exists():
        return []
    s = calibrate_noise([str(dng)], CalibrateOptions(output=tmp / "real.json", overwrite=True))
    lines = ["", f"## The real DNG ({dng.name}, one frame: local statistics)", "",
             "| channel | sigma_o^2 | alpha | beta | points | residual RMS |",
             "|---|---|---|---|---|---|"]
    for ch, f in next(iter(s["noise"].values())).items():
        lines.append(f"| {ch} | {f['sigma_o2']:.1f} | {f['alpha']:.3f} | not measured | {f['points']} | "
                     f"{f['residual_rms']:.3f} |")
    return lines


def main(quick: bool = False, out: Path | None = None) -> str:
    out = out or Path(__file__).parent / "results" / f"noise_calibration{'_quick' if quick else ''}.md"
    gains, sigmas = ((0.25, 1.0, 4.0), (2.0, 16.0)) if quick else (GAINS, SIGMAS)
    t0 = time.perf_counter()
    per_scene: dict[str, list] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, (scene, scale) in scenes(quick).items():
            for g in gains:
                for s in sigmas:
                    for b in (False, True):
                        per_scene.setdefault(name, []).append(run_config(scene, scale, g, s, b, Path(tmp)))
            print(f"{name}: {len(per_scene[name])} configurations, {time.perf_counter() - t0:.0f} s", flush=True)
        real = real_dng(Path(tmp))
    every = [r for rs in per_scene.values() for r in rs]
    lines = ["# calibrate-noise accuracy (simulated DNG brackets, known parameters)", "",
             f"{len(every)} configurations: sqrt(alpha) in {gains} x sigma_o in {sigmas} (14-bit codes), beta = 0 and beta/alpha = {PRNU2:g}; scenes {', '.join(per_scene)}; "
             f"{time.perf_counter() - t0:.0f} s.  Median (90th percentile) relative error over configurations "
             "and the 4 CFA channels.", "",
             "| scene | source | sigma_o^2 | alpha | beta (beta > 0) | model picked (bracket: no beta) | merge PSNR true / measured / "
             "photon only (dB) |", "|---|---|---|---|---|---|---|"]

    def cell(e, fmt=".1%"):
        return f"{np.median(e):{fmt}} ({np.percentile(e, 90):{fmt}})" if e.size else "-"

    table2 = ["", "One bracket against what it allows (Cramer-Rao standard error of the exposure contrasts, "
              "median (90th percentile)):", "",
              "| scene | s.e. sigma_o^2 | error / s.e. | target reachable / within (5 %) | s.e. alpha | error / s.e. | "
              "target reachable / within (2 %) |", "|---|---|---|---|---|---|---|"]

    for name, rs in list(per_scene.items()) + [("all", every)]:
        psnr = " / ".join(f"{np.mean([r[f'psnr_{k}'] for r in rs]):.2f}" for k in ("true", "measured", "photon"))
        for source, label in (("bracket", "one bracket"), ("flats", "darks + flats")):
            lines.append(f"| {name} | {label} | {cell(rel_errors(rs, source, 'sigma_o2'))} | "
                         f"{cell(rel_errors(rs, source, 'alpha'))} | "
                         f"{'not measured' if source == 'bracket' else cell(rel_errors(rs, source, 'beta'))} | "
                         f"{picks(rs, source):.0%} | {psnr if source == 'bracket' else ''} |")
        row = [name]
        for key in ("sigma_o2", "alpha"):
            se, z, reach, within = achievable_cells(rs, key)
            row += [cell(se), cell(z, ".2f"), f"{reach:.0%} / {within:.0%}"]
        table2.append("| " + " | ".join(row) + " |")
    lines += table2
    worst = sorted(((abs(r["bracket"][ch]["sigma_o2"] / r["truth"]["sigma_o2"] - 1), name, r, ch)
                    for name, rs in per_scene.items() for r in rs for ch in CHANNELS), key=lambda w: -w[0])[:8]
    lines += ["", "Largest one-bracket sigma_o^2 errors:", "",
              "| scene | sqrt(alpha) | sigma_o | beta > 0 | channel | error | s.e. | error / s.e. |",
              "|---|---|---|---|---|---|---|---|"]
    for e, name, r, ch in worst:
        se = r["achievable"][ch]["sigma_o2"]
        lines.append(f"| {name} | {r['config']['sqrt_alpha']:g} | {r['config']['sigma_o']:g} | "
                     f"{'yes' if r['config']['beta'] else 'no'} | {ch} | {e:.1%} | {se:.1%} | {e / se:.1f} |")
    cost = np.array([r["psnr_true"] - r["psnr_measured"] for r in every])
    lines += ["", f"Cost of not knowing the camera (true minus measured-on-the-bracket PSNR): mean {cost.mean():+.3f} dB, "
              f"worst {cost.max():+.3f} dB.  Bracket calibration time (5 frames, incl. decoding): median "
              f"{np.median([r['bracket_seconds'] for r in every]):.2f} s."]
    lines += real
    return write_result(out, lines)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="2 scenes, 3 gains x 2 offsets")
    args = ap.parse_args()
    print(main(args.quick))
