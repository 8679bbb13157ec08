"""Generate the man pages under man/ from the click definitions (``make man``).

Run as ``python -m hdrmerge_cli.manpages DIR``; uses click-man, so the pages cannot
drift from ``--help`` (tests/test_manpages.py regenerates them and compares).

``python -m hdrmerge_cli.manpages --usage [docs/usage.md]`` writes the option reference
of each command into docs/usage.md, between ``<!-- options:COMMAND:start -->`` and
``<!-- options:COMMAND:end -->`` (:func:`update_usage`; tests/test_docs.py checks it is
current), from the same click definitions.

click-man copies help text into the page verbatim, so a help line starting with ``'``
or ``.`` would be read by roff as a request and silently dropped, and a backslash would
start an escape.  :class:`_EscapedManPage` escapes every text field before click-man
adds its own macros.
"""
from __future__ import annotations

import sys
from unittest import mock

MAN_DATE = "2026-11-21"


def roff_escape(text: str) -> str:
    r"""``text`` safe as roff input text: ``\`` -> ``\e``, and ``\&`` before a ``.`` or
    ``'`` that starts a line (where roff would take it for a control character)."""
    lines = text.replace("\\", r"\e").split("\n")
    return "\n".join(r"\&" + line if line.startswith((".", "'")) else line for line in lines)


def _escaped_man_page_class():
    from click_man.man import ManPage

    class _EscapedManPage(ManPage):
        """click-man's page with all help text roff-escaped (the macros it adds are not)."""

        def __str__(self):
            fields = ("short_help", "synopsis", "description", "options", "commands")
            saved = {f: getattr(self, f) for f in fields}
            try:
                self.short_help = roff_escape(self.short_help)
                self.synopsis = roff_escape(self.synopsis)
                self.description = roff_escape(self.description)
                self.options = [(roff_escape(o), roff_escape(d)) for o, d in self.options]
                self.commands = [(roff_escape(n), roff_escape(d)) for n, d in self.commands]
                return super().__str__()
            finally:
                for f, value in saved.items():
                    setattr(self, f, value)

    return _EscapedManPage


def write(target_dir: str) -> None:
    import click_man.core
    from click_man.core import write_man_pages

    from hdrmerge_cli._version import __version__
    from hdrmerge_cli.cli import COMMANDS, cli

    for name in COMMANDS:  # click-man walks ``cli.commands``; the group loads them lazily
        cli.add_command(cli.get_command(None, name))
    # click-man's generate_man_page builds ``core.ManPage``; swap in the escaping subclass
    with mock.patch.object(click_man.core, "ManPage", _escaped_man_page_class()):
        write_man_pages("hdrmerge-cli", cli, version=__version__, target_dir=target_dir, date=MAN_DATE)


#: options whose method has a section in docs/method.md: the reference links to it
METHOD_LINKS = {
    "--weights": "method.md#weightings", "--estimator": "method.md#estimators",
    "--variance": "method.md#the-variance-factor", "--irls": "method.md#estimators",
    "--noise": "method.md#the-noise-model", "--profile": "method.md#the-noise-model",
    "--bounds": "method.md#weightings", "--k": "method.md#weightings",
    "--crf": "method.md#the-camera-response", "--times": "method.md#exposures-and-their-labels",
    "--align": "method.md#registration", "--deghost": "method.md#deghosting",
    "--colorspace": "method.md#colour", "--cfa": "method.md#colour",
    "--reference": "method.md#output-units-and-unmeasured-pixels",
    "--extra-channels": "method.md#output-units-and-unmeasured-pixels",
    "--method": "method.md#the-camera-response", "--coupling": "method.md#the-camera-response",
    "--anchor": "method.md#the-camera-response", "--lambda": "method.md#the-camera-response",
    "--darks": "method.md#calibrating-the-noise", "--flats": "method.md#calibrating-the-noise",
}


def _markdown_text(text: str) -> str:
    """Help text as Markdown that renders as written: emphasis characters escaped."""
    return " ".join(text.split()).replace("\\", "\\\\").replace("*", "\\*").replace("_", "\\_")


def usage_reference(name: str) -> str:
    """The option reference of subcommand ``name`` as a Markdown list: every option's
    flags and ``--help`` text (with click's defaults and ranges), and where
    docs/method.md explains the method behind it."""
    import click

    from hdrmerge_cli.cli import cli

    root = click.Context(cli, info_name="hdrmerge-cli")
    cmd = cli.get_command(root, name)
    ctx = click.Context(cmd, info_name=name, parent=root)
    usage = " ".join(cmd.collect_usage_pieces(ctx))
    lines = [f"`hdrmerge-cli {name} {usage}`", ""]
    for param in cmd.params:
        if not isinstance(param, click.Option) or param.hidden:
            continue
        record = param.get_help_record(ctx)
        if not record:
            continue
        flags, help_text = record
        line = f"- `{flags}`: {_markdown_text(help_text)}"
        link = next((METHOD_LINKS[o] for o in param.opts if o in METHOD_LINKS), None)
        if link:
            line += f" ([method]({link}))"
        lines.append(line)
    return "\n".join(lines)


def update_usage(text: str) -> str:
    """``text`` (docs/usage.md) with each marked option reference regenerated."""
    import re

    def replace(m):
        return f"{m.group(1)}\n{usage_reference(m.group(2))}\n{m.group(3)}"

    return re.sub(r"(<!-- options:([a-z-]+):start -->)\n.*?\n?(<!-- options:\2:end -->)", replace, text,
                  flags=re.S)


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--usage":
        from pathlib import Path

        path = Path(sys.argv[2] if len(sys.argv) > 2 else "docs/usage.md")
        path.write_text(update_usage(path.read_text()))
    else:
        write(sys.argv[1] if len(sys.argv) > 1 else "man")
