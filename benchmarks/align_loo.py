"""Leave-one-out with registration on the real brackets: which alignment lets the merge
predict a left-out frame best (the table behind ``merge --align``'s default).

For every bracket of ``../shared/data/brackets`` and every interior frame ``k``: the
response is estimated once on all the frames (``estimate-crf`` defaults: the same for every
method, so only the geometry differs); the other frames are aligned by each method and
merged by our merge (:func:`hdrmerge_cli.api.merge_arrays`); the left-out frame's codes are
predicted through the response (``z = gamma(E h_k)``); the prediction is registered onto
the frame by one evaluator for every method (OpenCV only: phase correlation, then ECC with
an affine model on a three-level pyramid -- a merge on another frame's grid is not
penalised for where it sits, only for what it shows: doubled edges, blur, misplaced
detail); and the RMSE in code values is taken over the frame's pixels that are well
exposed (every channel in [10, 245]) and covered by every method's frames.

Methods: no alignment (``--align off``); ours, ``--align auto`` (the default) and
``--align translation``, and ``--align auto --deghost auto`` (what the ghost test, off by
default, costs or gains on these mostly still brackets); the peers' aligned frames merged by ours with ``--align off``:
OpenCV's AlignMTB (median threshold bitmaps, whole-pixel shifts; Ward 2003) and Hugin's
``align_image_stack`` (control points and its own remapping; Debian ``hugin-tools``,
skipped with a note when missing).  HDRMerge aligns RAW files only (the motion
benchmark runs it).

    python -m benchmarks.align_loo [--quick]   # results/align_loo.md
"""
from __future__ import annotations

import argparse
import json
import logging
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks import revision, write_result
from benchmarks.real_loo import BRACKETS, HIGH, IMAGE_SUFFIXES, LOW, predict_ours, rmse

RESULTS = Path(__file__).parent / "results"
OURS = {"none (--align off)": {"align": "off"}, "hdrmerge-cli --align auto (default)": {"align": "auto"},
        "hdrmerge-cli --align translation": {"align": "translation"},
        "hdrmerge-cli --align auto --deghost auto": {"align": "auto", "deghost": "auto"}}
MTB, HUGIN = "OpenCV AlignMTB", "Hugin align_image_stack"


def register(actual: np.ndarray, pred: np.ndarray) -> np.ndarray:
    """The affine warp (``(2, 3)``, frame pixel -> prediction pixel) taking a prediction
    onto the frame, both ``(H, W)`` float32 (log codes): phase correlation at 1/4 scale,
    then ECC (affine) at 1/4, 1/2 and full scale; the evaluator, the same for every method."""
    import cv2

    warp = None
    for f in (4, 2, 1):
        a, p = ((cv2.resize(x, None, fx=1 / f, fy=1 / f, interpolation=cv2.INTER_AREA) if f > 1 else x)
                for x in (actual, pred))
        if warp is None:
            (dx, dy), _ = cv2.phaseCorrelate(a.astype(np.float64), p.astype(np.float64))
            warp = np.float32([[1, 0, dx], [0, 1, dy]])
        else:
            warp[:, 2] *= 2
        try:
            _, warp = cv2.findTransformECC(a, p, warp, cv2.MOTION_AFFINE,
                                           (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50 if f > 1 else 20, 1e-5),
                                           None, 3)
        except cv2.error:  # ECC did not converge: the last level's warp stands
            pass
    return warp.astype(np.float64)


def align_mtb(codes: list[np.ndarray]) -> tuple[list[np.ndarray], np.ndarray]:
    """OpenCV's AlignMTB onto the middle frame (as ``process`` does; whole pixels): the
    shifted frames and where all of them have data, ``(H, W)`` bool."""
    import cv2

    mtb = cv2.createAlignMTB()
    grey = [cv2.cvtColor(c, cv2.COLOR_RGB2GRAY) for c in codes]
    pivot = len(codes) // 2
    h, w = grey[0].shape
    out, covered = [], np.ones((h, w), bool)
    for c, g in zip(codes, grey):
        dx, dy = mtb.calculateShift(grey[pivot], g)
        out.append(mtb.shiftMat(c, (dx, dy)))
        covered[:max(dy, 0)] = covered[h + min(dy, 0):] = False
        covered[:, :max(dx, 0)] = covered[:, w + min(dx, 0):] = False
    return out, covered


def align_hugin(paths: list[str], tmp: Path) -> tuple[list[np.ndarray], np.ndarray]:
    """Hugin's ``align_image_stack -a`` (frames in the order given): its remapped frames
    (RGB) and where all of them have data (alpha)."""
    import cv2

    for old in tmp.glob("hugin_*.tif"):
        old.unlink()
    subprocess.run([shutil.which("align_image_stack"), "--use-given-order", "-a", str(tmp / "hugin_"), *paths],
                   check=True, capture_output=True, timeout=1800)
    out, covered = [], None
    for j in range(len(paths)):
        bgra = cv2.imread(str(tmp / f"hugin_{j:04d}.tif"), cv2.IMREAD_UNCHANGED)
        out.append(np.ascontiguousarray(bgra[..., 2::-1]))
        covered = bgra[..., 3] > 0 if covered is None else covered & (bgra[..., 3] > 0)
    return out, covered


def merged(codes, times, crf, options=None) -> tuple[np.ndarray, np.ndarray]:
    """Our merge of ``codes`` with ``options`` (:func:`hdrmerge_cli.api.merge_arrays`'s; default
    ``--align off``): ``(E (H, W, 3) per second of exposure, where every frame has data
    (H, W) bool)``."""
    from hdrmerge_cli.api import merge_arrays
    from hdrmerge_cli.core.registration import covered_mask

    m = merge_arrays(codes, times, crf=crf, **(options or {"align": "off"}))
    h, w = codes[0].shape[:2]
    covered = np.ones((h, w), bool)
    alignment = m.bracket.alignment
    if alignment is not None and alignment.applied:
        for warp in alignment.warps:
            covered &= covered_mask(np.asarray(warp), h, w)
    return m.image / m.h_ref, covered


def run(quick: bool = False, brackets=None) -> tuple[list[dict], dict]:
    import cv2

    from hdrmerge_cli.io.frames import load_codes
    from hdrmerge_cli.io.profile import crf_from_json
    from hdrmerge_cli.pipeline.bracket import read_bracket
    from hdrmerge_cli.io.metadata import exposure_values

    logging.getLogger("hdrmerge_cli").setLevel(logging.ERROR)
    skipped = {HUGIN: None if shutil.which("align_image_stack") else "not installed (apt-get install hugin-tools)"}
    rows = []
    folders = sorted(p for p in BRACKETS.iterdir() if p.is_dir() and (not brackets or p.name in brackets))
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        for folder in folders:
            frames = read_bracket(sorted(str(p) for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES))
            order = np.argsort(exposure_values(frames), kind="stable")
            frames = [frames[i] for i in order]
            times = [float(t) for t in exposure_values(frames)]
            profile = tmp / "profile.json"
            subprocess.run([sys.executable, "-m", "hdrmerge_cli", "estimate-crf", *[f.path for f in frames], "-o",
                            str(profile), "--overwrite", "-q"], check=True, capture_output=True)
            crf = crf_from_json(json.loads(profile.read_text())["crf"])
            codes = [load_codes(f) for f in frames]
            interior = [len(frames) // 2] if quick else range(1, len(frames) - 1)
            for k in interior:
                keep = [j for j in range(len(frames)) if j != k]
                kc, kt = [codes[j] for j in keep], [times[j] for j in keep]
                actual = codes[k].astype(np.float32)
                h, w = actual.shape[:2]
                grey = np.log1p(actual.mean(axis=-1))
                found = {}
                for name, options in OURS.items():
                    t0 = time.perf_counter()
                    found[name] = (*merged(kc, kt, crf, options), time.perf_counter() - t0)
                peers = [(MTB, lambda: align_mtb(kc))]
                if skipped[HUGIN] is None:
                    peers.append((HUGIN, lambda: align_hugin([frames[j].path for j in keep], tmp)))
                for name, align in peers:
                    t0 = time.perf_counter()
                    aligned, covered = align()
                    found[name] = (merged(aligned, kt, crf)[0], covered, time.perf_counter() - t0)
                row = {"bracket": folder.name, "left_out": frames[k].name}
                mask = np.all((codes[k] >= LOW) & (codes[k] <= HIGH), axis=-1)
                preds = {}
                for name, (e, covered, seconds) in found.items():
                    pred = predict_ours(e, crf, times[k]).astype(np.float32)
                    warp = register(grey, np.log1p(pred.mean(axis=-1)))
                    flags = cv2.WARP_INVERSE_MAP
                    preds[name] = cv2.warpAffine(pred, warp.astype(np.float32), (w, h), flags=cv2.INTER_LINEAR | flags,
                                                 borderMode=cv2.BORDER_REPLICATE)
                    mask &= cv2.warpAffine(covered.view(np.uint8), warp.astype(np.float32), (w, h),
                                           flags=cv2.INTER_NEAREST | flags, borderValue=0) > 0
                    row[name + " s"] = seconds
                for name, pred in preds.items():
                    row[name] = rmse(pred, actual, mask)
                row["pixels"] = int(mask.sum())
                rows.append(row)
                print(f"{row['bracket']} {row['left_out']}: " + ", ".join(
                    f"{n}={row[n]:.2f}" for n in found), flush=True)
    return rows, skipped


def table(rows: list[dict], skipped: dict, seconds: float, rev: str | None = None) -> list[str]:
    methods = [n for n in rows[0] if n not in ("bracket", "left_out", "pixels") and not n.endswith(" s")]
    none = methods[0]
    lines = ["# Alignment by leave-one-out on the real brackets", "",
             f"`python -m benchmarks.align_loo` at revision {rev or revision()}; {seconds:.0f} s.  Protocol in the module "
             "docstring: the other frames aligned by each method and merged by ours, the left-out frame predicted "
             "through the response estimated on all frames, the prediction registered onto it (affine ECC, the same "
             f"evaluator for all), RMSE in code values over its pixels with every channel in [{LOW}, {HIGH}] "
             "covered by every method's frames.  Lower is better; **bold**: best of the row.", ""]
    if any(skipped.values()):
        lines += ["Skipped: " + "; ".join(f"{n} ({why})" for n, why in skipped.items() if why), ""]
    arr = np.array([[r[m] for m in methods] for r in rows])
    base = arr[:, 0]
    lines += ["| method | mean RMSE | geo-mean ratio to no alignment | better / worse than no alignment (> 1 %) "
              "| best of the row | mean seconds (align + merge) |", "|---|---|---|---|---|---|"]
    best = np.nanmin(arr, axis=1)
    for i, m in enumerate(methods):
        ratio = np.exp(np.nanmean(np.log(arr[:, i] / base)))
        better, worse = int(np.sum(arr[:, i] < base * 0.99)), int(np.sum(arr[:, i] > base * 1.01))
        secs = np.mean([r[m + " s"] for r in rows])
        lines.append(f"| {m} | {np.nanmean(arr[:, i]):.3f} | {ratio:.3f} | {better} / {worse} | "
                     f"{int(np.sum(arr[:, i] <= best))}/{len(rows)} | {secs:.2f} |")
    lines += ["", "## Every case", "", "| bracket | left out | pixels | " + " | ".join(methods) + " |",
              "|---|---|---|" + "---|" * len(methods)]
    for r, vals in zip(rows, arr):
        lines.append(f"| {r['bracket']} | {r['left_out']} | {r['pixels']} | " + " | ".join(
            ("**%.2f**" if v == np.nanmin(vals) else "%.2f") % v for v in vals) + " |")
    lines += ["", f"'{none}' is the same merge without any alignment."]
    return lines


def main(quick: bool = False) -> str:
    if not BRACKETS.is_dir():
        return f"align_loo: skipped ({BRACKETS} not found: the real brackets live in ../shared/data)"
    t0, rev = time.perf_counter(), revision()  # the code measured, before anything is committed meanwhile
    rows, skipped = run(quick)
    return write_result(RESULTS / f"align_loo{'_quick' if quick else ''}.md",
                        table(rows, skipped, time.perf_counter() - t0, rev))


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="the middle frame of each bracket only")
    ap.add_argument("brackets", nargs="*", help="only these brackets (folder names)")
    args = ap.parse_args()
    if args.brackets:
        rows, skipped = run(args.quick, args.brackets)
        print("\n".join(table(rows, skipped, 0.0)))
    else:
        print(main(args.quick))
