"""Error types raised by the core; the CLI turns them into one-line messages."""


class HdrMergeError(Exception):
    """A problem with the data (not a programming error): reported in one line, exit 1."""
