"""The ``hdrmerge-cli`` command group; one module per subcommand."""
from __future__ import annotations

import errno
import importlib
import signal
import warnings

import click

from hdrmerge_cli import __version__
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

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except HdrMergeError as exc:
            raise DataError(str(exc)) from None
        except Terminated as exc:
            click.echo(f"hdrmerge-cli: stopped by {signal.Signals(exc.signum).name}; no partial output was left", err=True)
            ctx.exit(128 + exc.signum)
        except MemoryError:
            raise DataError("out of memory: merge fewer or smaller frames") from None
        except OSError as exc:
            if exc.errno == errno.EPIPE:  # e.g. `hdrmerge-cli ... --json | head`
                ctx.exit(0)
            where = f"{exc.filename}: " if exc.filename else ""
            raise DataError(f"{where}{exc.strerror or exc}") from None


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="hdrmerge-cli")
def cli():
    """Merge exposure brackets into scene-linear HDR images (OpenEXR) with the camera
    noise model of Goossens et al. (2012).

    Outputs are written to a temporary name and renamed; nothing is overwritten without
    --overwrite; logs go to stderr, --json summaries to stdout.  Exit codes: 0 success,
    1 a data error (explained in one line), 2 a usage error.
    """


def main():
    from hdrmerge_cli.io.frames import separate_python_stderr

    separate_python_stderr()
    # numpy's RuntimeWarnings (a 0/0 in a masked-out sample) say nothing a user can act on;
    # results are checked for finiteness before anything is written
    warnings.filterwarnings("ignore", category=RuntimeWarning)
    for sig in (signal.SIGTERM, signal.SIGHUP):  # handled like Ctrl-C: temporaries removed
        signal.signal(sig, raise_terminated)
    cli(prog_name="hdrmerge-cli")
