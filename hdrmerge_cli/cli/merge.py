"""hdrmerge-cli merge"""
from __future__ import annotations

import json
import logging
import sys
from pathlib import Path

import click

from hdrmerge_cli.cli.options import (
    BOUNDS_HELP, FiniteFloatRange, bounds_option_callback, common_options, emit, noise_option_callback, output_options,
    TIMES_HELP, parse_csv_list, times_or_estimate_callback, to_a_file
)
from hdrmerge_cli.core.choices import VARIANCE_FACTORS, WEIGHTINGS
from hdrmerge_cli.core.output_colorspace import COLORSPACES
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.io.times import ESTIMATE
from hdrmerge_cli.io.images import EXR_COMPRESSIONS
# the vocabularies only: the merge itself (NumPy, Numba, SciPy, OpenCV) is imported when it
# runs, so that --help and usage errors do not pay for it
from hdrmerge_cli.pipeline.options import (
    ALIGN_MODES, DEFAULT_GAP, DEGHOST_MODES, ESTIMATORS, EXTRA_CHANNELS, InputOptions, MergeOptions, MergeSettings,
    OutputOptions,
)

log = logging.getLogger("hdrmerge_cli")


@click.command("merge")
@click.argument("images", nargs=-1, type=click.Path(exists=True, dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(path_type=Path), callback=to_a_file,
              help="The EXR to write, or from RAW a floating-point DNG (*.dng: the merged mosaic, for raw editors; "
                   "its BaselineExposure, printed in the closing line and --json's dng_baseline_exposure_ev, makes "
                   "the default rendering show the --reference exposure: darktable ignores it, so raise darktable's "
                   "exposure by that many EV) (with --batch: the folder to write one EXR per bracket to).")
@click.option("--batch", "batch_dir", type=click.Path(exists=True, file_okay=False),
              help="Merge every bracket in this folder instead of IMAGES: frames are grouped by camera and image "
                   "layout, by the camera's bracketing tags (EXIF auto bracket, exposure compensation), by the "
                   "exposure sequence starting again, and by capture-time gaps (--gap) unless the frames across the "
                   "gap show the same scene (compared on thumbnails); files without an exposure time and the tool's "
                   "own previews are left out; each bracket's EXR is named "
                   "after its first frame.  A bad bracket is reported and skipped; the exit status is 1 if any "
                   "failed.  The output folder is left only if an output was written into it.")
@click.option("-j", "--jobs", default=1, show_default=True, type=click.IntRange(1, 256),
              help="--batch: brackets merged at once, each in its own process.")
@click.option("--gap", default=DEFAULT_GAP, show_default=True, type=FiniteFloatRange(0),
              help="--batch: largest time (s) from the end of one exposure to the start of the next in one "
                   "bracket; frames farther apart stay together only when they show the same scene.")
@click.option("--scheduler", metavar="ADDRESS",
              help="--batch: run on the Dask distributed scheduler at ADDRESS (e.g. tcp://host:8786), one task per "
                   "bracket; inputs and outputs must be on storage the workers share.")
@click.option("--skip-existing", is_flag=True,
              help="--batch: skip brackets whose EXR exists and is newer than all their frames.")
@click.option("--dry-run", is_flag=True,
              help="--batch: list the brackets, their outputs and why each was cut from the frames before it; "
                   "merge nothing.")
@click.option("--profile-out", type=click.Path(dir_okay=False, path_type=Path),
              help="Where to write the camera profile JSON used [default: OUTPUT with .profile.json].")
@click.option("--weights", type=click.Choice(["auto", *sorted(WEIGHTINGS)]), default="auto", show_default=True,
              help="Weighting function of (7): classical triangle, mann, deneve, gaussian, uniform; the paper's "
                   "probabilistic (32), direct (33), optimal (29), bounded (unknown noise parameters). auto: uniform "
                   "with the ml estimator, triangle with log; the measured winners.")
@click.option("--crf", metavar="CRF",
              help="Camera response of JPEG/TIFF/PNG input: linear, srgb, gamma:G, a CSV table (z, linear) "
                   "or a profile JSON [default: measured on the bracket, as estimate-crf does, or read from the "
                   "response cache; sRGB with a warning where the bracket cannot pin it].  RAW input is linear.")
@click.option("--times", callback=times_or_estimate_callback, metavar="T1,T2,...|estimate", help=TIMES_HELP)
@click.option("--times-file", type=click.Path(exists=True, dir_okay=False),
              help="File of lines 'name seconds' giving each image's exposure time (with --times estimate: the "
                   "labels that set the scale).")
@click.option("--reference", default="geomean", show_default=True, metavar="REF",
              help="Exposure (s) whose full-scale signal is 1.0 in the output: geomean, shortest, longest or seconds.")
@click.option("--colorspace", type=click.Choice(list(COLORSPACES)), default="rec709", show_default=True,
              help="Output colour space, stated in the EXR header (chromaticities and the Color Interop Forum's "
                   "colorInteropID): " + "; ".join(f"{k}: {v.description}" for k, v in COLORSPACES.items())
                   + ".  RAW converts through the camera matrix; images are taken as sRGB primaries (camera: "
                     "Rec.709, with a warning).  EXR only: a DNG keeps the camera's colour (a warning).")
@click.option("--cfa", is_flag=True, help="RAW: write the merged mosaic (channel Y, camera-native, no demosaic).")
@click.option("--half", is_flag=True, help="Write 16-bit half floats instead of 32-bit floats (EXR and DNG).")
@click.option("--compression", type=click.Choice(list(EXR_COMPRESSIONS)), default="auto", show_default=True,
              help="OpenEXR compression (EXR only: a DNG is always Deflate; a warning): "
                   + "; ".join(f"{k}: {v}" for k, v in EXR_COMPRESSIONS.items()) + ".")
@click.option("--no-cache", "no_cache", is_flag=True,
              help="Measure the noise on this bracket even if an earlier merge of the same camera and ISO stored it "
                   "in the per-camera cache ($HDRMERGE_CLI_CACHE_DIR, else $XDG_CACHE_HOME/hdrmerge-cli, else "
                   "~/.cache/hdrmerge-cli: noise.json; response.json holds images' responses, read back where a "
                   "bracket cannot pin its own), and store nothing there.")
@click.option("--extra-channels", callback=parse_csv_list, metavar="NAMES",
              help=f"Extra EXR channels, comma-separated: {', '.join(EXTRA_CHANNELS)}.")
@click.option("--noise", metavar="PARAMS", callback=noise_option_callback,
              help="Noise parameters of (17): sigma_o2=4,alpha=1,beta=0, or per channel 'R:... G:... B:...' "
                   "(code values of the linear signal; electrons for x), for every frame whatever its ISO.")
@click.option("--profile", type=click.Path(exists=True, dir_okay=False),
              help="Camera profile JSON (from calibrate-noise / estimate-crf): noise parameters and CRF; frames "
                   "of different ISOs each take their ISO's noise entry.")
@click.option("--variance", type=click.Choice(("auto",) + VARIANCE_FACTORS), default="auto", show_default=True,
              help="Variance factor sigma^-2 of (7): model (noise parameters, plus for images the codes' "
                   "quantisation through the response and a 1% model tolerance, or with the ML estimator the "
                   "variance beyond the model measured on the bracket), codes (quantisation and tolerance alone), "
                   "photon, none; auto = model for the ML estimator and for RAW when noise parameters are known, "
                   "codes for the log estimator of images with a non-linear response, photon otherwise.")
@click.option("--estimator", type=click.Choice(ESTIMATORS), default="auto", show_default=True,
              help="log = the paper's (7); ml = linear-domain inverse-variance with saturation censored; "
                   "auto = ml for RAW and linear images, and for camera-processed images whose exposure pairs the "
                   "noise model explains (a test at a 1e-3 false-alarm rate); log for those whose pairs show more "
                   "(JPEG processing).")
@click.option("--irls", type=click.IntRange(0, 50), metavar="N",
              help="Re-weight sigma^-2 at the current estimate up to N times (stops when it stops changing). "
                   "Default: 1 for the ML estimator with a noise model, else 0.")
@click.option("--k", "k", default=3.0, show_default=True, type=FiniteFloatRange(0.5, 10),
              help="Clipping margin of (47) in standard deviations (noise-model weights).")
@click.option("--lut", type=click.Path(exists=True, dir_okay=False),
              help="Weights table from 'weights-lut' (columns in exposure order) instead of --weights.")
@click.option("--bounds", metavar="BOUNDS", callback=bounds_option_callback, help=BOUNDS_HELP)
@click.option("--align", type=click.Choice(ALIGN_MODES), default="auto", show_default=True,
              help="Bring hand-held frames onto the middle exposure (OpenCV phase correlation and ECC on "
                   "exposure-normalised images, checked tile by tile so that a moving object cannot pull it): "
                   "translation, similarity (also rotation), auto (a rotation kept only where the tiles agree on "
                   "it and it beats translation; applied only when a frame is off by more than a quarter pixel), "
                   "off (a tripod bracket known to be still: no registration).  RAW moves by whole CFA periods "
                   "where that suffices, else each colour's sites are resampled.")
@click.option("--deghost", type=click.Choice(DEGHOST_MODES), default="off", show_default=True,
              help="Drop moving objects: per cell, a chi-square test of each frame against the reference (the "
                   "middle exposure) under the noise model, and the bounds a dark, clipped or (JPEG/TIFF/PNG) "
                   "near-white reading sets; "
                   "false-alarm rate 1e-3; regions feathered so that no seam shows; auto acts only when more than "
                   "0.2 % of a frame moves.  --extra-channels ghost shows where.")
@click.option("--crop", is_flag=True,
              help="Crop the EXR to the rectangle every aligned frame covers (as align_image_stack -C): the "
                   "borders a moved frame leaves, which fewer frames measure, are cut.  Nothing is cut when no "
                   "frame moved.")
@click.option("--preview", type=click.Path(dir_okay=False, path_type=Path),
              help="Also write a tone-mapped sRGB picture (Reinhard-Devlin; .jpg, .png or .tif) to look at.")
@click.option("--preview-size", default=2048, show_default=True, type=click.IntRange(0),
              help="Longest side of the preview in pixels (area-averaged; 0 = full size).")
@output_options
@common_options
def command(images, output, batch_dir, jobs, gap, scheduler, skip_existing, dry_run, profile_out, weights, crf, times,
            times_file, reference, colorspace, cfa, half, compression, no_cache, extra_channels, noise, profile, variance,
            estimator, irls, k, lut, bounds, align, deghost, crop, preview, preview_size, overwrite, as_json):
    """Merge a bracket IMAGES... (RAW, or JPEG/TIFF/PNG) into one scene-linear EXR.

    Frames are sorted by exposure (time x ISO); exposure times come from EXIF unless
    --times or --times-file is given.  Each label is checked against the frames (the
    ratio of neighbour frames on the pixels both expose well): a warning names a frame
    whose label is more than 1/3 EV off; --times estimate merges with the estimates.
    Output values are scene-linear: 1.0 is the
    clipping level of an exposure of --reference seconds (stated in the EXR header).
    Pixels clipped or dark in every frame get a finite bound (flagged in the 'clipped'
    channel: 1 saturated, -1 dark).  The camera profile used is written beside the EXR.

    With --batch DIR, every bracket of a folder is merged into -o OUTDIR (see --jobs,
    --scheduler, --skip-existing, --dry-run); the other options apply to each bracket.
    """
    if times is not None and times != ESTIMATE and times_file:
        raise click.UsageError("give either --times or --times-file, not both (--times estimate may take the labels "
                               "from --times-file)")
    opts = MergeOptions(  # how to merge, what the files are (text resolved as they are read), what to write
        MergeSettings(estimator=estimator, weights=weights, variance=variance, irls=irls, k=k, lut=lut, bounds=bounds,
                      align=align, deghost=deghost, reference=reference),
        InputOptions(crf=crf, profile=profile, noise=noise, times=times, times_file=times_file),
        OutputOptions(output=output, profile_out=profile_out, overwrite=overwrite, cfa=cfa, half=half,
                      extra_channels=extra_channels, colorspace=colorspace, compression=compression, preview=preview,
                      preview_size=preview_size, noise_cache=not no_cache, crop=crop),
    )
    given = _given(click.get_current_context())
    if preview is not None and str(preview).startswith("-"):  # `--preview --overwrite`: click took the option as the path
        raise click.BadParameter(f"needs a file name (got {preview}, an option?)", param_hint="--preview")
    if "preview_size" in given and preview is None:
        raise click.UsageError("--preview-size applies to --preview only")
    if crop and output is not None and Path(output).suffix.lower() == ".dng":
        raise click.BadParameter("a float DNG keeps the whole mosaic; crop an EXR output", param_hint="--crop")
    if crop and align == "off":
        raise click.UsageError("--crop cuts the borders an alignment leaves: it needs --align (not off)")
    if "ghost" in extra_channels and deghost == "off":
        log.warning("--extra-channels ghost without --deghost: the ghost channel is all zero")
    if batch_dir:
        return _batch(images, batch_dir, opts, jobs, gap, scheduler, skip_existing, dry_run, as_json)
    if not images:
        raise click.UsageError("give the bracket's IMAGES, or --batch DIR")
    if given & {"jobs", "gap", "scheduler", "skip_existing", "dry_run"}:
        raise click.UsageError("--jobs, --gap, --scheduler, --skip-existing and --dry-run apply to --batch only")
    if output.is_dir():
        raise click.UsageError(f"{output} is a folder; -o names the EXR or DNG to write (or use --batch DIR)")
    from hdrmerge_cli.pipeline.run import merge

    summary = merge(list(images), opts)
    written = [summary["output"], summary["profile"]] + ([summary["preview"]] if summary.get("preview") else [])
    said = f"wrote {', '.join(written[:-1])} and {written[-1]}"
    if "dng_baseline_exposure_ev" in summary:  # darktable 4.2 ignores the tag
        ev = summary["dng_baseline_exposure_ev"]
        said += (f"; the DNG's BaselineExposure is {ev:+.2f} EV: in an editor that ignores it (darktable) raise the "
                 f"exposure by {ev:.2f} EV to see the reference exposure")
    emit(summary, as_json, said)


def _given(ctx) -> set[str]:
    """Options set on the command line or in a --config file (not left at their default)."""
    sources = (click.core.ParameterSource.COMMANDLINE, click.core.ParameterSource.DEFAULT_MAP)
    return {p.name for p in ctx.command.params if ctx.get_parameter_source(p.name) in sources}


def _batch(images, batch_dir, opts, jobs, gap, scheduler, skip_existing, dry_run, as_json):
    from hdrmerge_cli.pipeline.batch import BatchOptions, describe, plan, run_batch, summarize

    if images:
        raise click.UsageError("give either IMAGES or --batch DIR, not both")
    if opts.inputs.times not in (None, ESTIMATE) or opts.io.profile_out is not None or opts.io.preview is not None:
        raise click.UsageError("--times, --profile-out and --preview name one bracket's files; with --batch use "
                               "--times-file, and the profiles are named after each EXR")
    if opts.io.output.exists() and not opts.io.output.is_dir():
        raise click.UsageError(f"{opts.io.output} is a file; with --batch, -o names the output folder")
    if scheduler and jobs != 1:
        log.warning("-j is ignored with --scheduler: the cluster's workers decide how many brackets run at once")
    if scheduler:  # cluster workers do not share our working directory: every file path absolute
        files = {"crf": opts.inputs.crf, "lut": opts.algorithm.lut, "times_file": opts.inputs.times_file,
                 "profile": opts.inputs.profile}
        opts = opts.replace(**{k: str(Path(v).resolve()) for k, v in files.items() if v and Path(v).is_file()})
    bopts = BatchOptions(batch_dir, opts.io.output, opts, jobs, gap, scheduler, skip_existing)
    entries = plan(bopts)
    if dry_run:
        summary = summarize(entries)
        click.echo(json.dumps(summary, indent=1) if as_json else describe(summary))
        return
    todo = sum(e["status"] == "planned" for e in entries)
    quiet = logging.getLogger("hdrmerge_cli").level > logging.WARNING
    with click.progressbar(length=todo, label="merging brackets", file=sys.stderr, hidden=quiet or todo == 0 or not sys.stderr.isatty()) as bar:
        summary = run_batch(bopts, entries, progress=bar.update)
    emit(summary, as_json, f"{summary['merged']} bracket(s) merged into {opts.io.output}, {summary['skipped']} skipped, "
                           f"{summary['failed']} failed")
    if summary["failed"]:
        raise HdrMergeError(f"{summary['failed']} of {len(summary['brackets'])} brackets failed (see above)")
