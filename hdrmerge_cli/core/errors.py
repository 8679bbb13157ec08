"""Error types raised by the core; the CLI turns them into one-line messages."""


class HdrMergeError(Exception):
    """A problem with the data (not a programming error): reported in one line, exit 1."""


class Terminated(BaseException):
    """SIGINT (Ctrl-C), SIGTERM or SIGHUP arrived: a BaseException, so no ``except
    Exception`` swallows it and every temporary output is removed on the way out."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


#: the stop signals received in this process, in order
RECEIVED: list[int] = []


def raise_terminated(signum, frame):
    """A signal handler: note the signal, then raise :class:`Terminated`.  A library's bare
    ``except:`` can swallow the exception; the note stays, and :func:`check_not_stopped`
    raises it again before anything is committed."""
    RECEIVED.append(signum)
    raise Terminated(signum)


def check_not_stopped() -> None:
    """Raise :class:`Terminated` if a stop signal arrived earlier in this process, even
    one whose exception was swallowed on the way."""
    if RECEIVED:
        raise Terminated(RECEIVED[0])
