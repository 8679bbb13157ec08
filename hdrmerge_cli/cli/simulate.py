"""hdrmerge-cli simulate"""
from __future__ import annotations

from pathlib import Path

import click

from hdrmerge_cli.cli.options import (
    SEED, FiniteFloatRange, common_options, emit, output_options, times_option_callback, to_a_file
)
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.sensor import SensorModel
from hdrmerge_cli.io.noisespec import NOISE_RANGES
from hdrmerge_cli.pipeline.simulate import FORMATS, SimulateOptions, frame_isos, simulate


#: largest side of a simulated frame (JPEG's limit)
MAX_SIDE = 65500
#: range of --scale: wide enough for a scene in any unit, narrow enough not to overflow
SCALE_RANGE = (1e-12, 1e12)


#: ISOs a 16-bit EXIF field holds
ISO_RANGE = (1, 65535)


def _isos(ctx, param, value):
    """``--iso``: one ISO, or a comma list (one per --times entry)."""
    try:
        isos = [int(v) for v in str(value).split(",")]
    except ValueError:
        raise click.BadParameter(f"{value!r}: give an ISO or a comma list of ISOs, e.g. 100,400,1600") from None
    if not all(ISO_RANGE[0] <= i <= ISO_RANGE[1] for i in isos):
        raise click.BadParameter(f"{value}: each ISO must lie between {ISO_RANGE[0]} and {ISO_RANGE[1]} (a 16-bit "
                                 "EXIF field)")
    return isos[0] if len(isos) == 1 else isos


def _size(ctx, param, value):
    try:
        w, h = (int(v) for v in str(value).lower().split("x"))
        if not (2 <= w <= MAX_SIDE and 2 <= h <= MAX_SIDE):
            raise ValueError
    except ValueError:
        raise click.BadParameter(f"use WIDTHxHEIGHT, each 2 to {MAX_SIDE}, e.g. 768x512") from None
    return w, h


@click.command("simulate")
@click.option("-o", "--output", "output_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              callback=to_a_file,
              help="Folder for the frames, truth.exr and simulation.json.")
@click.option("--scene", default="builtin", show_default=True,
              help="'builtin' (procedural, ~19 stops), 'flat' (uniform, --scale electrons per second: flat-field "
                   "frames), 'dark' (no light: dark frames) or a scene-linear HDR image (EXR, Radiance .hdr, float "
                   "TIFF) whose values are photo-electrons per second; 8/16-bit images (JPEG, PNG...) are "
                   "display-referred and clipped, not scenes, and are refused.")
@click.option("--size", default="768x512", show_default=True, callback=_size, help="Size of the built-in scene.")
@click.option("--downscale", default=1, show_default=True, type=click.IntRange(1, 64),
              help="Average the scene over NxN blocks first.")
@click.option("--scale", default=1.0, show_default=True, type=FiniteFloatRange(*SCALE_RANGE),
              help="Multiply the scene (electrons per second per unit).")
@click.option("--frames", default=5, show_default=True, type=click.IntRange(1, 64),
              help="Number of exposures when --times is not given (chosen to cover the scene; for 'flat', "
                   "2 % to 90 % of saturation).")
@click.option("--repeat", default=1, show_default=True, type=click.IntRange(1, 64),
              help="Frames per exposure time (and its ISO; independent noise, the same fixed pattern), e.g. 2 "
                   "for photon-transfer pairs.")
@click.option("--times", callback=times_option_callback, metavar="T1,T2,...", help="Exposure times in seconds.")
@click.option("--format", "fmt", type=click.Choice(FORMATS), default="dng", show_default=True,
              help="DNG (Bayer RAW) or camera-processed JPEG/TIFF/PNG with EXIF.")
@click.option("--bits", type=click.IntRange(8, 16), help="Bits of the linear A/D converter [default: 14 for DNG, 12 otherwise].")
@click.option("--black", type=click.IntRange(min=0), help="Black level [default: 2^(bits-5) for DNG, 0 otherwise].")
@click.option("--alpha", default=0.25, show_default=True, type=FiniteFloatRange(*NOISE_RANGES["alpha"]),
              help="Squared gain alpha of (17) at --base-iso, code values^2 per electron.")
@click.option("--sigma-o2", default=9.0, show_default=True, type=FiniteFloatRange(*NOISE_RANGES["sigma_o2"]),
              help="Read-noise variance sigma_o^2 of (17) at --base-iso, code values^2 (quantisation adds 1/12).")
@click.option("--beta", default=0.0, show_default=True, type=FiniteFloatRange(*NOISE_RANGES["beta"]),
              help="Gain fixed-pattern noise beta of (17) at --base-iso.")
@click.option("--sigma-post2", default=0.0, show_default=True, type=FiniteFloatRange(*NOISE_RANGES["sigma_o2"]),
              help="The part of --sigma-o2 added after the ISO amplifier (code values^2, at most --sigma-o2): "
                   "at ISO i, with g = i / base ISO, alpha and beta scale by g^2 and sigma_o^2 becomes "
                   "(sigma_o^2 - sigma_post^2) g^2 + sigma_post^2 (Hasinoff et al. 2010).")
@click.option("--base-iso", type=FiniteFloatRange(*ISO_RANGE),
              help="The ISO at which --alpha, --sigma-o2 and --beta hold [default: the lowest --iso].")
@click.option("--crf", default="srgb", show_default=True, help="Camera response for JPEG/TIFF/PNG (as in merge).")
@click.option("--out-bits", type=click.Choice(["8", "16"]), default="8", show_default=True,
              help="Bits per sample of TIFF/PNG output (JPEG is 8).")
@click.option("--iso", default="100", show_default=True, callback=_isos, metavar="ISO[,ISO...]",
              help="ISO of the frames: the sensor's gain (see --sigma-post2) and the metadata.  One ISO for every "
                   "frame, or a comma list pairing entry by entry with --times (the same length; each time at its "
                   "ISO, --repeat times).  The automatic times (no --times) are for a single ISO.")
@click.option("--seed", default=0, show_default=True, type=SEED, help="Random seed (scene texture and noise).")
@output_options
@common_options
def command(output_dir, scene, size, downscale, scale, frames, repeat, times, fmt, bits, black, alpha, sigma_o2, beta,
            sigma_post2, base_iso, crf, out_bits, iso, seed, overwrite, as_json):
    """Render a bracket from a scene through the paper's sensor model (16)-(18).

    Poisson photon noise, gain sqrt(alpha) with gain fixed-pattern noise beta, read
    noise sigma_o^2, quantisation to BITS and clipping; DNG frames are Bayer RGGB
    mosaics with a black level, JPEG/TIFF/PNG frames go through --crf.  Each frame is
    rendered at its --iso: the gain amplifies the photo-electrons and the read noise
    before the amplifier, then the read noise after it (--sigma-post2) is added.  Also
    writes the ground truth truth.exr (in the units of 'merge') and simulation.json
    (with the sensor's parameters at each ISO).  Seeded.
    """
    bits = bits or (14 if fmt == "dng" else 12)
    black = black if black is not None else (2 ** (bits - 5) if fmt == "dng" else 0)
    if out_bits == "16" and fmt in ("jpg", "dng"):
        raise click.BadParameter("JPEG holds 8 bits per sample; give --format tif or png for 16" if fmt == "jpg" else
                                 "DNG frames hold the sensor's --bits; --out-bits is for TIFF and PNG",
                                 param_hint="--out-bits")
    if sigma_post2 > sigma_o2:
        raise click.BadParameter(f"{sigma_post2:g} exceeds --sigma-o2 {sigma_o2:g} (it is the part of the read noise "
                                 "after the amplifier)", param_hint="--sigma-post2")
    try:
        frame_isos(iso, times)
    except HdrMergeError as exc:  # a usage error here (exit 2), before any work
        raise click.BadParameter(str(exc).removeprefix("--iso: "), param_hint="--iso") from None
    if base_iso is None:
        base_iso = float(min(iso) if isinstance(iso, list) else iso)
    sensor = SensorModel(alpha=alpha, sigma_o2=sigma_o2, beta=beta, bits=bits, black=black, sigma_post2=sigma_post2,
                         base_iso=base_iso)
    opts = SimulateOptions(
        output_dir=output_dir, scene=scene, width=size[0], height=size[1], downscale=downscale, scale=scale,
        frames=frames, times=times, repeat=repeat, sensor=sensor, fmt=fmt, crf=crf, out_bits=int(out_bits), iso=iso, seed=seed,
        overwrite=overwrite,
    )
    summary = simulate(opts)
    emit(summary, as_json, f"wrote {len(summary['frames'])} frames, truth.exr and simulation.json to {output_dir}")
