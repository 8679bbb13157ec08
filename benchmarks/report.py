"""``python -m benchmarks.report``: docs/benchmarks.md and the README's headline table,
generated from the result files in benchmarks/results/.

Every number in the project's documentation that a benchmark measured comes from here,
so each is written once (by the benchmark that measured it) and the pages cannot
contradict the results.  ``make bench`` runs this after the benchmarks.

- docs/benchmarks.md: each full-run result file (not the ``*_quick.md`` ones), its
  headings moved one level down, with the run's provenance (the revision it ran at)
  left out; the plots beside the results are linked.
- README.md: the headline table between ``<!-- headline:start -->`` and
  ``<!-- headline:end -->``, a few cells pulled from the result files by row and column
  name (a renamed row or column fails here, loudly, instead of going stale).

``--check`` writes nothing and exits 1 when either file differs from what it would write.
"""
from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
DOC = ROOT / "docs" / "benchmarks.md"
README = ROOT / "README.md"
START, END = "<!-- headline:start -->", "<!-- headline:end -->"

#: result files in the order the page shows them, with a one-line summary each
SECTIONS = (
    ("real_loo", "Real JPEG brackets: responses and merges by leave-one-out, against the peers"),
    ("decisions", "Automatic choices on the real photographs, against their stated answers"),
    ("loss_parts", "Where a left-out real frame is lost: the response or the merge"),
    ("align_loo", "Alignment on the real brackets by leave-one-out, against Hugin and OpenCV"),
    ("motion", "Alignment and ghost removal on randomised moving brackets"),
    ("cli_defaults", "The command line's defaults on simulated brackets, against the Cramer-Rao bound and the peers"),
    ("accuracy", "Every weighting and estimator against the Cramer-Rao bound, with speed"),
    ("fig19", "The paper's Fig. 19: a simulated scene through the CRF x^0.4"),
    ("fig17", "The paper's Fig. 17: SNR gain of each weighting over the triangle"),
    ("crf_dorf", "Camera response estimation on the DoRF curves"),
    ("noise_calibration", "Noise calibration (calibrate-noise) against known parameters"),
    ("speed", "Speed and memory: the merge core, end to end, other commands"),
    ("speed_whole", "Speed: whole commands against HDRMerge, Luminance HDR and OpenCV"),
    ("input_kinds", "What each program does with each kind of frame"),
    ("plan", "Capture plans against conventional brackets, predicted and measured"),
)

#: the command that writes a result file, where it is not ``python -m benchmarks NAME``
COMMANDS = {"fig17": "python -m benchmarks.fig17", "fig19": "python -m benchmarks.fig19",
            "speed_whole": "python -m benchmarks.speed --whole"}

#: plots written beside a result file
PLOTS = {"accuracy": ("accuracy_raw.png", "accuracy_jpeg.png"), "speed": ("speed.png",)}

#: text of a run's provenance, left out of the docs: "at revision c0ffee1-dirty"
_PROVENANCE = re.compile(r" at revision [0-9a-f]{7,40}(?:-dirty)?")
#: wording of a result file that speaks of the code's past, and what the docs say instead
_REWORDINGS = ((" (the previous default)", ""),)


# --- reading result tables ----------------------------------------------------------

def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def tables(name: str) -> list[tuple[list[str], list[list[str]]]]:
    """The Markdown tables of ``results/NAME.md``: (header, rows) each, in file order."""
    out, lines = [], (RESULTS / f"{name}.md").read_text().splitlines()
    i = 0
    while i < len(lines):
        if lines[i].startswith("|") and i + 1 < len(lines) and re.match(r"^\|[-| :]+\|$", lines[i + 1].strip()):
            header, rows, i = _cells(lines[i]), [], i + 2
            while i < len(lines) and lines[i].startswith("|"):
                rows.append(_cells(lines[i]))
                i += 1
            out.append((header, rows))
        else:
            i += 1
    return out


def cell(name: str, row: str, column: str, *, first_column: str | None = None, key: int = 0) -> str:
    """The cell of ``results/NAME.md`` in the row whose ``key``-th cell is ``row`` (bold
    marks ignored) and the column headed ``column``, from the first table that has both
    (and, if given, whose first header is ``first_column``)."""
    for header, rows in tables(name):
        if column not in header or (first_column and header[0] != first_column):
            continue
        for r in rows:
            if r[key].replace("**", "") == row:
                return r[header.index(column)].replace("**", "")
    raise KeyError(f"benchmarks/results/{name}.md: no row {row!r} with a column {column!r}")


def _num(text: str) -> float:
    return float(text.rstrip("%x").split()[0])


def _best(name: str, rows: dict[str, str], column: str, **kw) -> str:
    """The lowest of several rows' cells, with the label of the row that has it."""
    values = {label: _fmt2(cell(name, row, column, **kw)) for label, row in rows.items()}
    label = min(values, key=lambda k: _num(values[k]))
    return f"{values[label]} ({label})" if len(values) > 1 else values[label]


# --- the headline table -------------------------------------------------------------

PEERS = ("HDRMerge", "Luminance HDR", "pfstools", "Hugin", "OpenCV", "colour-hdri")


def headline() -> str:
    """The README's table: one row per measurement, hdrmerge-cli and each peer."""
    rl, al, cd, sw, cr, ik, mo = ("real_loo", "align_loo", "cli_defaults", "speed_whole", "crf_dorf",
                                  "input_kinds", "motion")
    mean = "mean RMSE"
    rows = []

    def row(what, link, ours, **peers):
        rows.append([what, ours] + [peers.get(p.replace(" ", "_").replace("-", "_"), "-") for p in PEERS]
                    + [f"[{link}](docs/benchmarks.md#{_slug(dict(SECTIONS)[link])})"])

    row("Real JPEG brackets: error predicting a left-out frame (code values; lower is better)", "real_loo",
        _fmt2(cell(rl, "merge (no option)", mean)),
        Luminance_HDR=_best(rl, {"Debevec": "luminance-debevec", "Robertson": "luminance-robertson"}, mean),
        pfstools=_fmt2(cell(rl, "pfstools", mean)),
        OpenCV=_best(rl, {"Debevec": "opencv-debevec", "Robertson": "opencv-robertson"}, mean),
        colour_hdri=_fmt2(cell(rl, "colour-hdri", mean)))
    row("... left-out frames where the error is at or below every peer's", "real_loo",
        cell(rl, "merge (no option)", "cases <= best peer"),
        colour_hdri=cell(rl, "colour-hdri", "cases <= best peer"))
    row("Real brackets aligned by each program, merged by ours: leave-one-out error", "align_loo",
        f"{_fmt2(cell(al, 'hdrmerge-cli --align auto (default)', mean))}",
        Hugin=_fmt2(cell(al, "Hugin align_image_stack", mean)),
        OpenCV=f"{_fmt2(cell(al, 'OpenCV AlignMTB', mean))} (AlignMTB)")
    row("Randomised hand-held brackets: cases with every frame within 0.2 px", "motion",
        cell(mo, "hdrmerge-cli --align auto", "shift <= 0.2 px"),
        OpenCV=f"{cell(mo, 'OpenCV AlignMTB (translation, integer px)', 'shift <= 0.2 px')} (AlignMTB)")
    exact = "below exact CRB, < 0.1 (mean)"
    row("Simulated 12-bit RAW: dB below the exact Cramer-Rao bound (lower is better)", "cli_defaults",
        cell(cd, "hdrmerge-cli defaults", exact),
        HDRMerge=cell(cd, "HDRMerge --no-align", exact) + " (`--no-align`)")
    tif = [t for t in tables(cd) if exact in t[0]][1]  # section B, the 8-bit TIFFs

    def tif_cell(method):
        return next(r for r in tif[1] if r[0] == method)[tif[0].index(exact)]
    row("Simulated 8-bit TIFF: dB below the bound (defaults; `--estimator ml`)", "cli_defaults",
        f"{tif_cell('hdrmerge-cli defaults')}; {tif_cell('hdrmerge-cli --estimator ml')}",
        Luminance_HDR=f"{tif_cell('Luminance HDR robertson')} (Robertson)",
        pfstools=tif_cell("pfstools (pfshdrcalibrate -f)"),
        OpenCV=f"{min(tif_cell('OpenCV MergeDebevec'), tif_cell('OpenCV MergeRobertson'), key=float)} (Robertson)")
    dorf = {r[1]: r for h, rs in tables(cr)[:1] for r in rs if r[0] == "moderate"}
    col = tables(cr)[0][0].index("median RMSE")
    row("Response recovered from 5 frames, 101 DoRF curves: median error of g", "crf_dorf",
        dorf["goossens"][col],
        OpenCV=min((f"{dorf[m][col]} ({m.split()[1]})" for m in ("opencv Debevec", "opencv Robertson")),
                   key=lambda s: float(s.split()[0])))
    wall, peak = "wall s", "peak MB"

    def sw_cell(case, tool, column):
        return next(r for r in tables(sw)[0][1] if r[0] == case and r[1] == tool)[tables(sw)[0][0].index(column)]
    first = "hdrmerge-cli merge: first merge (default options, empty cache)"
    for case, ours, peers in (
            ("24 MP x 3 DNG", first,
             {"HDRMerge": "HDRMerge -b 32 (float DNG)", "Luminance_HDR": "luminance-hdr-cli -s out.exr"}),
            ("24 MP x 3 DNG, 2 EV apart", first, {"HDRMerge": "HDRMerge -b 32 (float DNG)"}),
            ("24 MP x 3 DNG, hand-held", "hdrmerge-cli merge: first merge (default options: aligned)",
             {"HDRMerge": "HDRMerge -b 32 (float DNG; aligns by default)"}),
            ("4 x 0.4 MP DNG", first, {"HDRMerge": "HDRMerge -b 32 (float DNG)"}),
            ("3 x 12 MP 8-bit TIFF", "hdrmerge-cli merge: first merge (default options: response measured)",
             {"OpenCV": "OpenCV imread + MergeDebevec (known sRGB response) + EXR write",
              "Luminance_HDR": "luminance-hdr-cli -s out.exr"})):
        row(f"A camera's first merge, {case}: seconds / peak MB", "speed_whole",
            f"{sw_cell(case, ours, wall)} / {sw_cell(case, ours, peak)}",
            **{p: f"{sw_cell(case, t, wall)} / {sw_cell(case, t, peak)}" for p, t in peers.items()})
    kinds = dict(zip(tables(ik)[0][0], next(r for r in tables(ik)[0][1] if "kinds merged" in r[0])))
    row("Kinds of frame merged (grey, alpha, 16-bit, tiny, Bayer and linear DNG)", "input_kinds",
        kinds["hdrmerge-cli"].replace("**", ""),
        **{p.replace(" ", "_").replace("-", "_"): kinds[p].replace("**", "") for p in PEERS if p in kinds})
    head = ["measured", "hdrmerge-cli", *PEERS, "details"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def _fmt2(text: str) -> str:
    return f"{float(text):.2f}"


def _slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading."""
    s = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return s.replace(" ", "-")


# --- docs/benchmarks.md ---------------------------------------------------------------

INTRO = """\
# Benchmarks

Generated by `python -m benchmarks.report` from the result files in
[benchmarks/results/](../benchmarks/results/); do not edit by hand.  Each section is one
benchmark's last full run, with the command that writes it (`make bench` runs
`python -m benchmarks`, every benchmark but the figure reproductions and the
whole-command timing, and then this report; `python -m benchmarks [--quick] [NAME...]`
runs some).  Each benchmark's protocol is in its module's docstring, `benchmarks/NAME.py`.
Times are from a 2-core machine; ratios measured in the same run are what count.

The peer programs are Debian packages, skipped with a note when absent:
`apt-get install hdrmerge luminance-hdr pfstools hugin-tools` (HDRMerge, `luminance-hdr-cli`,
`pfshdrcalibrate`, Hugin's `align_image_stack`).  OpenCV and colour-hdri run in the same
process.  [benchmarks/peers.py](../benchmarks/peers.py) says how each peer is run and how its
response is read back.  Benchmarks that need the real brackets and HDR scenes of
`../shared/data` skip with a note without them.

Contents:

"""


def clean(text: str) -> str:
    text = _PROVENANCE.sub("", text)
    for old, new in _REWORDINGS:
        text = text.replace(old, new)
    return text


def benchmarks_page() -> str:
    parts = [INTRO]
    parts += [f"- [{title}](#{_slug(title)}) (`{name}`)\n" for name, title in SECTIONS]
    for name, title in SECTIONS:
        body = clean((RESULTS / f"{name}.md").read_text()).strip().splitlines()
        if body and body[0].startswith("# "):
            body = body[1:]  # the file's own title: the section's heading replaces it
        body = ["#" + line if line.startswith("#") else line for line in body]
        parts.append(f"\n## {title}\n\n`benchmarks/results/{name}.md`, written by `{COMMANDS.get(name, f'python -m benchmarks {name}')}`.\n\n")
        parts.append("\n".join(body).strip() + "\n")
        for png in PLOTS.get(name, ()):
            if (RESULTS / png).exists():
                parts.append(f"\n![{png}](../benchmarks/results/{png})\n")
    return "".join(parts)


def readme_with_headline(readme: str) -> str:
    if START not in readme or END not in readme:
        raise ValueError(f"README.md has no {START} ... {END} markers")
    head, rest = readme.split(START, 1)
    _, tail = rest.split(END, 1)
    return f"{head}{START}\n{headline()}\n{END}{tail}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.report", description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="write nothing; exit 1 if a file is out of date")
    args = ap.parse_args(argv)
    wanted = {DOC: benchmarks_page(), README: readme_with_headline(README.read_text())}
    stale = [p for p, text in wanted.items() if not p.exists() or p.read_text() != text]
    if args.check:
        for p in stale:
            print(f"{p.relative_to(ROOT)} is out of date: run python -m benchmarks.report", file=sys.stderr)
        return 1 if stale else 0
    for p in stale:
        p.write_text(wanted[p])
        print(f"wrote {p.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
