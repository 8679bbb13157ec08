"""Error types raised by the core; the CLI turns them into one-line messages."""


class HdrMergeError(Exception):
    """A problem with the data (not a programming error): reported in one line, exit 1."""


class Terminated(BaseException):
    """SIGTERM or SIGHUP arrived: unwinds like Ctrl-C (a BaseException, so no ``except
    Exception`` swallows it), so every temporary output is removed on the way out."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


def raise_terminated(signum, frame):
    """A signal handler: turn SIGTERM/SIGHUP into :class:`Terminated`."""
    raise Terminated(signum)
