"""Leave-one-out on the real brackets of ``../shared/data/brackets``: our methods and the
peers on the same frames.

For every bracket and every interior frame ``k`` (the shortest and longest exposures
would need extrapolation): merge all frames but ``k`` -- the camera response estimated
*without* frame ``k`` -- predict frame ``k``'s codes through each method's own response
(``z = gamma(E h_k)``), and measure the RMSE in code values over the pixels whose actual
code lies in [10, 245] (well exposed) in every channel.  No ground truth is needed, and a
method that gets the response, the merge or the units wrong predicts the frame badly.

Frames are decimated (every ``s``-th pixel, so the codes stay genuine camera codes) to at
most :data:`MAX_PIXELS` pixels.  Hand-held and ghosted brackets are kept (no method
aligns here): their numbers show how much misregistration costs everyone alike.

Ours: each CRF method of ``estimate-crf`` (and its options) with each merge configuration;
peers: :mod:`benchmarks.peers` (OpenCV Debevec/Robertson, colour-hdri, Luminance HDR CLI,
pfstools when installed).

    python -m benchmarks.real_loo [--quick]   # results/real_loo.md
"""
from __future__ import annotations

import argparse
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks import write_result

RESULTS = Path(__file__).parent / "results"
BRACKETS = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "brackets"
MAX_PIXELS = 400_000
LOW, HIGH = 10, 245
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")
TIMES_FILE = "exposure_times_seconds.txt"


def load_bracket(folder: Path, max_pixels: int = MAX_PIXELS):
    """Frames (sorted by exposure), their decimated codes (H, W, 3) uint8, exposures and
    the decimation step."""
    from hdrmerge_cli.io.frames import load_codes
    from hdrmerge_cli.pipeline.bracket import read_bracket
    from hdrmerge_cli.io.metadata import exposure_values

    paths = sorted(str(p) for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    times = folder / TIMES_FILE  # a bracket without EXIF (a film scan) states its times in this file
    frames = read_bracket(paths, times_file=str(times) if times.exists() else None)
    step = max(1, int(np.ceil(np.sqrt(frames[0].width * frames[0].height / max_pixels))))
    codes = [np.ascontiguousarray(load_codes(f)[::step, ::step]) for f in frames]
    return frames, codes, exposure_values(frames), step


# ---------------------------------------------------------------- our configurations
def ours(codes, exposures, frames, crf: str = "goossens", crf_options: dict | None = None, weights: str = "triangle",
         estimator: str = "log", noise: str = "none", variance: str = "auto", irls: int = 0, excess: bool = False):
    """Estimate the response of ``codes`` (our estimate-crf), merge them (our merge core).
    ``excess``: the noise measured on each frame's local statistics and the variance beyond
    it on the exposure pairs, as merge measures them on an image bracket
    (:mod:`hdrmerge_cli.pipeline.excess`), the latter in the tables in place of the fixed
    tolerance.  Returns (E per second in units of the normalised linear signal, CRF)."""
    from benchmarks.core_merge import merge_frames
    from hdrmerge_cli.core.crf_estimate import fit_response

    log_h = np.log(exposures)
    opts = dict(crf_options or {})
    crf = fit_response(codes, log_h, 256, crf, opts.pop("smoothing", None), opts.pop("samples", None), opts).crf
    params = None
    if noise == "measured" and excess:  # as merge measures an image bracket's noise (None where it cannot)
        from hdrmerge_cli.pipeline.noise import measure_noise

        lookup = {id(f): c for f, c in zip(frames, codes)}
        found, _ = measure_noise(frames, crf, lambda f: lookup[id(f)], None, cache=False)
        params = [found[ch] for ch in frames[0].channel_names] if found else None
    elif noise == "measured":
        from hdrmerge_cli.core.noise import NoiseParams
        from hdrmerge_cli.pipeline.noise import estimate_bracket_noise

        lookup = {id(f): c for f, c in zip(frames, codes)}
        used, _, _ = estimate_bracket_noise(frames, crf, lambda f: lookup[id(f)], None)
        params = [NoiseParams(**used[ch]) for ch in frames[0].channel_names]
    measured = None
    if excess:
        from hdrmerge_cli.pipeline.excess import measure_excess
        from hdrmerge_cli.core.samples import Samples

        samples = Samples([c.astype(np.float32) / 255.0 for c in codes], np.ones(codes[0].shape[:2], bool),
                          (0, 0, 0, 0), 1, 1.0 / 255.0)
        names = frames[0].channel_names
        measured = measure_excess(samples, exposures, crf, dict(zip(names, params)) if params else None, names)
    from hdrmerge_cli.core.reconstruct import prior_rate_of
    from hdrmerge_cli.pipeline.choices import default_variance

    k = len(codes) // 2
    prior = prior_rate_of(codes[k], 0.0, 255.0, exposures[k], crf.at_codes(256, np.zeros(3), 255.0)) if weights in ("probabilistic", "direct", "optimal") else None
    e, _, _ = merge_frames(codes, exposures, crf, [0.0] * 3, [255.0] * 3, weights, params,
                           default_variance(params, crf) if variance == "auto" else variance, estimator, prior_rate=prior,
                           pattern=np.arange(3)[None, :], irls_iterations=irls, excess=measured)
    return e.astype(np.float64), crf


def plain_merge(paths: list[str], step: int, h: float, workdir: Path, times: list[float] | None = None) -> np.ndarray:
    """The command a user types, ``hdrmerge-cli merge FILES -o out.exr`` with no response
    option (the response measured on the bracket), on the full-resolution files, with
    ``--align off`` as every row here (alignment is align_loo's subject); the left-out frame
    of exposure ``h`` predicted through the response its profile records, on the
    benchmark's decimated grid.  ``times``: the frames' exposure times, where EXIF has none."""
    import json
    import subprocess
    import sys

    from hdrmerge_cli.io.images import read_exr
    from hdrmerge_cli.io.profile import crf_from_json

    exe = Path(sys.executable).parent / "hdrmerge-cli"
    out = workdir / "plain.exr"
    given = ["--times", ",".join(f"{t:.9g}" for t in times)] if times else []
    subprocess.run([str(exe), "merge", *paths, *given, "-o", str(out), "-q", "--overwrite", "--align", "off"],
                   check=True)
    pixels, header = read_exr(str(out))
    crf = crf_from_json(json.loads(out.with_suffix(".profile.json").read_text())["crf"])
    e = pixels[::step, ::step, :3].astype(np.float64) / float(header["hdrmerge:referenceExposure"])
    return predict_ours(e, crf, h)


def predict_ours(e: np.ndarray, crf, h: float) -> np.ndarray:
    return np.stack([crf.forward(np.clip(e[..., c] * h, 0, 1), c) * 255.0 for c in range(3)], axis=-1)


#: name -> keywords of :func:`ours`
CONFIGS = {
    "defaults": {},
    "indep. channels": {"crf_options": {"coupling": 0.0}},
    "var=photon": {"variance": "photon"},
    "var=none": {"variance": "none"},
    "noise measured": {"noise": "measured"},
    "debevec CRF": {"crf": "debevec"},
    "robertson CRF": {"crf": "robertson"},
    "probabilistic": {"weights": "probabilistic", "noise": "measured"},
    "uniform/ml": {"weights": "uniform", "estimator": "ml", "noise": "measured"},
    "excess/log": {"noise": "measured", "variance": "codes", "excess": True},
    "excess/ml": {"weights": "uniform", "estimator": "ml", "noise": "measured", "excess": True, "irls": 1},
}
#: what each configuration is (the Markdown legend)
LEGEND = {
    "defaults": "what `estimate-crf` then `merge --crf` do with no option: the goossens QP with coupled channels, "
                "triangle weights, the log estimator (7), the `codes` variance factor",
    "indep. channels": "defaults with `estimate-crf --coupling 0`",
    "var=photon": "defaults with `merge --variance photon` (photon noise alone)",
    "var=none": "defaults with `merge --variance none` (weights alone, as OpenCV and colour-hdri)",
    "noise measured": "defaults with the noise measured on the bracket (`--variance model`)",
    "debevec CRF": "`estimate-crf --method debevec`, merge defaults",
    "robertson CRF": "`estimate-crf --method robertson`, merge defaults",
    "probabilistic": "`merge --weights probabilistic` (noise measured on the bracket)",
    "uniform/ml": "`merge --estimator ml --weights uniform` (noise measured on the bracket, no IRLS)",
    "excess/log": "defaults with the variance beyond the noise model measured on the exposure pairs "
                  "([method](method.md#the-variance-beyond-the-noise-model)) in place of the 1 % tolerance",
    "excess/ml": "`merge --estimator ml`: uniform weights, the noise measured on each frame's local statistics, "
                 "the variance beyond it measured on the exposure pairs, one IRLS pass",
}


def rmse(pred: np.ndarray, actual: np.ndarray, mask: np.ndarray) -> float:
    d = pred[mask] - actual[mask]
    return float(np.sqrt(np.mean(d * d)))


#: the row of the plain command (:func:`plain_merge`)
PLAIN = "merge (no option)"


def run(quick: bool = False, configs=None, peers=True, brackets=None, plain=True) -> list[dict]:
    configs = configs or CONFIGS
    rows = []
    folders = sorted(p for p in BRACKETS.iterdir() if p.is_dir())
    if brackets:
        folders = [f for f in folders if f.name in brackets]
    available = {}
    if peers:
        from benchmarks import peers as peer_mod

        available = peer_mod.available()
    for folder in folders:
        frames, codes, exposures, step = load_bracket(folder, MAX_PIXELS // (4 if quick else 1))
        interior = range(1, len(frames) - 1)
        if quick:
            interior = [len(frames) // 2]
        for k in interior:
            keep = [j for j in range(len(frames)) if j != k]
            actual = codes[k].astype(np.float64)
            mask = np.all((codes[k] >= LOW) & (codes[k] <= HIGH), axis=-1)
            row = {"bracket": folder.name, "left_out": frames[k].name, "frames": len(frames), "pixels": int(mask.sum())}
            if plain:
                t = time.perf_counter()
                with tempfile.TemporaryDirectory() as tmp:
                    try:
                        times = [frames[j].exposure_time for j in keep] if (folder / TIMES_FILE).exists() else None
                        pred = plain_merge([frames[j].path for j in keep], step, exposures[k], Path(tmp), times)
                        row[PLAIN] = rmse(pred, actual, mask)
                    except Exception as exc:  # noqa: BLE001
                        logging.warning("%s %s: %s failed: %s", folder.name, frames[k].name, PLAIN, exc)
                        row[PLAIN] = float("nan")
                row[PLAIN + " s"] = time.perf_counter() - t
            for name, kw in configs.items():
                t = time.perf_counter()
                try:
                    e, crf = ours([codes[j] for j in keep], exposures[keep], [frames[j] for j in keep], **kw)
                    row[name] = rmse(predict_ours(e, crf, exposures[k]), actual, mask)
                except Exception as exc:  # noqa: BLE001 - a benchmark reports and goes on
                    logging.warning("%s %s: %s failed: %s", folder.name, frames[k].name, name, exc)
                    row[name] = float("nan")
                row[name + " s"] = time.perf_counter() - t
            for name, why in available.items():
                if why is not None:
                    continue
                with tempfile.TemporaryDirectory() as tmp:
                    try:
                        res = peer_mod.run_peer(name, [codes[j] for j in keep], list(exposures[keep]), Path(tmp))
                        row[name] = rmse(peer_mod.predict_codes(res, exposures[k]), actual, mask)
                        row[name + " s"] = res.seconds
                    except Exception as exc:  # noqa: BLE001
                        logging.warning("%s %s: peer %s failed: %s", folder.name, frames[k].name, name, exc)
                        row[name] = float("nan")
            rows.append(row)
            print(f"{row['bracket']} {row['left_out']}: " + ", ".join(
                f"{n}={v:.2f}" for n, v in row.items() if isinstance(v, float) and not n.endswith(" s")), flush=True)
    return rows, available


def table(rows, available) -> list[str]:
    methods = [n for n in rows[0] if n not in ("bracket", "left_out", "frames", "pixels") and not n.endswith(" s")]
    peer_names = [m for m in methods if m not in CONFIGS and m != PLAIN]
    lines = ["# Leave-one-out on the real brackets", "",
             "RMSE (code values) of the left-out frame's codes predicted from the merge of the other frames, "
             f"over its pixels with every channel in [{LOW}, {HIGH}]; frames decimated to at most "
             f"{MAX_PIXELS} pixels. Lower is better; **bold** = best of the row.", ""]
    lines += ["Ours (one estimate-crf + merge per left-out frame, the response fitted without it):", ""]
    lines += [f"- **{n}**: {LEGEND[n]}" for n in methods if n in LEGEND]
    if PLAIN in methods:
        lines += [f"- **{PLAIN}**: `hdrmerge-cli merge FILES -o out.exr --align off`, no response given (it is "
                  "measured on the bracket), on the full-resolution files; seconds: the whole command"]
    lines += ["", "Peers (see benchmarks/peers.py): each recovers its own response from the same frames and "
              "merges with it; the left-out frame is predicted through that response.", ""]
    skipped = {n: why for n, why in available.items() if why}
    if skipped:
        lines += ["Peers skipped: " + "; ".join(f"{n} ({why})" for n, why in skipped.items()), ""]
    lines += ["| bracket | left out | " + " | ".join(methods) + " |", "|---|---|" + "---|" * len(methods)]
    for r in rows:
        vals = [r[m] for m in methods]
        best = np.nanmin(vals)
        lines.append(f"| {r['bracket']} | {r['left_out']} | " + " | ".join(
            ("**%.2f**" if v == best else "%.2f") % v for v in vals) + " |")
    arr = np.array([[r[m] for m in methods] for r in rows])
    best_peer = np.nanmin(arr[:, [methods.index(p) for p in peer_names]], axis=1) if peer_names else None
    lines += ["", "| method | mean RMSE | geo-mean ratio to best peer | cases <= best peer | mean seconds |",
              "|---|---|---|---|---|"]
    for i, m in enumerate(methods):
        ratio = (np.exp(np.nanmean(np.log(arr[:, i] / best_peer))) if best_peer is not None else float("nan"))
        wins = int(np.sum(arr[:, i] <= best_peer * (1 + 1e-9))) if best_peer is not None else 0
        secs = np.mean([r.get(m + " s", np.nan) for r in rows])
        lines.append(f"| {m} | {np.nanmean(arr[:, i]):.3f} | {ratio:.3f} | {wins}/{len(rows)} | {secs:.2f} |")
    return lines


def neutral_drift(crf, lo: int = 5, hi: int = 250) -> float:
    """How far a neutral ramp (equal codes in every channel) drifts in colour over codes
    ``lo..hi``: the largest peak-to-peak of ``log gamma_c^-1(z) - log gamma_G^-1(z)``."""
    g = np.log(np.maximum(crf.table[:, lo:hi + 1], 1e-300))
    return float(max(np.ptp(g[c] - g[1]) for c in (0, 2)))


def drift_table(quick: bool = False) -> list[str]:
    """Each bracket's response from all its frames, channels independent and coupled."""
    from hdrmerge_cli.core.crf_estimate import fit_response

    lines = ["", "## Neutral ramps", "",
             "Colour drift of a neutral ramp (equal codes in R, G, B) through each bracket's response, codes 5-250: "
             "the largest peak-to-peak over codes of log(R/G) and log(B/G) (0 = stays neutral; 0.1 = 10 % colour "
             "shift between shadows and highlights).", "",
             "| bracket | channels independent | coupled (default) |", "|---|---|---|"]
    for folder in sorted(p for p in BRACKETS.iterdir() if p.is_dir()):
        _, codes, exposures, _ = load_bracket(folder, MAX_PIXELS // (4 if quick else 1))
        free = fit_response(codes, np.log(exposures), 256, options={"coupling": 0.0}).crf
        tied = fit_response(codes, np.log(exposures), 256).crf
        lines.append(f"| {folder.name} | {neutral_drift(free):.3f} | {neutral_drift(tied):.3f} |")
    return lines


def main(quick: bool = False) -> str:
    if not BRACKETS.is_dir():
        return f"real_loo: skipped ({BRACKETS} not found: the real brackets live in ../shared/data)"
    rows, available = run(quick)
    return write_result(RESULTS / f"real_loo{'_quick' if quick else ''}.md",
                        table(rows, available) + drift_table(quick))


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    print(main(ap.parse_args().quick))
