"""The ``hdrmerge-cli`` command group; one module per subcommand."""
from __future__ import annotations

import errno
import importlib
import signal
import warnings

import click

from hdrmerge_cli.core.errors import HdrMergeError, Terminated, raise_terminated


#: subcommand -> the module defining it as ``command``; imported only when that command
#: runs (or help lists it), so one command does not pay for the others' imports
COMMANDS = {
    "calibrate-noise": "calibrate_noise",
    "estimate-crf": "estimate_crf",
    "merge": "merge",
    "weights-lut": "weights_lut",
    "info": "info",
    "simulate": "simulate",
    "plan": "plan",
}

#: each command's one-line summary (the first paragraph of its docstring) for the group's
#: --help, which then imports no command module (numpy, numba, scipy...); a test checks
#: these against the commands' own help so they cannot drift
SUMMARIES = {
    "calibrate-noise": "Fit the sensor noise model Var[y] = sigma_o^2 + alpha x + beta x^2 (17) per ISO and channel.",
    "estimate-crf": "Estimate the inverse camera response g(z) = log gamma^-1(z) of a bracket of JPEG/TIFF/PNG "
                    "frames and write it to a profile JSON for 'merge --crf' or 'merge --profile'.",
    "merge": "Merge a bracket IMAGES... (RAW, or JPEG/TIFF/PNG) into one scene-linear EXR.",
    "weights-lut": "Tabulate a weighting function per exposure: one row per code value z, one column per exposure "
                   "(and channel, for a per-channel CRF or noise), values in [0, 1].  'merge --lut' reuses the "
                   "table so batch runs skip rebuilding it.",
    "info": "Describe frames IMAGES and whether they cover the scene as a bracket.",
    "simulate": "Render a bracket from a scene through the paper's sensor model (16)-(18).",
    "plan": "Plan the bracket to shoot: the exposure times and ISOs with the best worst-case SNR for the scene of "
            "METERING_FRAMES.",
}


#: what to do when a command runs out of memory
OUT_OF_MEMORY = {
    "merge": "merge fewer or smaller frames",
    "simulate": "use a smaller --size or scene",
    "estimate-crf": "give fewer or smaller frames, or fewer --samples",
    "calibrate-noise": "give fewer or smaller frames",
    "weights-lut": "use fewer exposures or --bits",
    "info": "describe fewer or smaller frames",
    "plan": "give fewer or smaller metering frames",
}


class DataError(click.ClickException):
    """A data error: ``hdrmerge-cli: error: ...`` on one line, exit 1 (usage errors stay
    click's, exit 2)."""

    def show(self, file=None):
        click.echo(f"hdrmerge-cli: error: {self.format_message()}", err=True)


class _Group(click.Group):
    """Turns data errors into one-line messages with exit code 1 (never a traceback);
    loads subcommands lazily."""

    def list_commands(self, ctx):
        return list(COMMANDS)

    def get_command(self, ctx, name):
        if name not in COMMANDS:
            return None
        return importlib.import_module(f"hdrmerge_cli.cli.{COMMANDS[name]}").command

    def format_commands(self, ctx, formatter):
        """The command list of --help from :data:`SUMMARIES`, without importing the commands."""
        limit = formatter.width - 6 - max(map(len, COMMANDS))
        rows = [(name, click.Command(name, help=SUMMARIES[name]).get_short_help_str(limit)) for name in COMMANDS]
        with formatter.section("Commands"):
            formatter.write_dl(rows)

    def invoke(self, ctx):
        if _RUN_FROM_MAIN:
            # here, not in main(): the group's own --help/--version exit before this and
            # so never import io.frames (numpy)
            from hdrmerge_cli.io.frames import separate_python_stderr

            separate_python_stderr()
        from hdrmerge_cli.cli.options import name_config_in_error, name_config_in_usage_error

        try:
            return super().invoke(ctx)
        except click.BadParameter as exc:
            name_config_in_usage_error(exc)
            raise
        except HdrMergeError as exc:
            raise DataError(name_config_in_error(ctx.meta, str(exc))) from None
        except (Terminated, KeyboardInterrupt) as exc:  # Unix tools exit 128 + the signal (130 for Ctrl-C)
            signum = exc.signum if isinstance(exc, Terminated) else signal.SIGINT
            click.echo(f"hdrmerge-cli: stopped by {signal.Signals(signum).name}; no partial output was left", err=True)
            ctx.exit(128 + signum)
        except MemoryError:
            advice = OUT_OF_MEMORY.get(ctx.invoked_subcommand, OUT_OF_MEMORY["merge"])
            raise DataError(f"out of memory: {advice}") from None
        except OSError as exc:
            if exc.errno == errno.EPIPE:  # e.g. `hdrmerge-cli ... --json | head`
                ctx.exit(0)
            where = f"{exc.filename}: " if exc.filename else ""
            raise DataError(f"{where}{exc.strerror or exc}") from None


def _print_version(ctx, param, value):
    """``--version``: the installed version, read only when asked for (importlib.metadata
    costs every other command's start-up tens of ms)."""
    if not value or ctx.resilient_parsing:
        return
    from hdrmerge_cli._version import __version__

    click.echo(f"hdrmerge-cli, version {__version__}")
    ctx.exit()


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--version", is_flag=True, expose_value=False, is_eager=True, callback=_print_version,
              help="Show the version and exit.")
def cli():
    """Merge exposure brackets into scene-linear HDR images (OpenEXR) with the camera
    noise model of Goossens et al. (2012).

    Outputs are written to a temporary name and renamed; nothing is overwritten without
    --overwrite; logs go to stderr, --json summaries to stdout.  Exit codes: 0 success,
    1 a data error (explained in one line), 2 a usage error.
    """


#: set by :func:`main` (the installed command), not by click's test runner, whose captured
#: stderr must stay in place
_RUN_FROM_MAIN = False


def main():
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):  # first: temporaries removed, exit 128 + signal
        signal.signal(sig, raise_terminated)
    global _RUN_FROM_MAIN
    _RUN_FROM_MAIN = True
    # numpy's RuntimeWarnings (a 0/0 in a masked-out sample) say nothing a user can act on;
    # results are checked for finiteness before anything is written
    warnings.filterwarnings("ignore", category=RuntimeWarning)
    from hdrmerge_cli.io.malloc import one_malloc_arena

    one_malloc_arena()
    cli(prog_name="hdrmerge-cli")
