"""Option decorators shared by the subcommands."""
from __future__ import annotations

import json
import logging
import math
import sys
import tomllib

import click

from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.io.logs import StderrFormatter


def _set_verbosity(ctx, param, value):
    state = ctx.ensure_object(dict)
    state[param.name] = value
    verbose, quiet = state.get("verbose", 0), state.get("quiet", False)
    level = logging.ERROR if quiet else (logging.WARNING, logging.INFO, logging.DEBUG)[min(verbose, 2)]
    logger = logging.getLogger("hdrmerge_cli")
    logger.handlers[:] = []
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(StderrFormatter())
    logger.addHandler(handler)
    logger.setLevel(level)
    logger.propagate = False
    return value


#: largest --config file read (bytes)
MAX_CONFIG_BYTES = 2**20
#: ``ctx.meta`` key (shared with the group's context): the command's context and the
#: --config file it read, so that errors about values from that file can name it
CONFIG_META = "hdrmerge_cli.config"


def _load_config(ctx, param, value):
    """Read a TOML file into the command's defaults: the command line still wins.

    Keys are long option names (``weights``, ``times-file``, ``lambda``), at the top
    level or in a table named after the subcommand (``[merge]``)."""
    from hdrmerge_cli.io.profile import read_text

    if value is None:
        return None
    try:
        data = tomllib.loads(read_text(value, MAX_CONFIG_BYTES))
    except HdrMergeError as exc:
        raise click.BadParameter(str(exc), ctx, param) from None
    except tomllib.TOMLDecodeError as exc:
        raise click.BadParameter(f"{value}: not valid TOML ({exc})", ctx, param) from None
    except RecursionError:
        raise click.BadParameter(f"{value}: not valid TOML (nested too deeply)", ctx, param) from None
    section = data.get(ctx.info_name, {}) if isinstance(data.get(ctx.info_name), dict) else {}
    top = {k: v for k, v in data.items() if not isinstance(v, dict)}
    merged = top | section
    options = {}
    for opt in ctx.command.params:
        if isinstance(opt, click.Option) and opt.name != "config":
            options[opt.name] = opt
            for flag in opt.opts:
                if flag.startswith("--"):
                    options[flag[2:].replace("-", "_")] = opt
    defaults = {}
    for key, val in merged.items():
        opt = options.get(key.replace("-", "_"))
        if opt is None:
            raise click.BadParameter(f"{value}: unknown key {key[:40]!r} for '{ctx.info_name}'", ctx, param)
        if isinstance(val, list) and not opt.multiple and opt.nargs == 1:
            val = ",".join(str(v) for v in val)  # times = [0.01, 0.1] as --times 0.01,0.1
        defaults[opt.name] = val
    ctx.default_map = (ctx.default_map or {}) | defaults
    ctx.meta[CONFIG_META] = (ctx, value)
    return value


def _from_config(meta: dict, param) -> str | None:
    """The --config file that gave ``param`` its value, or None."""
    ctx, path = meta.get(CONFIG_META, (None, None))
    if ctx is None or param is None or param.name is None:
        return None
    return path if ctx.get_parameter_source(param.name) == click.core.ParameterSource.DEFAULT_MAP else None


def name_config_in_usage_error(exc: click.BadParameter) -> None:
    """A bad value read from the --config file: its message names that file too."""
    path = _from_config(exc.ctx.meta, exc.param) if exc.ctx is not None else None
    if path is not None and exc.param_hint is None:
        exc.param_hint = f"{exc.param.get_error_hint(exc.ctx)} in {path}"


def name_config_in_error(meta: dict, message: str) -> str:
    """``message`` of a data error, plus the --config file when the message is about an
    option that file set (it names the option's flag or the value as written there)."""
    ctx, _ = meta.get(CONFIG_META, (None, None))
    for param in ctx.command.params if ctx is not None else ():
        path = _from_config(meta, param)
        if path is None or not isinstance(param, click.Option):
            continue
        flag = max(param.opts, key=len)
        raw = str((ctx.default_map or {}).get(param.name, ""))
        if flag in message or (len(raw) >= 3 and raw in message):
            return f"{message} ({flag} is set in {path})"
    return message


def common_options(f):
    """--config, -v/--verbose, -q/--quiet."""
    f = click.option("-q", "--quiet", is_flag=True, expose_value=False, is_eager=True, callback=_set_verbosity,
                     help="Only print errors on stderr.")(f)
    f = click.option("-v", "--verbose", count=True, expose_value=False, is_eager=True, callback=_set_verbosity,
                     help="More detail on stderr (-vv for debug).")(f)
    f = click.option("--config", type=click.Path(dir_okay=False), is_eager=True, expose_value=False,
                     callback=_load_config, help="TOML file of option defaults (the command line wins).")(f)
    return f


def output_options(f):
    """--overwrite and --json."""
    f = click.option("--json", "as_json", is_flag=True, help="Print a JSON summary on stdout.")(f)
    f = click.option("--overwrite", is_flag=True, help="Replace existing output files.")(f)
    return f


def emit(summary: dict, as_json: bool, text: str) -> None:
    """The JSON summary on stdout (``--json``); otherwise one line on stderr saying what
    was written (silenced by -q)."""
    if as_json:
        click.echo(json.dumps(summary, indent=1))
    elif logging.getLogger("hdrmerge_cli").level <= logging.WARNING:
        click.echo(f"hdrmerge-cli: {text}", err=True)


def to_a_file(ctx, param, value):
    """``-o``: a file or folder name; ``-`` (standard output) is refused as what it is."""
    if value is not None and str(value) == "-":
        raise click.BadParameter("writing to standard output is not supported: outputs are files, written whole "
                                 "and then renamed into place; give a name (e.g. -o out.exr) and read that file")
    return value


def parse_csv_list(ctx, param, value):
    if value is None:
        return ()
    if isinstance(value, (list, tuple)):
        return tuple(str(v) for v in value)
    return tuple(v.strip() for v in value.split(",") if v.strip())


BOUNDS_HELP = ("Upper bounds for the bounded weights on the normalised signal: inv_alpha=0.005,sigma_o2=0.02,beta=0 "
               "(the paper's JPEG values, the default), or delta=W with one of them to solve the other so that the "
               "clipping-safe range is W of full scale.")


#: random seeds (NumPy's generators take non-negative integers)
SEED = click.IntRange(min=0)


class FiniteFloatRange(click.FloatRange):
    """``click.FloatRange`` that also refuses ``nan`` and ``+-inf`` (FloatRange lets nan
    through any bounds, and inf through open-ended ones).  Same help text as FloatRange."""

    def convert(self, value, param, ctx):
        rv = super().convert(value, param, ctx)
        if not math.isfinite(rv):
            self.fail(f"{value!r} is not a finite number.", param, ctx)
        return rv


def _text_checked_by(parser: str):
    """A callback that checks a text option with :mod:`hdrmerge_cli.io.noisespec`'s
    ``parser`` as soon as it is read, so that an empty text is an error too (not silently
    unset); its HdrMergeError, which names the option, is a one-line data error (exit 1)
    like the later checks of the values.  Passes the text on."""
    def callback(ctx, param, value):
        from hdrmerge_cli.io import noisespec

        if value is None:
            return None
        getattr(noisespec, parser)(str(value))  # its HdrMergeError becomes the group's one-line data error
        return str(value)

    return callback


#: ``--noise`` and ``--bounds``, checked by :func:`~hdrmerge_cli.io.noisespec.parse_noise` and ``parse_bounds``
noise_option_callback, bounds_option_callback = _text_checked_by("parse_noise"), _text_checked_by("parse_bounds")


def times_option_callback(ctx, param, value):
    from hdrmerge_cli.io.times import parse_times

    if value is None:
        return None
    if isinstance(value, (list, tuple)):
        value = ",".join(str(v) for v in value)
    try:
        return parse_times(str(value))
    except HdrMergeError as exc:
        raise click.BadParameter(str(exc), ctx, param) from None


def times_or_estimate_callback(ctx, param, value):
    """``--times``: exposure times as :func:`times_option_callback`, or the word
    ``estimate`` (exposures measured on the frames, the labels giving the scale)."""
    from hdrmerge_cli.io.times import ESTIMATE

    if isinstance(value, str) and value.strip().lower() == ESTIMATE:
        return ESTIMATE
    return times_option_callback(ctx, param, value)


TIMES_HELP = ("Exposure times in seconds, in the order of IMAGES (e.g. 1/100,1/25,0.5); overrides EXIF.  'estimate': "
              "measure the exposures on the frames (neighbour ratios of the pixels both expose well, chained from a "
              "reference frame whose label, from EXIF or --times-file, sets the scale).")
