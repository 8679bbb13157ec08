"""hdrmerge-cli info"""
from __future__ import annotations

import json

import click

from hdrmerge_cli.cli.options import common_options, times_option_callback
from hdrmerge_cli.pipeline.info import bracket_info, format_info


@click.command("info")
@click.argument("images", nargs=-1, required=True, type=click.Path(exists=True, dir_okay=False))
@click.option("--json", "as_json", is_flag=True, help="Print the report as JSON instead of a table.")
@click.option("--times", callback=times_option_callback, metavar="T1,T2,...",
              help="Exposure times in seconds, in the order of IMAGES; overrides EXIF.")
@click.option("--times-file", type=click.Path(exists=True, dir_okay=False), help="Lines 'name seconds'.")
@click.option("--crf", metavar="CRF",
              help="Camera response of JPEG/TIFF/PNG input for the exposure estimates (as in merge); without it "
                   "a response is fitted on the bracket.")
@click.option("--snr", is_flag=True,
              help="Also predict the bracket's worst-case SNR after 'merge' and what a plan of the same total time "
                   "reaches ('plan'); merges the bracket, so it takes as long as a merge.")
@click.option("--profile", type=click.Path(exists=True, dir_okay=False),
              help="With --snr: the camera's noise at each ISO (calibrate-noise) [default: measured on the bracket].")
@common_options
def command(images, as_json, times, times_file, crf, snr, profile):
    """Describe frames IMAGES and whether they cover the scene as a bracket.

    Per frame: camera, exposure time, ISO, bit depth, black and white levels, and the
    fractions of clipped (at the white level) and dark (at or below black) samples.  For
    the bracket: whether every pixel is measured by some frame, and otherwise which
    exposure to add.  The report goes to stdout.

    The exposures are also measured on the frames (neighbour ratios of the pixels both
    expose well, chained from the frame whose label agrees best): the 'estimate' column;
    a label more than 1/3 EV from its estimate is a warning.

    With --snr, the bracket's predicted worst-case SNR (as 'plan' defines it) and what
    the best plan of the same total time reaches.
    """
    if times is not None and times_file:
        raise click.UsageError("give either --times or --times-file, not both")
    summary = bracket_info(images, times, times_file, crf)
    if profile and not snr:
        raise click.UsageError("--profile serves --snr; give both")
    if snr:
        from hdrmerge_cli.pipeline.plan import PlanOptions, bracket_snr

        summary["snr"] = bracket_snr(list(images), PlanOptions(profile=profile, crf=crf, times=times,
                                                                times_file=times_file, noise_cache=False))
    click.echo(json.dumps(summary, indent=1) if as_json else format_info(summary))
