"""hdrmerge-cli: noise-optimal HDR merging of exposure brackets.

Implements Goossens, Luong, Aelterman, Pizurica, Philips, "Realistic camera noise
modeling with application to improved HDR synthesis", EURASIP J. Adv. Signal Process.
2012:171 ("the paper"; equations cited as (N)).

The Python API (:mod:`hdrmerge_cli.api`) works on arrays: :func:`merge`,
:func:`estimate_response`, :func:`estimate_noise`, :func:`register`, :func:`ghost_mask`;
:func:`merge_files` merges files as ``hdrmerge-cli merge`` does.
"""
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
