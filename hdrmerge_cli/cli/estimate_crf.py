"""hdrmerge-cli estimate-crf"""
from __future__ import annotations

from pathlib import Path

import click

from hdrmerge_cli.cli.options import common_options, emit, output_options, times_option_callback
from hdrmerge_cli.core.crf_estimate import CRF_ESTIMATORS
from hdrmerge_cli.pipeline.crf import estimate_crf


@click.command("estimate-crf")
@click.argument("images", nargs=-1, required=True, type=click.Path(exists=True, dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="The profile JSON to write.")
@click.option("--method", type=click.Choice(sorted(CRF_ESTIMATORS)), default="debevec", show_default=True,
              help="Estimation method.")
@click.option("--lambda", "smoothing", default=30.0, show_default=True, type=click.FloatRange(min=0),
              help="Smoothness weight of g''(z).")
@click.option("--samples", default=1000, show_default=True, type=click.IntRange(min=10),
              help="Pixels sampled per channel.")
@click.option("--times", callback=times_option_callback, metavar="T1,T2,...",
              help="Exposure times in seconds, in the order of IMAGES; overrides EXIF.")
@click.option("--times-file", type=click.Path(exists=True, dir_okay=False), help="Lines 'name seconds'.")
@click.option("--seed", default=0, show_default=True, type=int, help="Random seed of the pixel sampling.")
@click.option("--force", is_flag=True, help="Fit a CRF even for RAW (linear) input.")
@output_options
@common_options
def command(images, output, method, smoothing, samples, times, times_file, seed, force, overwrite, as_json):
    """Estimate the inverse camera response g(z) = log gamma^-1(z) of a bracket of
    JPEG/TIFF/PNG frames and write it to a profile JSON for 'merge --crf'.

    RAW input is linear and gets an identity CRF.
    """
    if times is not None and times_file:
        raise click.UsageError("give either --times or --times-file, not both")
    summary = estimate_crf(images, output, method, smoothing, samples, times, times_file, seed, force, overwrite)
    emit(summary, as_json, f"wrote {summary['output']}")
