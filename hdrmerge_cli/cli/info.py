"""hdrmerge-cli info"""
from __future__ import annotations

import json

import click

from hdrmerge_cli.cli.options import common_options
from hdrmerge_cli.pipeline.info import bracket_info, format_info


@click.command("info")
@click.argument("images", nargs=-1, required=True, type=click.Path(exists=True, dir_okay=False))
@click.option("--json", "as_json", is_flag=True, help="Print the report as JSON instead of a table.")
@common_options
def command(images, as_json):
    """Describe frames IMAGES and whether they cover the scene as a bracket.

    Per frame: camera, exposure time, ISO, bit depth, black and white levels, and the
    fractions of clipped (at the white level) and dark (at or below black) samples.  For
    the bracket: whether every pixel is measured by some frame, and otherwise which
    exposure to add.  The report goes to stdout.
    """
    summary = bracket_info(images)
    click.echo(json.dumps(summary, indent=1) if as_json else format_info(summary))
