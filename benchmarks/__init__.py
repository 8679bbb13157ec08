"""Benchmarks (not tests): run ``python -m benchmarks.<name>``; results go to benchmarks/results/."""
from pathlib import Path


def write_result(out: Path, lines: list[str]) -> str:
    """Write a Markdown result table and return its text."""
    text = "\n".join(lines) + "\n"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    return text


def quiet_import(name: str):
    """Import colour-science modules lazily (~1 s) without their optional-dependency
    warnings (e.g. about matplotlib) on stderr."""
    import importlib
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return importlib.import_module(name)


def save_figure(fig, path: Path) -> None:
    """Write a matplotlib figure (format from the suffix) as the commands' --plot does
    (atomically; replacing an older one), and close it."""
    from hdrmerge_cli.io.atomic import write_together
    from hdrmerge_cli.io.plots import figure_writer

    write_together([(path, figure_writer(fig, path))], True)


def revision() -> str:
    """The git revision measured (``-dirty``: uncommitted changes), or "unknown"."""
    import subprocess

    try:
        out = subprocess.run(["git", "describe", "--always", "--dirty"], cwd=Path(__file__).parent, text=True,
                             capture_output=True, timeout=30).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        out = ""
    return out or "unknown"
