"""hdrmerge-cli simulate"""
from __future__ import annotations

from pathlib import Path

import click

from hdrmerge_cli.cli.options import (
    SEED, FiniteFloatRange, common_options, emit, output_options, times_option_callback,
)
from hdrmerge_cli.core.sensor import SensorModel
from hdrmerge_cli.io.noisespec import NOISE_RANGES
from hdrmerge_cli.pipeline.simulate import FORMATS, SimulateOptions, simulate


#: largest side of a simulated frame (JPEG's limit)
MAX_SIDE = 65500
#: range of --scale: wide enough for a scene in any unit, narrow enough not to overflow
SCALE_RANGE = (1e-12, 1e12)


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
              help="Frames per exposure time (independent noise, the same fixed pattern), e.g. 2 for "
                   "photon-transfer pairs.")
@click.option("--times", callback=times_option_callback, metavar="T1,T2,...", help="Exposure times in seconds.")
@click.option("--format", "fmt", type=click.Choice(FORMATS), default="dng", show_default=True,
              help="DNG (Bayer RAW) or camera-processed JPEG/TIFF/PNG with EXIF.")
@click.option("--bits", type=click.IntRange(8, 16), help="Bits of the linear A/D converter [default: 14 for DNG, 12 otherwise].")
@click.option("--black", type=click.IntRange(min=0), help="Black level [default: 2^(bits-5) for DNG, 0 otherwise].")
@click.option("--alpha", default=0.25, show_default=True, type=FiniteFloatRange(*NOISE_RANGES["alpha"]),
              help="Squared gain alpha of (17), code values^2 per electron.")
@click.option("--sigma-o2", default=9.0, show_default=True, type=FiniteFloatRange(*NOISE_RANGES["sigma_o2"]),
              help="Read-noise variance sigma_o^2 of (17), code values^2 (quantisation adds 1/12).")
@click.option("--beta", default=0.0, show_default=True, type=FiniteFloatRange(*NOISE_RANGES["beta"]),
              help="Gain fixed-pattern noise beta of (17).")
@click.option("--crf", default="srgb", show_default=True, help="Camera response for JPEG/TIFF/PNG (as in merge).")
@click.option("--out-bits", type=click.Choice(["8", "16"]), default="8", show_default=True,
              help="Bits per sample of TIFF/PNG output (JPEG is 8).")
@click.option("--iso", default=100, show_default=True, type=click.IntRange(1, 65535),
              help="ISO written to the metadata (a 16-bit EXIF field).")
@click.option("--seed", default=0, show_default=True, type=SEED, help="Random seed (scene texture and noise).")
@output_options
@common_options
def command(output_dir, scene, size, downscale, scale, frames, repeat, times, fmt, bits, black, alpha, sigma_o2, beta, crf,
            out_bits, iso, seed, overwrite, as_json):
    """Render a bracket from a scene through the paper's sensor model (16)-(18).

    Poisson photon noise, gain sqrt(alpha) with gain fixed-pattern noise beta, read
    noise sigma_o^2, quantisation to BITS and clipping; DNG frames are Bayer RGGB
    mosaics with a black level, JPEG/TIFF/PNG frames go through --crf.  Also writes the
    ground truth truth.exr (in the units of 'merge') and simulation.json.  Seeded.
    """
    bits = bits or (14 if fmt == "dng" else 12)
    black = black if black is not None else (2 ** (bits - 5) if fmt == "dng" else 0)
    sensor = SensorModel(alpha=alpha, sigma_o2=sigma_o2, beta=beta, bits=bits, black=black)
    opts = SimulateOptions(
        output_dir=output_dir, scene=scene, width=size[0], height=size[1], downscale=downscale, scale=scale,
        frames=frames, times=times, repeat=repeat, sensor=sensor, fmt=fmt, crf=crf, out_bits=int(out_bits), iso=iso, seed=seed,
        overwrite=overwrite,
    )
    summary = simulate(opts)
    emit(summary, as_json, f"wrote {len(summary['frames'])} frames, truth.exr and simulation.json to {output_dir}")
