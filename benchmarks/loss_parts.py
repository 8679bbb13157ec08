"""Where a left-out frame of ``real_loo`` is lost: the response or the merge.

Every interior frame of every shared real bracket (``../shared/data/brackets``) left out
as in :mod:`benchmarks.real_loo` (frames decimated the same way, RMSE in code values over
the left-out frame's pixels within [10, 245]), predicted by crossing four responses with
two merges on the same frames:

- responses: ours (``estimate-crf`` defaults: the goossens QP on pixel pairs), the
  goossens QP and our Debevec-Malik fed the frames' histogram rows
  (:func:`~hdrmerge_cli.core.crf_estimate.histogram_correspondences`, floors read), and
  colour-hdri's (Debevec-Malik on Grossberg-Nayar samples);
- merges: ours (the merge core's defaults for an image bracket: triangle weights, the log
  estimator (7), the ``codes`` variance) and colour-hdri's (its hat weight, a weighted mean
  in linear units), reproduced by :func:`hat_merge`.

Colour-hdri's response through its merge is colour-hdri itself.  A row's best response
under our merge, against ours, says how much of the loss is the response; our response
under the linear hat mean, how much is the merge.

    python -m benchmarks loss_parts [--quick]   # results/loss_parts.md (--quick: the middle frame only)
"""
from __future__ import annotations

import logging
import tempfile
import warnings
from pathlib import Path

import numpy as np

from benchmarks import write_result
from benchmarks.decisions import TUNED  # the brackets the merge's choices were tuned on

RESULTS = Path(__file__).parent / "results"
#: column -> (response, merge)
COLUMNS = {
    "ours": ("ours", "ours"),
    "ours, hat mean": ("ours", "hat"),
    "QP on rows": ("goossens rows", "ours"),
    "D-M on rows": ("debevec rows", "ours"),
    "colour-hdri response": ("colour", "ours"),
    "colour-hdri": ("colour", "hat"),
}


#: the hat's domain in colour-hdri's weighting_function_Debevec1997 (its defaults)
HAT_DOMAIN = (0.01, 0.99)


def hat_merge(codes: list[np.ndarray], exposures: np.ndarray, crf) -> np.ndarray:
    """colour-hdri's merge (image_stack_to_HDRI): ``sum_j w(v) g^-1(v) / t_j / sum_j w(v)``
    of ``v = z / 255``, with its hat ``w = v - l`` up to the middle of the domain ``(l, h)``
    (:data:`HAT_DOMAIN`), ``h - v`` above, 0 outside, divided by its largest value in each
    frame, and kept within ``(eps, 1)``; the shortest frame weighs 1 at ``v >= 0.5`` and the
    longest at ``v <= 0.5`` (so that every pixel has a weight); (H, W, 3) float64."""
    lo, hi = HAT_DOMAIN
    eps = np.finfo(np.float64).eps
    num = den = 0.0
    for j, (z, t) in enumerate(zip(codes, exposures)):
        v = np.clip(z / 255.0, eps, 1.0)
        w = np.maximum(np.where(v <= (lo + hi) / 2, v - lo, hi - v), 0.0)
        w = np.clip(w / w.max(), eps, 1.0)
        if j == 0:
            w[v >= 0.5] = 1.0
        if j == len(codes) - 1:
            w[v <= 0.5] = 1.0
        num = num + w * np.stack([crf.inverse(v[..., c], c) for c in range(3)], -1) / t
        den = den + w
    return num / np.maximum(den, 1e-12)


def responses(codes, exposures) -> tuple[dict, object]:
    """Each response of :data:`COLUMNS` by name, fitted on ``codes``, and colour-hdri's own
    result (:class:`benchmarks.peers.PeerResult`)."""
    from benchmarks import peers
    from hdrmerge_cli.core.crf import table_crf
    from hdrmerge_cli.core.crf_estimate import fit_response, histogram_correspondences

    log_h = np.log(exposures)
    rows = [r[:, None, :] for r in histogram_correspondences(codes, 256)]
    out = {"ours": fit_response(codes, log_h, 256).crf,
           "goossens rows": fit_response(rows, log_h, 256).crf,
           "debevec rows": fit_response(rows, log_h, 256, "debevec").crf}
    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        colour = peers.run_peer("colour-hdri", codes, list(exposures), Path(tmp))
    # run_peer made it non-decreasing and positive; the ramp makes it strictly increasing (invertible)
    out["colour"] = table_crf(colour.response + 1e-9 * np.arange(256))
    return out, colour


def run(quick: bool = False) -> list[dict]:
    from benchmarks import peers
    from benchmarks.core_merge import merge_frames
    from benchmarks.real_loo import BRACKETS, HIGH, LOW, load_bracket, predict_ours, rmse

    rows = []
    for folder in sorted(p for p in BRACKETS.iterdir() if p.is_dir()):
        frames, codes, exposures, _ = load_bracket(folder)
        for k in [len(frames) // 2] if quick else range(1, len(frames) - 1):
            keep = [j for j in range(len(frames)) if j != k]
            kc, ke = [codes[j] for j in keep], exposures[keep]
            actual = codes[k].astype(np.float64)
            mask = np.all((codes[k] >= LOW) & (codes[k] <= HIGH), axis=-1)
            row = {"bracket": folder.name, "left out": frames[k].name}
            try:
                crfs, colour = responses(kc, ke)
            except Exception as exc:  # noqa: BLE001 - a benchmark reports and goes on
                logging.warning("%s %s: %s", folder.name, frames[k].name, exc)
                continue
            for name, (response, merge) in COLUMNS.items():
                if (response, merge) == ("colour", "hat"):
                    pred = peers.predict_codes(colour, exposures[k])
                else:
                    crf = crfs[response]
                    e = (hat_merge(kc, ke, crf) if merge == "hat" else
                         merge_frames(kc, ke, crf, [0.0] * 3, [255.0] * 3, "triangle", None, "codes", "log",
                                      pattern=np.arange(3)[None, :])[0].astype(np.float64))
                    pred = predict_ours(e, crf, exposures[k])
                row[name] = rmse(pred, actual, mask)
            rows.append(row)
            print(f"{row['bracket']} {row['left out']}: " + ", ".join(f"{n}={row[n]:.2f}" for n in COLUMNS), flush=True)
    return rows


#: the columns that keep our merge and change the response
UNDER_OUR_MERGE = ("QP on rows", "D-M on rows", "colour-hdri response")


def where_lost(r: dict) -> str:
    """Against colour-hdri: nothing lost; else the response, where another response under our
    merge is at or below it; else the merge, where our response under its hat mean is; else
    both."""
    if r["ours"] <= r["colour-hdri"]:
        return ""
    if min(r[n] for n in UNDER_OUR_MERGE) <= r["colour-hdri"]:
        return "response"
    return "merge" if r["ours, hat mean"] <= r["colour-hdri"] else "both"


def table(rows: list[dict]) -> list[str]:
    names = list(COLUMNS)
    lines = ["# Where a left-out frame is lost: the response or the merge", "",
             "RMSE (code values) of each `real_loo` left-out frame predicted by a response (columns' first word) "
             "under a merge: *ours* = the goossens QP on pixel pairs (estimate-crf defaults) under our merge core "
             "(triangle, log estimator, `codes` variance); *hat mean* = colour-hdri's linear weighted mean; "
             "*on rows* = fitted on the frames' histogram rows; *colour-hdri response* = its Debevec-Malik response "
             "under our merge (benchmarks/loss_parts.py).  **Bold** = lowest of the row.  *lost by*: where ours is "
             "above colour-hdri, *response* if another response under our merge is at or below colour-hdri, else "
             "*merge* if our response under the hat mean is, else *both*.", "",
             "| bracket | left out | " + " | ".join(names) + " | lost by |", "|---|---|" + "---|" * (len(names) + 1)]
    for r in rows:
        best = min(r[n] for n in names)
        lines.append(f"| {r['bracket']} | {r['left out']} | " + " | ".join(
            f"**{r[n]:.2f}**" if r[n] == best else f"{r[n]:.2f}" for n in names) + f" | {where_lost(r)} |")
    lines += ["", "| frames | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    for what, sel in (("all", lambda r: True), ("tuned on", lambda r: r["bracket"] in TUNED),
                      ("held apart", lambda r: r["bracket"] not in TUNED)):
        part = [r for r in rows if sel(r)]
        if part:
            lines.append(f"| {what} ({len(part)}): mean; at or below colour-hdri | " + " | ".join(
                f"{np.mean([r[n] for r in part]):.2f}; {sum(r[n] <= r['colour-hdri'] for r in part)}" for n in names)
                + " |")
    lost = [where_lost(r) for r in rows]
    lines += ["", "Frames above colour-hdri, lost by: " + ", ".join(
        f"{what} {lost.count(what)}" for what in ("response", "merge", "both")) + f" (of {len(rows)})."]
    return lines


def main(quick: bool = False) -> str:
    from benchmarks.real_loo import BRACKETS

    if not BRACKETS.is_dir():
        return f"loss_parts: skipped ({BRACKETS} not found: the real brackets live in ../shared/data)"
    return write_result(RESULTS / f"loss_parts{'_quick' if quick else ''}.md", table(run(quick)))


if __name__ == "__main__":
    print(main())
