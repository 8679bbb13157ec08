"""Numba kernels that import Numba on their first call, not when their module is imported.

Importing Numba costs about 0.3 s and setting up its code generator as much again; a command
that runs no kernel (``--help``, ``info``, a refused input) should pay neither, and a merge
should pay them on the second core while it reads its frames (``pipeline.run`` starts that).
A module writes ``@njit(...)`` and ``prange`` from here where it would write
``@numba.njit(...)`` and ``numba.prange``.  The first call of any of its kernels replaces,
in that module (and in every module that imported them), each :class:`Kernel` by
``numba.njit(**options)(function)`` and ``prange`` by ``numba.prange``: the very dispatchers
the decorator would have made at import, so kernels, their cache files and their results are
unchanged.  Kernels may call each other across modules.
"""
from __future__ import annotations

import functools
import sys
import threading

#: a stand-in for ``numba.prange`` in a module whose kernels are not compiled yet
prange = range

_lock = threading.RLock()


class Kernel:
    """A function to be compiled with ``numba.njit(**options)`` on first use."""

    def __init__(self, function, options: dict):
        functools.update_wrapper(self, function)
        self.function = function
        self.options = options
        self.dispatcher = None

    def __call__(self, *args, **kwargs):
        if self.dispatcher is None:
            compile_module(self.function.__module__)
        return self.dispatcher(*args, **kwargs)


def njit(**options):
    """``numba.njit(**options)``, applied when a kernel of the module is first called."""
    return lambda function: Kernel(function, options)


def num_threads() -> int:
    """``numba.get_num_threads()``."""
    import numba

    return numba.get_num_threads()


def compile_module(name: str) -> None:
    """Make the dispatchers of module ``name``'s kernels and bind them (and ``numba.prange``)
    in its namespace, first doing the same for the modules whose kernels it imported."""
    import numba

    with _lock:
        namespace = vars(sys.modules[name])
        if namespace.get("prange") is prange:
            namespace["prange"] = numba.prange
        kernels = [(key, value) for key, value in namespace.items() if isinstance(value, Kernel)]
        for key, kernel in kernels:  # its own first, so that a module importing these back finds them made
            if kernel.function.__module__ == name and kernel.dispatcher is None:
                kernel.dispatcher = numba.njit(**kernel.options)(kernel.function)
        for key, kernel in kernels:
            if kernel.dispatcher is None:
                compile_module(kernel.function.__module__)
            namespace[key] = kernel.dispatcher
