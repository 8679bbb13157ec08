"""Benchmarks (not tests): run ``python -m benchmarks.<name>``; results go to benchmarks/results/."""
from pathlib import Path


def write_result(out: Path, lines: list[str]) -> str:
    """Write a Markdown result table and return its text."""
    text = "\n".join(lines) + "\n"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    return text
