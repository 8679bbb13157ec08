"""hdrmerge-cli weights-lut"""
from __future__ import annotations

from pathlib import Path

import click

import numpy as np

from hdrmerge_cli.cli.options import (
    BOUNDS_HELP, FiniteFloatRange, bounds_option_callback, common_options, emit, noise_option_callback, output_options,
    times_option_callback, to_a_file
)
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.weights import NOISE_MODEL_WEIGHTS, WEIGHTING_FUNCTIONS
from hdrmerge_cli.io.atomic import write_together
from hdrmerge_cli.io.crfspec import resolve_crf
from hdrmerge_cli.io.luts import luts_writer
from hdrmerge_cli.io.metadata import exposure_values
from hdrmerge_cli.io.noisespec import parse_bounds, per_channel
from hdrmerge_cli.io.plots import check_figure_path, figure_writer
from hdrmerge_cli.pipeline.bracket import choose_crf, read_bracket
from hdrmerge_cli.pipeline.choices import RAW_HAS_NO_LUT, prior_rate as prior_rate_of
from hdrmerge_cli.pipeline.lut import PRIOR_RATE_RANGE, check_luts, luts_figure, weight_luts
from hdrmerge_cli.pipeline.noise import resolve_noise


@click.command("weights-lut")
@click.argument("images", nargs=-1, type=click.Path(exists=True, dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=Path), callback=to_a_file,
              help="Table to write: .csv, .npy or .json.")
@click.option("--times", callback=times_option_callback, metavar="T1,T2,...",
              help="Exposure times in seconds (instead of a bracket IMAGES).")
@click.option("--weights", type=click.Choice(sorted(WEIGHTING_FUNCTIONS)), default="triangle", show_default=True,
              help="Weighting function.")
@click.option("--crf", metavar="CRF", help="linear, srgb, gamma:G, a CSV table or a profile JSON [default: linear].")
@click.option("--profile", type=click.Path(exists=True, dir_okay=False), help="Profile JSON (its CRF is used).")
@click.option("--bits", default=8, show_default=True, type=click.IntRange(2, 16),
              help="Code values 0..2^bits-1 (with --times; a bracket gives its own).")
@click.option("--noise", metavar="PARAMS", callback=noise_option_callback,
              help="Noise parameters of (17), as in merge (for the paper's weights).")
@click.option("--prior-rate", type=FiniteFloatRange(*PRIOR_RATE_RANGE),
              help="Mean of the exponential irradiance prior, code values per second [default: from the bracket, "
                   "or mid-grey at the middle exposure].")
@click.option("--k", "k", default=3.0, show_default=True, type=FiniteFloatRange(0.5, 10),
              help="Clipping margin of (47) in standard deviations.")
@click.option("--bounds", metavar="BOUNDS", callback=bounds_option_callback, help=BOUNDS_HELP)
@click.option("--plot", type=click.Path(dir_okay=False, path_type=Path), help="Also draw the curves (PNG/PDF/SVG, by suffix).")
@output_options
@common_options
def command(images, output, times, weights, crf, profile, bits, noise, prior_rate, k, bounds, plot, overwrite, as_json):
    """Tabulate a weighting function per exposure: one row per code value z, one column
    per exposure (and channel, for a per-channel CRF or noise), values in [0, 1].
    'merge --lut' reuses the table so batch runs skip rebuilding it."""
    if bool(images) == (times is not None):
        raise click.UsageError("give either a bracket IMAGES... or --times")
    if crf and profile:
        raise click.UsageError("give either --crf or --profile, not both")
    if plot:
        check_figure_path(plot, overwrite)
    spec = crf or profile
    if images:
        frames = read_bracket(list(images))
        if frames[0].kind == "raw":
            raise HdrMergeError(f"{frames[0].path}: {RAW_HAS_NO_LUT} (merge it without --lut)")
        exposures, n_codes = list(exposure_values(frames)), frames[0].n_codes
        curve = choose_crf(frames, spec)
        params = resolve_noise(frames, noise, profile, crf)
        prior = prior_rate or (prior_rate_of(frames, np.array(exposures), curve) if weights in NOISE_MODEL_WEIGHTS
                               else None)
        names = frames[0].channel_names
    else:
        exposures, n_codes = sorted(times), 2**bits
        curve = resolve_crf(spec or "linear")
        params = resolve_noise([], noise, profile, crf)
        prior = prior_rate
        per_rgb = (params and set(params) != {"*"}) or (curve.table is not None and curve.table.shape[0] == 3)
        names = ["R", "G", "B"] if per_rgb else ["*"]
    noise_list = per_channel(params, names) if params else None
    table, labels = weight_luts(curve, n_codes, exposures, weights, noise_list, prior, k,
                                parse_bounds(bounds) if bounds else None)
    check_luts(table, labels, weights, prior_rate if weights in NOISE_MODEL_WEIGHTS else None)
    meta = {"weights": weights, "crf": curve.describe(), "exposures": exposures, "n_codes": n_codes, "k": k}
    writers = [(output, luts_writer(output, table, labels, meta))]
    if plot:
        writers.append((plot, figure_writer(luts_figure(table, labels, f"{weights} weights, CRF {curve.describe()}"),
                                            plot)))
    write_together(writers, overwrite)
    emit(meta | {"output": str(output), "columns": labels, "plot": str(plot) if plot else None}, as_json,
         f"wrote {output}" + (f" and {plot}" if plot else ""))
