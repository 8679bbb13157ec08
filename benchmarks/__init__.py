"""Benchmarks (not tests): run ``python -m benchmarks.<name>``; results go to benchmarks/results/."""
from pathlib import Path


def write_result(out: Path, lines: list[str]) -> str:
    """Write a Markdown result table and return its text."""
    text = "\n".join(lines) + "\n"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    return text


def revision() -> str:
    """The git revision measured (``-dirty``: uncommitted changes), or "unknown"."""
    import subprocess

    try:
        out = subprocess.run(["git", "describe", "--always", "--dirty"], cwd=Path(__file__).parent, text=True,
                             capture_output=True, timeout=30).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        out = ""
    return out or "unknown"
