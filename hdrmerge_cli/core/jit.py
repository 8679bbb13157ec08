"""Numba kernels that import Numba on their first call, not when their module is imported.

Importing Numba costs about 0.3 s and setting up its code generator as much again; a command
that runs no kernel (``--help``, ``info``, a refused input) pays neither (a merge sets the
generator up on ``pipeline.run``'s prepare-kernels thread).  A module writes ``@njit(...)``
and ``prange`` from here where it would write ``@numba.njit(...)`` and ``numba.prange``.
The first call of any of its kernels binds in that module's namespace ``numba.prange`` and,
for each :class:`Kernel`, ``numba.njit(**options)(function)``: the very dispatchers the
decorator would have made at import, so kernels, their cache files and their results are
unchanged.  A kernel calls only kernels of its own module.
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
    """Bind ``numba.prange`` and the dispatcher of each of module ``name``'s kernels in its
    namespace; each :class:`Kernel` then hands its calls to its dispatcher."""
    import numba

    with _lock:
        namespace = vars(sys.modules[name])
        kernels = [(key, value) for key, value in namespace.items()
                   if isinstance(value, Kernel) and value.function.__module__ == name and value.dispatcher is None]
        if namespace.get("prange") is prange:
            namespace["prange"] = numba.prange
        made = [(kernel, numba.njit(**kernel.options)(kernel.function)) for _, kernel in kernels]
        for (key, _), (_, dispatcher) in zip(kernels, made):
            namespace[key] = dispatcher
        for kernel, dispatcher in made:  # last: a kernel called on another thread finds its module's bound
            kernel.dispatcher = dispatcher
