"""Generate the man pages under man/ from the click definitions (``make man``).

Run as ``python -m hdrmerge_cli.manpages DIR``; uses click-man, so the pages cannot
drift from ``--help`` (tests/test_manpages.py regenerates them and compares).

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


if __name__ == "__main__":
    write(sys.argv[1] if len(sys.argv) > 1 else "man")
