"""How the command speaks on stderr: ``hdrmerge-cli: [level: ]message``, one line each."""
from __future__ import annotations

import logging

PROG = "hdrmerge-cli"


class StderrFormatter(logging.Formatter):
    """``hdrmerge-cli: warning: ...`` (no level word for info), in every process."""

    def format(self, record):
        level = "" if record.levelno == logging.INFO else f"{record.levelname.lower()}: "
        return f"{PROG}: {level}{record.getMessage()}"
