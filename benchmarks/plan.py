"""``python -m benchmarks plan``: capture plans (``hdrmerge-cli plan``) on real HDR scenes
rendered by the simulator, against conventional brackets, predicted and measured.

Protocol.  Each scene of ../shared/data/hdr (downscaled 2x) is scaled so that its
99.99th-percentile photosite saturates at 1/500 s at ISO 100, then seen by two simulated
14-bit cameras (alpha 0.25 code values^2 per electron at ISO 100):

- ``post-amp``: read noise mostly after the ISO amplifier (sigma_o^2 = 36 code values^2 at
  ISO 100, 32 of them after it: a camera whose high ISOs lower the read noise, as in
  Hasinoff et al. 2010);
- ``ISO-invariant``: all read noise before the amplifier (sigma_o^2 = 4, none after it).

The metering bracket is 3 DNG frames at ISO 100 (1/500, 1/60, 1/8 s).  The profile holds
the noise (17) at each whole-stop ISO from 100 to 6400 (the simulator's own, so that the
plan, not the calibration, is measured).  For each total time, ``plan --time T`` gives
the plan with the ISO free and with ISO 100 only, and its comparisons the best
conventional 1- and 2-EV brackets at ISO 100 within the same time.  Each bracket is then
simulated (fresh noise) and merged (``merge --profile --cfa``, defaults).

Measured worst-case SNR: per channel, the photosites whose true irradiance lies in the
range the plan protects (from the 1 % darkest to the 0.1 % brightest of the metered
photosites, ``plan``'s defaults), binned by true irradiance (1/12 EV, and a bin starting
at each frame's SNR dip); per bin the SNR ``-10 log10 mean((E_merged / E_true - 1)^2)``
over bins holding at least 0.1 % of the channel's photosites (as ``plan`` counts the
irradiances a scene holds) and 100 of them.  ``worst case at truth``: the model's SNR of
the worst bin (``-10 log10`` of the mean of ``1 / SNR(r)`` over its photosites);
``measured``: the merged result's in that bin; ``lowest measured bin``: the minimum over
all bins, biased low by each bin's sampling noise (about 0.6 dB at 100 photosites).
``plan's worst case`` is what ``plan`` printed from the metering frames.  The 1st
percentile: the SNR that all but 1 % of the photosites reach (each colour weighed
alike, lost photosites included; photosites whose true irradiance is 0, which some
scenes hold, have no SNR and are left out), ``plan's 1 %`` as ``plan`` printed it, ``at truth``
from each photosite's true irradiance, ``measured`` with each photosite taking its
1/12-EV bin's measured SNR.  The conventional brackets are those ``plan`` compares with:
frames 1 or 2 EV apart at ISO 100 from any first time, shot as many times over as the
time and the 10 frames allow, the best worst case.  Time saved: the total time of the
shortest conventional bracket that reaches the plan's predicted worst case, over the
plan's.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).parent / "results"
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "hdr"
SCENES = ("ScanLines_Desk.exr", "ScanLines_MtTamWest.exr", "ScanLines_StillLife.exr")
CAMERAS = {"post-amp": {"sigma_o2": 36.0, "sigma_post2": 32.0},
           "ISO-invariant": {"sigma_o2": 4.0, "sigma_post2": 0.0}}
ALPHA, BITS, BLACK = 0.25, 14, 512
ISOS = (100, 200, 400, 800, 1600, 3200, 6400)
METERING = (1 / 500, 1 / 60, 1 / 8)
BUDGETS = (1 / 4, 2.0)
SATURATE_AT = 1 / 500
BIN_EV, MIN_BIN, OCCUPIED = 1 / 12, 100, 1e-3


def _cli(*args) -> subprocess.CompletedProcess:
    cmd = [str(Path(sys.executable).parent / "hdrmerge-cli"), *map(str, args)]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=os.environ | {"PYTHONWARNINGS": "ignore"})
    if proc.returncode:
        raise RuntimeError(f"{' '.join(cmd[1:4])}...: {proc.stderr.strip()[-300:]}")
    return proc


def _camera_flags(camera: dict) -> list[str]:
    return ["--alpha", ALPHA, "--sigma-o2", camera["sigma_o2"], "--sigma-post2", camera["sigma_post2"],
            "--bits", BITS, "--black", BLACK, "--base-iso", 100]


def _profile(path: Path, camera: dict) -> None:
    from hdrmerge_cli.core.crf import CRF
    from hdrmerge_cli.core.sensor import SensorModel
    from hdrmerge_cli.io.profile import new_profile

    sensor = SensorModel(alpha=ALPHA, sigma_o2=camera["sigma_o2"], sigma_post2=camera["sigma_post2"], bits=BITS,
                         black=BLACK, base_iso=100)
    noise = {}
    for iso in ISOS:
        s = sensor.at_iso(iso)
        noise[f"ISO{iso}"] = {ch: {"sigma_o2": s.sigma_o2_total, "alpha": s.alpha, "beta": s.beta}
                              for ch in ("R", "G", "B")}
    prof = new_profile({"make": "hdrmerge-cli", "model": "simulated sensor"}, BITS, CRF("linear"), [], "benchmark")
    path.write_text(json.dumps(prof | {"noise": noise}))


def _scene(name: str, work: Path) -> tuple[Path, float, np.ndarray]:
    """The scene downscaled 2x (written as EXR), the --scale that saturates its
    99.99th percentile at SATURATE_AT, and its RGGB mosaic of electrons per second."""
    from hdrmerge_cli.core.cfa import mosaic
    from hdrmerge_cli.io.images import read_exr, write_exr

    pixels, _ = read_exr(str(SHARED / name))
    rgb = np.clip(pixels[..., :3].astype(np.float64), 0, None)
    h, w = rgb.shape[0] // 4 * 4, rgb.shape[1] // 4 * 4
    rgb = rgb[:h, :w].reshape(h // 2, 2, w // 2, 2, 3).mean(axis=(1, 3))
    path = work / name
    if not path.exists():
        write_exr(str(path), rgb.astype(np.float32), ["R", "G", "B"], {})
    electrons = (2 ** BITS - 1 - BLACK) / np.sqrt(ALPHA) / SATURATE_AT
    scale = electrons / float(np.percentile(rgb, 99.99))
    return path, scale, mosaic(rgb * scale, "RGGB")


def _measure(folder: Path, merged: Path, electrons: np.ndarray, frames: list[dict], camera: dict,
             ranges: dict) -> dict:
    """Measured and predicted-at-truth worst-case SNR (dB) of one merged bracket, over
    the irradiance ``ranges`` per channel name (code values per second at ISO 100) that
    the plan targeted."""
    from hdrmerge_cli.core import capture_hasinoff2010 as cap
    from hdrmerge_cli.core.cfa import mosaic
    from hdrmerge_cli.core.noise import NoiseParams
    from hdrmerge_cli.core.sensor import SensorModel
    from hdrmerge_cli.io.images import read_exr

    truth = mosaic(read_exr(str(folder / "truth.exr"))[0][..., :3].astype(np.float64), "RGGB")
    est = read_exr(str(merged))[0][..., 0].astype(np.float64)
    rel2 = (est / np.maximum(truth, 1e-30) - 1.0) ** 2
    sensor = SensorModel(alpha=ALPHA, sigma_o2=camera["sigma_o2"], sigma_post2=camera["sigma_post2"], bits=BITS,
                         black=BLACK, base_iso=100)
    y_full = float(2 ** BITS - 1 - BLACK)
    plan = []
    for f in frames:
        s = sensor.at_iso(f["iso"])
        p = NoiseParams(s.sigma_o2_total, s.alpha, s.beta)
        plan.append((cap.make_settings([f["time"]], [f["iso"]], {f["iso"]: (p,)}, 100.0, y_full)[0], 1))
    r = electrons * np.sqrt(ALPHA)  # code values per second at ISO 100
    bins = []  # (predicted, measured, photosites) per bin of every channel
    low_pred, low_meas = [], []  # per channel: (SNR per photosite, weight), predicted and by its bin's measure
    for (i, j), name in zip(((0, 0), (0, 1), (1, 0), (1, 1)), ("R", "G", "G2", "B")):
        rc, e2 = r[i::2, j::2].ravel(), rel2[i::2, j::2].ravel()
        n = rc.size
        inv = 1.0 / np.maximum(cap.snr_power(rc, plan, 0), 1e-300)
        # the 1st percentile over the photosites that see light (a scene's zeros have no
        # SNR), each colour weighed alike as plan does: each takes its 1/12-EV bin's
        # measured SNR
        lit = rc > 0
        weight = np.full(int(lit.sum()), 0.5 if name.startswith("G") else 1.0) / lit.sum()
        index = np.floor(np.log2(rc[lit]) / BIN_EV).astype(np.int64)
        _, inverse = np.unique(index, return_inverse=True)
        per_bin = np.bincount(inverse, e2[lit]) / np.bincount(inverse)
        low_pred.append((-10 * np.log10(inv[lit]), weight))
        low_meas.append((-10 * np.log10(np.maximum(per_bin[inverse], 1e-300)), weight))
        lo, hi = ranges[name]
        keep = (rc >= lo) & (rc <= hi)
        rc, e2, inv = rc[keep], e2[keep], inv[keep]
        # bins of BIN_EV that also start at each frame's SNR dip
        clips = [s.clipping_point(0) for s, _ in plan]
        edges = np.unique(np.r_[lo * 2.0 ** np.arange(0, np.log2(hi / lo) + BIN_EV, BIN_EV),
                                [c for c in clips if lo < c < hi]])
        index = np.searchsorted(edges, rc, side="right")
        for b in np.unique(index):
            sel = index == b
            if sel.sum() >= max(MIN_BIN, OCCUPIED * n):
                bins.append((-10 * np.log10(np.mean(inv[sel])), -10 * np.log10(np.mean(e2[sel])), int(sel.sum())))
    worst = min(bins)
    return {"predicted_at_truth": float(worst[0]), "measured": float(worst[1]),
            "measured_min": float(min(b[1] for b in bins)),
            "low_at_truth": _percentile(low_pred), "low_measured": _percentile(low_meas)}


def _percentile(parts: list) -> float:
    """The low end (``plan``'s percentile) of per-photosite SNRs ``[(snr, weight), ...]``."""
    from hdrmerge_cli.core.capture_hasinoff2010 import LOW_PERCENTILE, weighted_percentile

    return weighted_percentile(np.concatenate([a for a, _ in parts]), np.concatenate([b for _, b in parts]),
                               LOW_PERCENTILE)


def _shoot(work: Path, tag: str, scene: Path, scale: float, camera: dict, frames: list[dict], profile: Path,
           seed: int) -> Path:
    """Simulate the bracket ``frames`` of the scene and merge it (defaults, --cfa)."""
    folder = work / tag
    times = ",".join(repr(f["time"]) for f in frames)
    isos = ",".join(str(int(f["iso"])) for f in frames)
    _cli("simulate", "-o", folder, "-q", "--scene", scene, "--scale", scale, "--times", times, "--iso", isos,
         "--seed", seed, *_camera_flags(camera))
    _cli("merge", *sorted(folder.glob("frame_*.dng")), "--profile", profile, "--cfa", "-o", folder / "m.exr", "-q")
    return folder


def run_case(work: Path, scene_name: str, camera_name: str, budget: float, seed: int) -> list[dict]:
    camera = CAMERAS[camera_name]
    scene, scale, electrons = _scene(scene_name, work)
    profile = work / f"{camera_name}.json"
    _profile(profile, camera)
    meter = work / f"meter-{camera_name}"
    if not meter.exists():
        _cli("simulate", "-o", meter, "-q", "--scene", scene, "--scale", scale, "--times",
             ",".join(map(repr, METERING)), "--seed", seed, *_camera_flags(camera))
    dngs = sorted(meter.glob("frame_*.dng"))
    t0 = time.perf_counter()
    free = json.loads(_cli("plan", *dngs, "--profile", profile, "--time", budget, "--json").stdout)
    plan_seconds = time.perf_counter() - t0
    brackets = {"plan, ISO free": free, "plan, ISO 100": free["compared"]["plan at ISO 100 only"]}
    for step in (1, 2):
        conv = free["compared"].get(f"conventional {step}-EV bracket at ISO 100")
        if conv is not None:
            brackets[f"conventional {step}-EV"] = conv
    same = [free["compared"].get(f"conventional {s}-EV bracket at ISO 100, same SNR") for s in (1, 2)]
    same_time = min((c["total_time"] for c in same if c), default=None)
    rows = []
    for k, (name, b) in enumerate(brackets.items()):
        folder = _shoot(work, f"{camera_name}-{budget:g}-{k}", scene, scale, camera, b["frames"], profile, seed + k + 1)
        m = _measure(folder, folder / "m.exr", electrons, b["frames"], camera, free["worst_case"]["range"])
        rows.append({"scene": scene_name.removeprefix("ScanLines_").removesuffix(".exr"), "camera": camera_name,
                     "budget": budget, "bracket": name, "frames": len(b["frames"]), "time": b["total_time"],
                     "isos": sorted({int(f["iso"]) for f in b["frames"]}),
                     "predicted": b["predicted_worst_snr_db"], "predicted_low": b.get("predicted_low_snr_db", float("nan")), **m,
                     "time_saved": (same_time / free["total_time"]) if (same_time and k == 0) else None,
                     "plan_seconds": plan_seconds if k == 0 else None})
    return rows


def _table(rows: list[dict]) -> str:
    head = ("| scene | camera | budget (s) | bracket | frames | time (s) | ISOs | plan's worst case (dB) | "
            "worst case at truth (dB) | measured (dB) | lowest measured bin (dB) | plan's 1 % (dB) | 1 % at truth (dB) | "
            "1 % measured (dB) | time saved at equal SNR |")
    out = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        saved = f"{r['time_saved']:.1f}x" if r["time_saved"] else ""
        out.append(f"| {r['scene']} | {r['camera']} | {r['budget']:g} | {r['bracket']} | {r['frames']} | "
                   f"{r['time']:.3g} | {','.join(map(str, r['isos']))} | {r['predicted']:.1f} | "
                   f"{r['predicted_at_truth']:.1f} | {r['measured']:.1f} | {r['measured_min']:.1f} | "
                   f"{r['predicted_low']:.1f} | {r['low_at_truth']:.1f} | {r['low_measured']:.1f} | {saved} |")
    return "\n".join(out)


#: predicted SNR (dB) below which a case is left out of the summary: the merged estimate
#: of a signal that noisy is far from Gaussian (its mean squared error is set by a few
#: outliers), and no bracket measures the scene
GAUSSIAN_DB = 6.0


def _summary(rows: list[dict]) -> str:
    """Per camera, over the cases whose brackets are all predicted above GAUSSIAN_DB: the
    plan (ISO free) minus the best conventional bracket of the same time, at the worst
    case and at the 1st percentile of photosites, predicted and measured; the plan minus
    the plan at ISO 100; the prediction's error; and the time saved."""
    lines = []
    for camera in CAMERAS:
        mine = [r for r in rows if r["camera"] == camera]
        cases = {(r["scene"], r["budget"]) for r in mine}
        kept = [c for c in cases if all(r["predicted_at_truth"] >= GAUSSIAN_DB for r in mine
                                        if (r["scene"], r["budget"]) == c)]
        diff = {k: [] for k in ("predicted", "measured_min", "low_at_truth", "low_measured")}
        iso_pred, iso_meas, err, saved = [], [], [], []
        for case in kept:
            same = {r["bracket"]: r for r in mine if (r["scene"], r["budget"]) == case}
            free = same["plan, ISO free"]
            conv = [r for k, r in same.items() if k.startswith("conventional")]
            for k, v in diff.items():
                # a measured 1 % where the model predicts under GAUSSIAN_DB there is set by outliers
                if k != "low_measured" or all(r["low_at_truth"] >= GAUSSIAN_DB for r in same.values()):
                    v.append(free[k] - max(r[k] for r in conv))
            iso_pred.append(free["predicted"] - same["plan, ISO 100"]["predicted"])
            iso_meas.append(free["measured_min"] - same["plan, ISO 100"]["measured_min"])
            err += [r["measured_min"] - r["predicted_at_truth"] for r in same.values()]
            if free["time_saved"]:
                saved.append(free["time_saved"])
        if not kept:
            lines.append(f"- **{camera}**: no case above {GAUSSIAN_DB:g} dB")
            continue

        def span(v):
            return f"{min(v):+.1f} to {max(v):+.1f} dB (median {np.median(v):+.1f}; at least 0 in {sum(x >= -0.05 for x in v)} of {len(v)})"

        within = sum(abs(e) <= 1.0 for e in err)
        lines.append(
            f"- **{camera}** ({len(kept)} of {len(cases)} cases; the others have a bracket predicted below "
            f"{GAUSSIAN_DB:g} dB). The plan with the ISO free minus the best conventional bracket of the same time: "
            f"worst case as `plan` predicts it {span(diff['predicted'])}, measured (lowest bin) "
            f"{span(diff['measured_min'])}; 1st percentile of photosites at truth {span(diff['low_at_truth'])}, "
            f"measured {span(diff['low_measured'])} (where it is predicted above {GAUSSIAN_DB:g} dB at truth). Minus the plan at ISO 100: predicted {min(iso_pred):+.1f} to "
            f"{max(iso_pred):+.1f} dB, measured {min(iso_meas):+.1f} to {max(iso_meas):+.1f} dB. Lowest measured bin "
            f"minus predicted at truth within 1 dB in {within} of {len(err)} brackets (median {np.median(err):+.2f}, "
            f"range {min(err):+.1f} to {max(err):+.1f} dB). Time saved at equal SNR (predicted) "
            f"{min(saved):.1f}x to {max(saved):.1f}x.")
    return "\n".join(lines)


def main(quick: bool = False) -> str:
    if not SHARED.is_dir():
        return f"plan: skipped, no HDR scenes at {SHARED}"
    scenes = SCENES[:1] if quick else SCENES
    budgets = BUDGETS[:1] if quick else BUDGETS
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-plan-") as tmp:
        for s, scene in enumerate(scenes):
            for camera in CAMERAS:
                for budget in budgets:
                    work = Path(tmp) / f"{s}"
                    work.mkdir(exist_ok=True)
                    rows += run_case(work, scene, camera, budget, 10 * s + 1)
    seconds = [r["plan_seconds"] for r in rows if r["plan_seconds"]]
    text = "\n".join([
        "# Capture plans against conventional brackets" + (" (quick)" if quick else ""), "",
        (__doc__ or "").split("\n\n", 1)[1].split("\n\n")[0].replace("\n", " "), "",
        _summary(rows), "",
        f"`plan` took {min(seconds):.1f} to {max(seconds):.1f} s per run (metering merge and the programs).", "",
        _table(rows), ""])
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / ("plan_quick.md" if quick else "plan.md")).write_text(text)
    return text
