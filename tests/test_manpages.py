"""The man pages in man/: up to date with the click definitions, and no help text lost
to roff (a help line starting with ``'`` or ``.`` is read as a request and dropped)."""
import inspect
import re
import shutil
import subprocess
from pathlib import Path
from unittest import mock

import click
import pytest

from hdrmerge_cli.cli import COMMANDS, cli

click_man_core = pytest.importorskip("click_man.core")

ROOT = Path(__file__).resolve().parents[1]
MAN = ROOT / "man"
PAGES = ["hdrmerge-cli", *COMMANDS]  # the group's page, then one per subcommand

#: man(7) macros and the few roff requests a man page may start a line with
KNOWN_MACROS = {
    "TH", "SH", "SS", "PP", "P", "LP", "TP", "TQ", "IP", "HP", "RS", "RE", "PD", "B", "I", "BI", "BR", "IB",
    "IR", "RB", "RI", "SB", "SM", "EX", "EE", "UR", "UE", "MT", "ME", "SY", "OP", "YS", "MR",
    "nf", "fi", "br", "sp", "ad", "na", "nh", "hy", "ne", "in", "ti", "ft",
}

#: what groff's utf8 device may print for ASCII characters in the source
_UTF8_BACK = str.maketrans({"\u2010": "-", "\u2212": "-", "\u2019": "'", "\u2018": "`", "\u02dc": "~",
                            "\u02c6": "^", "\u00a0": " "})


def _page_path(page: str) -> Path:
    return MAN / f"{'hdrmerge-cli' if page == 'hdrmerge-cli' else 'hdrmerge-cli-' + page}.1"


def _expected_texts(page: str) -> list[tuple[str, str]]:
    """(what, text) for every piece of help click-man puts on ``page``: the description,
    each option's help (with click's [default: ...] extras), each subcommand's summary."""
    root = click.Context(cli, info_name="hdrmerge-cli")
    if page == "hdrmerge-cli":
        ctx = root
        texts = [(f"{name} summary", click_man_core.get_short_help_str(cli.get_command(root, name)))
                 for name in COMMANDS]
    else:
        ctx = click.Context(cli.get_command(root, page), info_name=page, parent=root)
        texts = []
    cmd = ctx.command
    texts.append(("description", inspect.cleandoc(cmd.help or "")))
    for param in cmd.params:
        if isinstance(param, click.Option) and not param.hidden:
            record = param.get_help_record(ctx)
            if record:
                texts += [(f"option {record[0]}", record[0]), (f"{record[0]} help", record[1])]
    return [(what, text) for what, text in texts if text.strip()]


def _squash(text: str) -> str:
    """Without whitespace: immune to filling, justification and breaks after hyphens."""
    return re.sub(r"\s+", "", text)


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    """The pages ``make man`` would write now."""
    from hdrmerge_cli.manpages import write

    out = tmp_path_factory.mktemp("man")
    write(str(out))
    return out


def test_pages_are_up_to_date(generated):
    assert sorted(p.name for p in generated.glob("*.1")) == sorted(p.name for p in MAN.glob("*.1")), \
        "the set of man pages changed: run make man"
    for new in generated.glob("*.1"):
        assert (MAN / new.name).read_text() == new.read_text(), f"man/{new.name} is out of date: run make man"


# --- without groff ------------------------------------------------------------------

def _bad_control_lines(source: str) -> list[str]:
    """Lines roff would take for a request that is not a man macro (their text is lost)."""
    bad = []
    for line in source.splitlines():
        if line.startswith("'"):
            bad.append(line)
        elif line.startswith(".") and not line.startswith('.\\"'):
            name = line[1:].split(maxsplit=1)[0] if line[1:].strip() else ""
            if name and name not in KNOWN_MACROS:
                bad.append(line)
    return bad


def _text_of_source(source: str) -> str:
    """The page's text lines with the escapes click-man and hdrmerge_cli.manpages use
    undone (macro lines dropped): what a reader sees, give or take layout."""
    text = "\n".join(line for line in source.splitlines() if not re.match(r"[.']", line))
    for escape, char in ((r"\&", ""), (r"\-", "-"), (r"\fB", ""), (r"\fP", ""), (r"\e", "\\")):
        text = text.replace(escape, char)
    return text


@pytest.mark.parametrize("page", PAGES)
def test_no_help_line_is_read_as_a_request(page, generated):
    for where in (MAN, generated):
        source = (where / _page_path(page).name).read_text()
        bad = _bad_control_lines(source)
        assert not bad, f"{_page_path(page).name}: roff would drop these lines: {bad} (escape with \\&)"
        text = _squash(_text_of_source(source))
        for what, expected in _expected_texts(page):
            assert _squash(expected) in text, f"{what} missing from {_page_path(page).name}"


def test_escaping_keeps_dots_quotes_and_backslashes(tmp_path):
    from hdrmerge_cli.manpages import _escaped_man_page_class, roff_escape

    assert roff_escape(".x\n'y\n a.\\b") == "\\&.x\n\\&'y\n a.\\eb"

    @click.command(help=".SH not a heading\n'quoted' start\n\nC:\\path and \\fB not bold")
    @click.option("--opt", help=".PP\n'a' b \\n")
    def demo(opt):
        pass

    with mock.patch.object(click_man_core, "ManPage", _escaped_man_page_class()):
        source = click_man_core.generate_man_page(click.Context(demo, info_name="demo"), version="1", date="x")
    assert not _bad_control_lines(source)
    assert source.count("\n.SH ") + source.startswith(".SH ") == 4  # NAME SYNOPSIS DESCRIPTION OPTIONS
    page = tmp_path / "demo.1"
    page.write_text(source)
    if _renderer():
        text, warnings = _render(page)
        assert not warnings
        for expected in (".SH not a heading", "'quoted' start", "C:\\path and \\fB not bold", ".PP 'a' b \\n"):
            assert expected in text


# --- rendered by groff / man --------------------------------------------------------

def _renderer():
    if shutil.which("groff"):
        return "groff"
    if shutil.which("man"):
        return "man"
    return None


def _render(path: Path) -> tuple[str, str]:
    """(plain text as a reader sees it, warnings) for the page at ``path``."""
    if _renderer() == "groff":
        cmd = ["groff", "-man", "-Tutf8", "-ww", "-rLL=200n", "-rHY=0", "-P-c", "-P-b", "-P-u", "-P-o", str(path)]
        env = None
    else:
        import os

        cmd = ["man", "--warnings", "--nh", "--nj", "-l", str(path)]
        env = os.environ | {"MANWIDTH": "200", "MAN_KEEP_FORMATTING": "", "MANPAGER": "cat", "PAGER": "cat"}
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, check=True)
    text = re.sub(r"\x1b\[[0-9;]*m", "", proc.stdout)  # SGR, if the device used it anyway
    text = re.sub(r".\x08", "", text)  # overstrike bold/underline
    return text.translate(_UTF8_BACK), proc.stderr.strip()


needs_roff = pytest.mark.skipif(_renderer() is None, reason="neither groff nor man is installed")


@needs_roff
@pytest.mark.parametrize("page", PAGES)
def test_rendered_page_shows_all_help_without_warnings(page):
    path = _page_path(page)
    text, warnings = _render(path)
    assert not warnings, f"{path.name}: {warnings}"
    rendered = _squash(text)
    for what, expected in _expected_texts(page):
        assert _squash(expected) in rendered, f"{what} not rendered from {path.name}: {expected[:60]!r}..."


@pytest.mark.parametrize("command", COMMANDS)
def test_every_option_in_help_output_is_on_the_page(run, command):
    """Against the installed command's own --help, not just the click objects."""
    opts = set(re.findall(r"(?<![\w-])--[a-z0-9][a-z0-9-]*", run(command, "--help").stdout)) - {"--help"}
    assert opts
    text = _text_of_source(_page_path(command).read_text())
    missing = sorted(o for o in opts if o not in text)
    assert not missing, f"{missing} missing from man/{_page_path(command).name}: run make man"
