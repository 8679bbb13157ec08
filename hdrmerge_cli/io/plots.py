"""Figures for the --plot options: matplotlib without a display, written atomically."""
from __future__ import annotations

from pathlib import Path

from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.io.atomic import check_writable

def check_figure_path(path: str | Path, overwrite: bool) -> None:
    """Refuse, before any work is done, a figure that could not be written: a suffix
    matplotlib does not write, or an existing file without ``overwrite``."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    formats = sorted(FigureCanvasAgg.get_supported_filetypes())
    suffix = Path(path).suffix.lower().lstrip(".")
    if suffix not in formats:
        raise HdrMergeError(f"{path}: cannot draw a figure of type {suffix or '(none)'!r}; use one of {', '.join(formats)}")
    check_writable(path, overwrite)


def pyplot():
    """matplotlib.pyplot on the non-interactive Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def figure_writer(fig, path: str | Path):
    """A writer of ``fig`` in the format of ``path``'s suffix, for
    :func:`~hdrmerge_cli.io.atomic.write_together` (the figure is closed once saved)."""
    def write(tmp: str) -> None:
        fig.savefig(tmp, format=Path(path).suffix.lower().lstrip("."))
        pyplot().close(fig)

    return write
