"""Generate the man pages under man/ from the click definitions (``make man``).

Run as ``python -m hdrmerge_cli.manpages DIR``; uses click-man, so the pages cannot
drift from ``--help`` (a test regenerates them and compares).
"""
from __future__ import annotations

import sys

MAN_DATE = "2026-11-21"


def write(target_dir: str) -> None:
    from click_man.core import write_man_pages

    from hdrmerge_cli import __version__
    from hdrmerge_cli.cli import COMMANDS, cli

    for name in COMMANDS:  # click-man walks ``cli.commands``; the group loads them lazily
        cli.add_command(cli.get_command(None, name))
    write_man_pages("hdrmerge-cli", cli, version=__version__, target_dir=target_dir, date=MAN_DATE)


if __name__ == "__main__":
    write(sys.argv[1] if len(sys.argv) > 1 else "man")
