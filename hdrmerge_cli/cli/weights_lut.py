"""hdrmerge-cli weights-lut"""
from __future__ import annotations

from pathlib import Path

import click

from hdrmerge_cli.cli.options import common_options, emit, output_options, times_option_callback
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.weights import WEIGHTING_FUNCTIONS
from hdrmerge_cli.io.crfspec import resolve_crf
from hdrmerge_cli.pipeline.lut import weight_luts, write_luts
from hdrmerge_cli.pipeline.merge import choose_crf, exposure_values, read_bracket


@click.command("weights-lut")
@click.argument("images", nargs=-1, type=click.Path(exists=True, dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Table to write: .csv, .npy or .json.")
@click.option("--times", callback=times_option_callback, metavar="T1,T2,...",
              help="Exposure times in seconds (instead of a bracket IMAGES).")
@click.option("--weights", type=click.Choice(sorted(WEIGHTING_FUNCTIONS)), default="triangle", show_default=True,
              help="Weighting function.")
@click.option("--crf", metavar="CRF", help="linear, srgb, gamma:G, a CSV table or a profile JSON [default: linear].")
@click.option("--profile", type=click.Path(exists=True, dir_okay=False), help="Profile JSON (its CRF is used).")
@click.option("--bits", default=8, show_default=True, type=click.IntRange(1, 16),
              help="Code values 0..2^bits-1 (with --times; a bracket gives its own).")
@output_options
@common_options
def command(images, output, times, weights, crf, profile, bits, overwrite, as_json):
    """Tabulate a weighting function per exposure: one row per code value z, one column
    per exposure (and channel, for a per-channel CRF), with values in [0, 1]."""
    if bool(images) == (times is not None):
        raise click.UsageError("give either a bracket IMAGES... or --times")
    if crf and profile:
        raise click.UsageError("give either --crf or --profile, not both")
    spec = profile or crf
    if images:
        frames = read_bracket(list(images))
        exposures, n_codes = list(exposure_values(frames)), frames[0].n_codes
        curve = choose_crf(frames, spec)
        if frames[0].kind == "raw":
            raise HdrMergeError(f"{frames[0].path}: RAW brackets have per-file black levels; give --times and --bits")
    else:
        exposures, n_codes = sorted(times), 2**bits
        curve = resolve_crf(spec or "linear")
    table, labels = weight_luts(curve, n_codes, exposures, weights)
    meta = {"weights": weights, "crf": curve.describe(), "exposures": exposures, "n_codes": n_codes}
    write_luts(output, table, labels, meta, overwrite)
    emit(meta | {"output": str(output), "columns": labels}, as_json, f"wrote {output}")
