"""hdrmerge-cli calibrate-noise"""
from __future__ import annotations

from pathlib import Path

import click

from hdrmerge_cli.cli.options import common_options, emit, output_options, to_a_file
from hdrmerge_cli.pipeline.calibrate import CalibrateOptions, calibrate_noise


@click.command("calibrate-noise")
@click.argument("images", nargs=-1, type=click.Path(exists=True, dir_okay=False))
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), callback=to_a_file,
              help="The profile JSON to write [default: update --profile in place].")
@click.option("--darks", type=click.Path(exists=True, file_okay=False),
              help="Folder of dark frames (no light; at least two per ISO): read noise by photon transfer.")
@click.option("--flats", type=click.Path(exists=True, file_okay=False),
              help="Folder of flat fields, at least two frames at each of three or more exposure times: "
                   "gain and gain FPN by photon transfer (EMVA 1288).")
@click.option("--crf", metavar="CRF", help="Camera response of JPEG/TIFF/PNG input (as in merge; required for "
                                           "them unless --profile has one).")
@click.option("--profile", type=click.Path(exists=True, dir_okay=False),
              help="Existing profile: the new noise entries are merged into it (other ISOs and its CRF kept).")
@click.option("--plot", type=click.Path(dir_okay=False, path_type=Path),
              help="Draw noise variance against mean with the fitted curves (PNG, SVG or PDF).")
@click.option("--window", default=7, show_default=True, type=click.IntRange(3, 31), help="Local window size.")
@click.option("--bins", default=64, show_default=True, type=click.IntRange(4, 1024), help="Intensity bins.")
@output_options
@common_options
def command(images, output, darks, flats, crf, profile, plot, window, bins, overwrite, as_json):
    """Fit the sensor noise model Var[y] = sigma_o^2 + alpha x + beta x^2 (17) per ISO
    and channel.

    From photographs IMAGES (RAW, or JPEG/TIFF/PNG through --crf): the paper's local
    statistics in flat, unclipped windows and, for a bracket of a static scene, the
    exposure-normalised differences of consecutive frames (texture-free; frames that
    moved, whose differences exceed twice the flat windows' variance, fall back to the
    windows alone); photographs do not measure beta (scene texture and gain FPN look alike), so
    it is 0 unless --flats measure it.  From --darks/--flats:
    photon transfer (EMVA 1288), the reference when available.  The profile says which method gave each number; per frame
    the summary says whether it is photon- or offset-noise limited.  With two or more
    ISOs the profile also holds, per channel, the read noise split into its parts before
    the ISO amplifier (electrons^2) and after it (code values^2): sigma_o^2(ISO) =
    pre alpha(ISO) + post (Hasinoff et al. 2010).
    """
    summary = calibrate_noise(images, CalibrateOptions(output, darks, flats, crf, profile, plot, window, bins,
                                                       overwrite))
    emit(summary, as_json, f"wrote {summary['output']}")
