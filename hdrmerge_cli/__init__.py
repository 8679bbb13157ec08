"""hdrmerge-cli: noise-optimal HDR merging of exposure brackets.

Implements Goossens, Luong, Aelterman, Pizurica, Philips, "Realistic camera noise
modeling with application to improved HDR synthesis", EURASIP J. Adv. Signal Process.
2012:171 ("the paper"; equations cited as (N)).

The Python API (:mod:`hdrmerge_cli.api`) works on arrays: :func:`merge`,
:func:`estimate_response`, :func:`estimate_noise`, :func:`register`, :func:`ghost_mask`;
:func:`merge_files` merges files as ``hdrmerge-cli merge`` does.
"""
import os
import tempfile


def _writable(folder: str) -> bool:
    try:
        os.makedirs(folder, exist_ok=True)
        tempfile.TemporaryFile(dir=folder).close()
        return True
    except OSError:
        return False


def _place_kernel_cache() -> None:
    """Where numba caches the compiled kernels: beside the sources (``__pycache__``) when
    that is writable, else ``$XDG_CACHE_HOME/hdrmerge-cli/numba`` (``~/.cache/...``), else
    a folder of this user's under the temporary directory; with no writable place at all
    the kernels compile without a cache (a slower start, never an error).  A
    ``NUMBA_CACHE_DIR`` the user set is kept."""
    if os.environ.get("NUMBA_CACHE_DIR") or _writable(os.path.join(os.path.dirname(__file__), "core", "__pycache__")):
        return
    home = os.path.expanduser("~")
    bases = [os.environ.get("XDG_CACHE_HOME") or (os.path.join(home, ".cache") if home != "~" else ""),
             os.path.join(tempfile.gettempdir(), f"hdrmerge-cli-{os.getuid() if hasattr(os, 'getuid') else 'user'}")]
    for base in filter(None, bases):
        folder = os.path.join(base, "hdrmerge-cli", "numba") if base is bases[0] else os.path.join(base, "numba")
        if _writable(folder):
            os.environ["NUMBA_CACHE_DIR"] = folder
            return
    from numba.core.dispatcher import Dispatcher

    Dispatcher.enable_caching = lambda self: None


_place_kernel_cache()

#: the Python API (:mod:`hdrmerge_cli.api`), imported on first use so that the command
#: line's start-up does not pay for it; ``__version__`` too is read on first use (the
#: installed metadata: importlib.metadata costs tens of ms)
__all__ = ["CRF", "Merged", "MergeSettings", "NoiseParams", "Registration", "estimate_noise", "estimate_response",
           "ghost_mask", "merge", "merge_files", "register", "__version__"]


def __getattr__(name: str):
    if name == "__version__":
        from hdrmerge_cli._version import __version__

        return __version__
    if name in __all__:
        from hdrmerge_cli import api

        return getattr(api, name)
    raise AttributeError(f"module 'hdrmerge_cli' has no attribute {name!r}")
