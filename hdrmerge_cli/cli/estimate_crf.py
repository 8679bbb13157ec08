"""hdrmerge-cli estimate-crf"""
from __future__ import annotations

from pathlib import Path

import click

from hdrmerge_cli.cli.options import (
    BOUNDS_HELP, SEED, FiniteFloatRange, bounds_option_callback, common_options, emit, output_options, TIMES_HELP,
    times_or_estimate_callback, to_a_file
)
from hdrmerge_cli.core.crf_estimate import CRF_ESTIMATORS
from hdrmerge_cli.core.crf_goossens2012 import (
    DEFAULT_ANCHOR, DEFAULT_COUPLING, DEFAULT_LAMBDA, DEFAULT_WEIGHTING, PAIR_WEIGHTS,
)
from hdrmerge_cli.core.weights import WEIGHTING_FUNCTIONS
from hdrmerge_cli.io.times import ESTIMATE
from hdrmerge_cli.pipeline.response import MAX_SMOOTHING, CRFOptions
from hdrmerge_cli.pipeline.run import estimate_crf


@click.command("estimate-crf")
@click.argument("images", nargs=-1, required=True, type=click.Path(exists=True, dir_okay=False))
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), callback=to_a_file,
              help="The profile JSON to write (default with --profile: that profile, updated in place).")
@click.option("--method", type=click.Choice(list(CRF_ESTIMATORS)), default="goossens", show_default=True,
              help="goossens: the paper's monotone QP (37) on comparagrams; debevec: Debevec-Malik 1997 least "
                   "squares; robertson: Robertson et al. 2003 iterations.")
@click.option("--lambda", "smoothing", type=FiniteFloatRange(0, MAX_SMOOTHING),
              help=f"Smoothness weight of g''. Default per method: goossens {DEFAULT_LAMBDA:g} (normalised: "
                   f"independent of pixel count and bit depth), debevec "
                   f"{CRF_ESTIMATORS['debevec'].smoothing:g} (Debevec-Malik's per-sample scale); robertson has none.")
@click.option("--coupling", type=FiniteFloatRange(0, MAX_SMOOTHING), default=DEFAULT_COUPLING, show_default=True,
              help="goossens: weight pulling the channels' curves to one shape where their own data are weak "
                   "(0: independent channels), so neutral shadows stay neutral.")
@click.option("--anchor", type=FiniteFloatRange(0, MAX_SMOOTHING), default=DEFAULT_ANCHOR, show_default=True,
              help="goossens: weight of a prior pulling the curve's slope towards sRGB's, which decides only where "
                   "the frames leave the response undetermined (codes no frame pair reaches, frames far apart); "
                   "0: none.")
@click.option("--samples", type=click.IntRange(min=0),
              help="Pixels used per channel, 0 for all; at least (codes - 1) / (frames - 1) (Debevec-Malik's "
                   "N (P - 1) >= Zmax - Zmin). Default: all for goossens and robertson "
                   f"(their cost hardly grows with it), {CRF_ESTIMATORS['debevec'].samples} for debevec.")
@click.option("--weighting", type=click.Choice(sorted(WEIGHTING_FUNCTIONS)),
              help=f"goossens: the weights w_j(z) of (36) [default: {DEFAULT_WEIGHTING}]; noise-model weights are "
                   "re-evaluated with each new CRF until g settles.")
@click.option("--pair-weight", type=click.Choice(PAIR_WEIGHTS), default="photon", show_default=True,
              help="goossens: the frame-pair factor of (37), for photon- or offset-noise-dominated cameras.")
@click.option("--bounds", metavar="BOUNDS", callback=bounds_option_callback,
              help="goossens with --weighting bounded: " + BOUNDS_HELP)
@click.option("--profile", type=click.Path(exists=True, dir_okay=False),
              help="An existing profile JSON whose CRF to replace (its noise model and other entries are kept).")
@click.option("--plot", type=click.Path(dir_okay=False, path_type=Path),
              help="Also draw g(z) per channel with each frame's data points (PNG/PDF/SVG).")
@click.option("--times", callback=times_or_estimate_callback, metavar="T1,T2,...|estimate",
              help=TIMES_HELP + "  The response is then fitted with the estimates (alternating, at most 3 rounds).")
@click.option("--times-file", type=click.Path(exists=True, dir_okay=False), help="Lines 'name seconds'.")
@click.option("--seed", default=0, show_default=True, type=SEED, help="Random seed of the pixel sampling.")
@click.option("--force", is_flag=True, help="Fit a CRF even for RAW (linear) input.")
@output_options
@common_options
def command(images, output, method, smoothing, coupling, anchor, samples, weighting, pair_weight, bounds, profile, plot, times,
            times_file, seed, force, overwrite, as_json):
    """Estimate the inverse camera response g(z) = log gamma^-1(z) of a bracket of
    JPEG/TIFF/PNG frames and write it to a profile JSON for 'merge --crf' or
    'merge --profile'.

    RAW input is linear and gets an identity CRF unless --force.
    """
    if times is not None and times != ESTIMATE and times_file:
        raise click.UsageError("give either --times or --times-file, not both (--times estimate may take the labels "
                               "from --times-file)")
    if output is None and profile is None:
        raise click.UsageError("give -o/--output, or --profile to update a profile in place")
    if method != "goossens" and (weighting or bounds or pair_weight != "photon" or coupling != DEFAULT_COUPLING
                                 or anchor != DEFAULT_ANCHOR):
        raise click.UsageError("--weighting, --pair-weight, --bounds, --coupling and --anchor apply to --method "
                               "goossens only")
    opts = CRFOptions(method, smoothing, samples, weighting, pair_weight, bounds, times, times_file, seed, force,
                      profile, plot, overwrite, coupling, anchor)
    summary = estimate_crf(images, output, opts)
    emit(summary, as_json, f"wrote {summary['output']}")
