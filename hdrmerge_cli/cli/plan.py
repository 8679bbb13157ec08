"""hdrmerge-cli plan"""
from __future__ import annotations

import json
from pathlib import Path

import click

from hdrmerge_cli.cli.options import FiniteFloatRange, common_options, times_option_callback


def _shutter_speeds(ctx, param, value):
    return None if value is None else tuple(times_option_callback(ctx, param, value))


def _isos(ctx, param, value):
    if value is None:
        return None
    try:
        values = tuple(float(v) for v in str(value).replace(" ", "").split(",") if v)
    except ValueError:
        raise click.BadParameter(f"{value!r}: give ISO speeds separated by commas, e.g. 100,400,1600") from None
    if not values or any(not (1 <= v <= 1e6) for v in values):
        raise click.BadParameter(f"{value!r}: ISO speeds are numbers from 1 to 1000000")
    return values


@click.command("plan")
@click.argument("metering_frames", nargs=-1, type=click.Path(exists=True, dir_okay=False))
@click.option("--time", "budget", type=FiniteFloatRange(1e-6, 1e5), metavar="SECONDS",
              help="Total exposure time: the plan with the best worst-case SNR within it.")
@click.option("--min-snr", type=FiniteFloatRange(-60, 120), metavar="DB",
              help="The shortest plan whose worst-case SNR reaches DB (with --time: within that time too).")
@click.option("--frames", default=10, show_default=True, type=click.IntRange(1, 64), help="At most N frames.")
@click.option("--shutter-speeds", callback=_shutter_speeds, metavar="T1,T2,...",
              help="The camera's shutter times in seconds [default: the 1/3-stop series, 1/8000 to 30 s].")
@click.option("--isos", callback=_isos, metavar="ISO1,ISO2,...",
              help="The ISOs the plan may use, each calibrated in --profile [default: every ISO the profile "
                   "calibrates; without a profile, the metering frames' ISO only].")
@click.option("--lose-dark", default=1.0, show_default=True, type=FiniteFloatRange(0.0, 50.0), metavar="PCT",
              help="The darkest PCT % of each channel's photosites may be lost: the range the plan protects "
                   "starts above them.")
@click.option("--lose-bright", default=0.1, show_default=True, type=FiniteFloatRange(0.0, 50.0), metavar="PCT",
              help="The brightest PCT % of each channel's photosites may be lost (clip in every frame): the range "
                   "the plan protects ends below them.")
@click.option("--profile", type=click.Path(exists=True, dir_okay=False),
              help="Camera profile from calibrate-noise: the noise at each ISO [default: measured on the metering "
                   "frames, which then plans their ISO only].")
@click.option("--crf", metavar="CRF", help="Camera response of JPEG/TIFF/PNG metering frames (as in merge).")
@click.option("--times", callback=times_option_callback, metavar="T1,T2,...",
              help="Exposure times of the metering frames in seconds, in their order; overrides EXIF.")
@click.option("--plot", type=click.Path(dir_okay=False, path_type=Path),
              help="Draw the predicted SNR against irradiance, with the scene's histogram (PNG, SVG or PDF).")
@click.option("--gphoto2", "script", type=click.Path(dir_okay=False, path_type=Path),
              help="Write a shell script that shoots the plan with gphoto2.")
@click.option("--search-time", default=4.0, show_default=True, type=FiniteFloatRange(0.1, 3600),
              help="Seconds the solver may search each program before it returns the best plan found (with its "
                   "gap to the optimum).")
@click.option("--overwrite", is_flag=True, help="Replace existing --plot and --gphoto2 files.")
@click.option("--json", "as_json", is_flag=True, help="Print the plan as JSON instead of a table.")
@common_options
def command(metering_frames, budget, min_snr, frames, shutter_speeds, isos, lose_dark, lose_bright, profile, crf,
            times, plot, script, search_time, overwrite, as_json):
    """Plan the bracket to shoot: the exposure times and ISOs with the best worst-case
    SNR for the scene of METERING_FRAMES.

    The metering frames (one or a quick bracket of the scene, merged as 'merge' does)
    give the scene's irradiance; --profile gives the camera's noise at each ISO (17)
    (else it is measured on the metering frames).  With --time, the plan has the best
    worst-case SNR within that total exposure time; with --min-snr, it is the shortest
    that reaches that SNR (Hasinoff, Durand and Freeman 2010: a mixed-integer program
    over the number of frames of each setting, solved by HiGHS).  The worst case is the
    lowest SNR of the merged irradiance over the range the plan protects: each channel's
    photosites but the --lose-dark darkest and the --lose-bright brightest.  Of the plans
    within 1 dB of the best worst case, and never below the conventional brackets', the
    plan is the one of least mean error over that range.  Prints the frames, the plan
    compared with a plan at the lowest ISO and with conventional 1- and 2-EV brackets of
    the same time, and the SNR against irradiance.
    """
    from hdrmerge_cli.pipeline.plan import PlanOptions, check_options, format_plan, meter, solve, write_outputs

    if budget is None and min_snr is None:
        raise click.UsageError("give --time SECONDS, --min-snr DB or both")
    opts = PlanOptions(budget, min_snr, frames, shutter_speeds, isos, lose_dark, lose_bright, profile, crf, times,
                       search_time=search_time)
    check_options(opts)
    write_outputs(None, plot, script, overwrite, check_only=True)
    summary = solve(meter(list(metering_frames), opts), opts)
    write_outputs(summary, plot, script, overwrite)
    click.echo(json.dumps(summary, indent=1) if as_json else format_plan(summary))
