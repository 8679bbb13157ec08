"""hdrmerge-cli calibrate-noise"""
from __future__ import annotations

from pathlib import Path

import click

from hdrmerge_cli.cli.options import common_options, emit, output_options
from hdrmerge_cli.pipeline.calibrate import calibrate_noise


@click.command("calibrate-noise")
@click.argument("images", nargs=-1, required=True, type=click.Path(exists=True, dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="The profile JSON to write.")
@click.option("--crf", metavar="CRF", help="Camera response of JPEG/TIFF/PNG input (as in merge).")
@click.option("--window", default=7, show_default=True, type=click.IntRange(3, 31), help="Local window size.")
@click.option("--bins", default=64, show_default=True, type=click.IntRange(4, 1024), help="Intensity bins.")
@output_options
@common_options
def command(images, output, crf, window, bins, overwrite, as_json):
    """Fit the sensor noise model Var[y] = sigma_o^2 + alpha x + beta x^2 (17) per ISO
    and channel from ordinary photographs (RAW, or JPEG/TIFF/PNG through --crf): local
    statistics in flat, unclipped windows; beta is kept only when an F-test needs it.
    """
    summary = calibrate_noise(images, output, crf, window, bins, overwrite)
    emit(summary, as_json, f"wrote {output}")
