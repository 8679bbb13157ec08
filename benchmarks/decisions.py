"""Every automatic choice of a default merge on the shared real photographs, against the
answer their sources state.

- **Labels and order**: each real bracket (``../shared/data/brackets``, and the brackets of
  ``../shared/data/folders``) merged with default options and with ``--crf srgb``; every
  label there is the published time or the camera's EXIF, so a frame called mislabelled is
  a false alarm unless the frames contradict its label (a blamed bracket's unblamed frame
  nearest the blamed ones is left out and predicted by merges with the labels and with
  ``--times estimate``), and an exit status other than 0 is a refusal.  Two simulated
  brackets check the other side: a frame whose label is 1 EV off must be named, and one
  whose four shortest frames read black must merge.
- **Grouping**: ``merge --batch --dry-run`` on the two real folders and on every bracket with
  EXIF times linked into one folder, against the brackets the data's README states.
- **Leave-one-out**: on the brackets the decisions were tuned on and on two more, the
  plain ``merge`` (no option; ``--align off``) with the middle frame left out, its codes
  predicted through the response the profile records, against every installed peer of
  benchmarks.peers on the same frames, RMSE in code values over the left-out frame's
  pixels within [10, 245].

The rules were tuned on the brackets marked *tuned* (the film scan for the floor of the
evidence; the two folders and the EOS 350D's three auto-bracket sequences for the
grouping); the others are reported apart, as what generalises.

    python -m benchmarks decisions [--quick]      # results/decisions.md
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

from benchmarks import write_result

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
RESULTS = Path(__file__).parent / "results"
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")
#: the brackets and folders the rules were tuned on
TUNED = {"memorial_film_scan_png", "eos350d_lamps_night_jpg", "handshot_three_brackets", "rx100m6_autobracket"}
#: the folders' brackets as their README states them (file-name prefixes, or file lists)
FOLDER_BRACKETS = {
    "handshot_three_brackets": [["fro_IMG_2600.jpg", "fro_IMG_2601.jpg", "fro_IMG_2602.jpg"],
                                [f"shop_img{k:02d}.JPG" for k in range(7, 15)],
                                [f"bld_img{k:02d}.JPG" for k in (1, 6, 7, 8, 9, 10, 11, 12, 13)]],
    "rx100m6_autobracket": [[f"DSC0{k}.JPG" for k in range(8196, 8201)], [f"DSC0{k}.JPG" for k in range(8201, 8206)]],
}


def _cli(*args, env=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "hdrmerge_cli", *map(str, args)], capture_output=True, text=True,
                          env=env)


def _brackets() -> list[tuple[str, list[str], list[str]]]:
    """(name, frame paths, extra merge arguments) of every real bracket."""
    out = []
    for d in sorted(p for p in (SHARED / "brackets").iterdir() if p.is_dir()):
        times = d / "exposure_times_seconds.txt"
        paths = sorted(str(p) for p in d.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        out.append((d.name, paths, ["--times-file", str(times)] if times.exists() else []))
    for folder, groups in FOLDER_BRACKETS.items():
        for g in groups:
            out.append((f"{folder}/{g[0].split('_')[0] if '_' in g[0] else g[0][:8]}",
                        [str(SHARED / "folders" / folder / n) for n in g], []))
    return out


def label_rows(quick: bool) -> list[dict]:
    """One row per real bracket and response option: frames, refusal, frames blamed."""
    rows = []
    for name, paths, extra in _brackets():
        for crf in ([], ["--crf", "srgb"]):
            with tempfile.TemporaryDirectory() as tmp:
                env = dict(os.environ, HDRMERGE_CLI_CACHE_DIR=f"{tmp}/cache")
                t = time.perf_counter()
                p = _cli("merge", *paths, *extra, *crf, "-o", f"{tmp}/m.exr", "--json", "-q", env=env)
                seconds = time.perf_counter() - t
            blamed = []
            if p.returncode == 0:
                frames = (json.loads(p.stdout).get("exposure_check") or {}).get("frames", [])
                blamed = [f["name"] for f in frames if f["mislabelled"]]
            rows.append({"bracket": name, "response": "srgb" if crf else "measured", "frames": len(paths),
                         "refused": p.returncode != 0, "blamed": blamed, "seconds": seconds,
                         "error": p.stderr.strip().splitlines()[-1] if p.returncode else ""})
            if quick:
                break
    return rows


def blame_check(name: str, paths: list[str], extra: list[str], blamed: list[str]) -> dict:
    """A blame weighed by the frames themselves: the unblamed frame nearest in exposure to the
    blamed ones is left out, the rest merged with their labels and with ``--times estimate``,
    and the left-out frame's codes predicted through each merge's response (RMSE in code
    values over its pixels within [10, 245]).  A lower error with the estimates says the
    frames contradict the labels; otherwise the blame is a false alarm."""
    from benchmarks.real_loo import LOW, HIGH, predict_ours, rmse
    from hdrmerge_cli.io.frames import load_codes
    from hdrmerge_cli.io.images import read_exr
    from hdrmerge_cli.io.metadata import exposure_values
    from hdrmerge_cli.io.profile import crf_from_json
    from hdrmerge_cli.pipeline.bracket import read_bracket

    frames = read_bracket(paths, None, extra[1] if extra else None)
    h = exposure_values(frames)
    bad = [j for j, f in enumerate(frames) if f.name in blamed]
    k = min((j for j in range(len(frames)) if j not in bad),
            key=lambda j: min(abs(np.log(h[j] / h[i])) for i in bad))
    codes = load_codes(frames[k]).astype(np.float64)
    mask = np.all((codes >= LOW) & (codes <= HIGH), axis=-1)
    keep = [frames[j] for j in range(len(frames)) if j != k]
    row = {"bracket": name, "left_out": frames[k].name}
    with tempfile.TemporaryDirectory() as tmp:
        Path(tmp, "t.txt").write_text("\n".join(f"{f.name} {f.exposure_time!r}" for f in keep))
        env = dict(os.environ, HDRMERGE_CLI_CACHE_DIR=f"{tmp}/cache")
        for what, more in (("labels", []), ("estimates", ["--times", "estimate"])):
            _cli("merge", *[f.path for f in keep], "--times-file", f"{tmp}/t.txt", *more, "-o", f"{tmp}/p.exr",
                 "--overwrite", "-q", env=env).check_returncode()
            pixels, header = read_exr(f"{tmp}/p.exr")
            crf = crf_from_json(json.loads(Path(tmp, "p.profile.json").read_text())["crf"])
            e = pixels[..., :3].astype(np.float64) / float(header["hdrmerge:referenceExposure"])
            row[what] = rmse(predict_ours(e, crf, h[k]), codes, mask)
    return row


def simulated_rows() -> list[dict]:
    """A frame labelled 1 EV off must be named; a bracket whose shortest frames read black
    must merge with its labels."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, HDRMERGE_CLI_CACHE_DIR=f"{tmp}/cache")
        _cli("simulate", "-o", f"{tmp}/sim", "--format", "jpg", "--size", "384x256", "--frames", "5", "-q", env=env)
        from hdrmerge_cli.pipeline.bracket import read_bracket

        frames = read_bracket([str(p) for p in sorted(Path(tmp, "sim").glob("frame_*.jpg"))], None)
        sim = [Path(f.path) for f in frames]
        times = [f.exposure_time for f in frames]
        if times:
            wrong = list(times)
            wrong[1] *= 2.0
            p = _cli("merge", *sim, "--times", ",".join(repr(t) for t in wrong), "-o", f"{tmp}/w.exr", "--json",
                     "-q", env=env)
            named = [f["name"] for f in json.loads(p.stdout)["exposure_check"]["frames"] if f["mislabelled"]] \
                if p.returncode == 0 else []
            rows.append({"case": "simulated JPEG, frame 2 labelled 1 EV long", "expected": sim[1].name,
                         "got": ", ".join(named) or "none", "right": named == [sim[1].name]})
        paths, ts = black_frames_bracket(Path(tmp))
        p = _cli("merge", *paths, "--times", ",".join(repr(t) for t in ts), "-o", f"{tmp}/b.exr", "-q", env=env)
        rows.append({"case": "simulated phone bracket, 4 shortest frames black", "expected": "merged",
                     "got": "merged" if p.returncode == 0 else f"refused: {p.stderr.strip()[:90]}",
                     "right": p.returncode == 0})
    return rows


def black_frames_bracket(folder: Path, shape=(240, 320), seed: int = 5) -> tuple[list[str], list[float]]:
    """A phone-like 8-bit bracket, 1/4000 s to 8 s in 10 JPEGs, whose four shortest frames
    read black (mean codes 1-3), their noise falling frame to frame as noise reduction makes
    it (so each black frame reads darker than the one before): the paths and the times."""
    import cv2

    rng = np.random.default_rng(seed)
    e = np.clip(np.exp(cv2.GaussianBlur(rng.standard_normal(shape), (0, 0), 3) * 4), 0, None)
    e = np.clip(e / np.percentile(e, 99.9), 0, 4)
    times = [1 / 4000, 1 / 2000, 1 / 1000, 1 / 500, 1 / 125, 1 / 30, 1 / 8, 1 / 2, 2, 8]
    noise = [0.002, 0.0012, 0.0006, 0.0004] + [0.0004] * 6
    paths = []
    for k, (t, sd) in enumerate(zip(times, noise)):
        x = np.clip(e * t / 2.5 + rng.normal(0, sd, e.shape), 0, 1)
        z = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
        paths.append(str(folder / f"f{k}.jpg"))
        cv2.imwrite(paths[-1], np.repeat(np.rint(255 * z).astype(np.uint8)[..., None], 3, -1))
    return paths, times


def grouping_rows() -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for folder, want in FOLDER_BRACKETS.items():
            got = [sorted(Path(p).name for p in g) for g in _groups(SHARED / "folders" / folder, tmp)]
            want = [sorted(g) for g in want]
            whole = sum(g in got for g in want)
            joined = sum(any(set(g) < set(h) for h in got) for g in want)
            rows.append({"folder": folder, "groups": [len(g) for g in got], "expected": len(want), "whole": whole,
                         "joined": joined})
        shoot = Path(tmp, "all")
        shoot.mkdir()
        want = []
        for name, paths, extra in _brackets():
            if extra or "/" in name:  # EXIF-timed shared brackets only
                continue
            want.append(sorted(str(Path(p).resolve()) for p in paths))
            for p in paths:
                (shoot / f"{name}__{Path(p).name}").symlink_to(p)
        got = [sorted(str(Path(p).resolve()) for p in g) for g in _groups(shoot, tmp)]
        rows.append({"folder": "every EXIF bracket in one folder", "groups": [len(g) for g in got],
                     "expected": len(want), "whole": sum(g in got for g in want), "joined": 0})
    return rows


def _groups(folder: Path, tmp: str) -> list[list[str]]:
    """The frames' paths of each bracket ``merge --batch --dry-run`` finds in ``folder``."""
    p = _cli("merge", "--batch", folder, "-o", f"{tmp}/out", "--dry-run", "--json")
    return [e["frames"] for e in json.loads(p.stdout)["brackets"]]


def _left_out_errors(frames, keep: list[int], k: int, times: bool, codes, h, step: int, mask, names) -> dict:
    """Frame ``k`` predicted from a plain merge of frames ``keep`` (``times``: their times
    given on the command line) and from each peer of ``names`` on the same frames' decimated
    ``codes``: RMSE in code values over ``mask``, keyed "merge (no option)" and by peer."""
    from benchmarks import peers
    from benchmarks.real_loo import predict_ours, rmse
    from hdrmerge_cli.io.images import read_exr
    from hdrmerge_cli.io.profile import crf_from_json

    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, HDRMERGE_CLI_CACHE_DIR=f"{tmp}/cache")
        args = [frames[j].path for j in keep]
        if times:
            args += ["--times", ",".join(repr(frames[j].exposure_time) for j in keep)]
        _cli("merge", *args, "-o", f"{tmp}/p.exr", "-q", "--align", "off", env=env).check_returncode()
        pixels, header = read_exr(f"{tmp}/p.exr")
        crf = crf_from_json(json.loads(Path(tmp, "p.profile.json").read_text())["crf"])
        e = pixels[::step, ::step, :3].astype(np.float64) / float(header["hdrmerge:referenceExposure"])
        out["merge (no option)"] = rmse(predict_ours(e, crf, h[k]), codes[k].astype(np.float64), mask)
        for peer in names:
            res = peers.run_peer(peer, [codes[j] for j in keep], list(h[keep]), Path(tmp, peer))
            out[peer] = rmse(peers.predict_codes(res, h[k]), codes[k].astype(np.float64), mask)
    return out


def loo_rows(quick: bool) -> list[dict]:
    """The middle frame left out, plain merge against the peers (benchmarks.peers)."""
    from benchmarks import peers
    from benchmarks.real_loo import LOW, HIGH
    from hdrmerge_cli.io.frames import load_codes
    from hdrmerge_cli.io.metadata import exposure_values
    from hdrmerge_cli.pipeline.bracket import read_bracket

    available = peers.available()
    names = [n for n in peers.PEERS if available[n] is None]
    wanted = {"memorial_film_scan_png", "handshot_three_brackets/fro", "handshot_three_brackets/shop",
              "eos350d_lamps_night_jpg", "stack_jpg"}
    rows = []
    for name, paths, extra in _brackets():
        if name not in wanted or (quick and name != "handshot_three_brackets/fro"):
            continue
        frames = read_bracket(paths, None, extra[1] if extra else None)
        h = exposure_values(frames)
        k = len(frames) // 2
        step = max(1, int(np.ceil(np.sqrt(frames[0].width * frames[0].height / 400_000))))
        codes = [np.ascontiguousarray(load_codes(f)[::step, ::step]) for f in frames]
        mask = np.all((codes[k] >= LOW) & (codes[k] <= HIGH), axis=-1)
        keep = [j for j in range(len(frames)) if j != k]
        row = {"bracket": name, "left_out": frames[k].name}
        row |= _left_out_errors(frames, keep, k, bool(extra), codes, h, step, mask, names)
        rows.append(row)
    return rows, names, available


def pair_rows(quick: bool) -> list[dict]:
    """Two frames about 6 EV apart (the pair of each bracket spanning 4.5-7.5 EV nearest 6,
    the frame nearest their middle in EV left out), merged with no option: the response
    measured on two frames that share few or no well-exposed pixels, the frame between
    them predicted (RMSE, code values) against colour-hdri and OpenCV's Debevec on the same
    two frames.  None of these pairs was tuned on (the rule they test, histogram rows read
    above each frame's floor only, was chosen on fro and checked here)."""
    from benchmarks import peers
    from benchmarks.real_loo import LOW, HIGH
    from hdrmerge_cli.io.frames import load_codes
    from hdrmerge_cli.io.metadata import exposure_values
    from hdrmerge_cli.pipeline.bracket import read_bracket

    names = [n for n in ("colour-hdri", "opencv-debevec") if peers.available()[n] is None]
    rows = []
    for name, paths, extra in _brackets():
        if quick and name != "handshot_three_brackets/fro":
            continue
        frames = read_bracket(paths, None, extra[1] if extra else None)
        if frames[0].kind != "image" or frames[0].channels != 3:
            continue
        h = exposure_values(frames)
        ev = np.log2(h)
        spans = [(abs(ev[j] - ev[i] - 6), i, j) for i in range(len(frames)) for j in range(i + 2, len(frames))
                 if 4.5 <= ev[j] - ev[i] <= 7.5]
        if not spans:
            continue
        _, i, j = min(spans)
        m = min(range(i + 1, j), key=lambda q: abs(ev[q] - (ev[i] + ev[j]) / 2))
        step = max(1, int(np.ceil(np.sqrt(frames[0].width * frames[0].height / 400_000))))
        codes = [np.ascontiguousarray(load_codes(f)[::step, ::step]) for f in frames]
        mask = np.all((codes[m] >= LOW) & (codes[m] <= HIGH), axis=-1)
        row = {"bracket": name, "pair": f"{frames[i].name}, {frames[j].name} ({ev[j] - ev[i]:.1f} EV)",
               "left_out": frames[m].name}
        row |= _left_out_errors(frames, [i, j], m, bool(extra), codes, h, step, mask, names)
        rows.append(row)
    return rows, names


def _error_table(title: str, keys: list[str], heads: list[str], rows: list[dict], names: list[str]) -> list[str]:
    """A Markdown section of left-out errors: the ``keys`` columns (headed ``heads``), ours, then each peer."""
    cols = heads + ["merge (no option)"] + names
    lines = ["", f"## {title} (RMSE, code values)", "", "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        lines.append("| " + " | ".join([str(r[k]) for k in keys] + [f"{r[n]:.2f}" for n in ["merge (no option)"] + names])
                     + " |")
    return lines


def main(quick: bool = False) -> str:
    if not SHARED.is_dir():
        return f"decisions: skipped (no shared data at {SHARED})"
    labels = label_rows(quick)
    lines = ["# Decisions on real photographs", "",
             "Every automatic choice of a default merge against the answer the data's sources state "
             "(benchmarks/decisions.py).  *tuned*: the rules were tuned on it; the others are held apart.", "",
             "## Labels and order", "",
             "Every label here is the published time or the camera's EXIF: a frame blamed is a false alarm unless "
             "the frames themselves contradict its label (the left-out check below), an exit status other than 0 "
             "a refusal.", "",
             "| bracket | set | response | frames | refused | frames blamed | seconds |", "|---|---|---|---|---|---|---|"]
    for r in labels:
        what = "tuned" if r["bracket"].split("/")[0] in TUNED else "held apart"
        lines.append(f"| {r['bracket']} | {what} | {r['response']} | {r['frames']} | "
                     f"{'yes: ' + r['error'][:80] if r['refused'] else 'no'} | "
                     f"{len(r['blamed'])}{' (' + ', '.join(r['blamed']) + ')' if r['blamed'] else ''} | "
                     f"{r['seconds']:.1f} |")
    for what in ("tuned", "held apart"):
        sel = [r for r in labels if (r["bracket"].split("/")[0] in TUNED) == (what == "tuned")]
        lines.append(f"\n{what}: {sum(len(r['blamed']) for r in sel)} frames blamed and "
                     f"{sum(r['refused'] for r in sel)} refusals over {len(sel)} merges.")
    checks = [blame_check(r["bracket"], *next((p, e) for n, p, e in _brackets() if n == r["bracket"]), r["blamed"])
              for r in labels if r["blamed"] and r["response"] == "measured"]
    if checks:
        lines += ["", "### Blames weighed by a left-out frame", "",
                  "The unblamed frame nearest the blamed ones left out, the rest merged with their labels and "
                  "with `--times estimate` (default response), its codes predicted (RMSE, code values); "
                  "a lower error with the estimates says the frames, not the rule, contradict the labels.", "",
                  "| bracket | left out | with the labels | with the estimates | the frames contradict the labels |",
                  "|---|---|---|---|---|"]
        lines += [f"| {c['bracket']} | {c['left_out']} | {c['labels']:.2f} | {c['estimates']:.2f} | "
                  f"{'yes' if c['estimates'] < c['labels'] else 'no: a false alarm'} |" for c in checks]
    lines += ["", "## Simulated checks", "", "| case | expected | got | right |", "|---|---|---|---|"]
    lines += [f"| {r['case']} | {r['expected']} | {r['got']} | {'yes' if r['right'] else 'no'} |"
              for r in simulated_rows()]
    lines += ["", "## Grouping (`merge --batch --dry-run`)", "",
              "| folder | groups found (frames each) | brackets expected | whole | joined to others |",
              "|---|---|---|---|---|"]
    lines += [f"| {r['folder']} | {r['groups']} | {r['expected']} | {r['whole']} | {r['joined']} |"
              for r in grouping_rows()]
    rows, names, available = loo_rows(quick)
    lines += _error_table("Leave-one-out, the middle frame", ["bracket", "left_out"], ["bracket", "left out"],
                          rows, names)
    pairs, pair_names = pair_rows(quick)
    lines += _error_table("Two frames about 6 EV apart, the frame between them predicted", ["bracket", "pair", "left_out"],
                          ["bracket", "the two frames", "left out"], pairs, pair_names)
    best = sum(r["merge (no option)"] <= min(r[n] for n in pair_names) for r in pairs)
    lines.append(f"\nmerge at or below every peer on {best} of {len(pairs)}; mean {np.mean([r['merge (no option)'] for r in pairs]):.2f}"
                 + "".join(f", {n} {np.mean([r[n] for r in pairs]):.2f}" for n in pair_names) + ".")
    skipped = [f"{n}: {why}" for n, why in available.items() if why]
    if skipped:
        lines.append("\nSkipped: " + "; ".join(skipped))
    return write_result(RESULTS / f"decisions{'_quick' if quick else ''}.md", lines)


if __name__ == "__main__":
    print(main("--quick" in sys.argv))
