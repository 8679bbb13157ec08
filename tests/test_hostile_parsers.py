"""Hostile input to every parser of user values (command line, config, times file, CSV CRF
table, profile JSON): a checked value or a one-line HdrMergeError naming the option or
file, never another exception, a traceback or a hang, and nothing written."""
import json
import math
import traceback

import click
import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given, settings, strategies as st

from conftest import frames_of
from hdrmerge_cli.cli.options import FiniteFloatRange
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.io.crfspec import read_crf_csv
from hdrmerge_cli.io.noisespec import NOISE_RANGES, noise_from_profile, parse_bounds, parse_noise
from hdrmerge_cli.io.profile import KIND, crf_from_json, load_profile
from hdrmerge_cli.io.times import MAX_SECONDS, MIN_SECONDS, parse_number, parse_times, read_times_file

PROFILE = {"schema": 1, "kind": KIND, "crf": {"model": "srgb"}}


def _profile(**entries) -> str:
    return json.dumps(PROFILE | entries)


NOISE_OK = {"ISO100": {"R": {"sigma_o2": 4, "alpha": 1}}}
CRF_TABLE = {"model": "table", "inverse": [[0, 0.5, 1], [0, 1]]}
DEEP = '{"a":' * 200000 + "1" + "}" * 200000

#: name -> (arguments, files to write, exit code, words of the message); ``{IMG}`` is the
#: bracket's frames, ``{D}/`` the test's folder
CLI_CASES = {
    "times overflow": (["merge", "{IMG}", "--times", "1e400,1,2"], {}, 2, ["--times", "1e400"]),
    "times huge exponent": (["merge", "{IMG}", "--times", "1e999999999,1,2"], {}, 2, ["--times", "1e999999999"]),
    "simulate times": (["simulate", "--size", "16x16", "--frames", "2", "--times", "1e400,1"], {}, 2, ["--times"]),
    "times file duplicate": (["merge", "{IMG}", "--times-file", "{D}/t.txt"],
                             {"t.txt": "frame_00.jpg 1/100\nframe_01.jpg 0.1\nframe_00.jpg 1\nframe_02.jpg 1\n"}, 1,
                             ["t.txt:3", "frame_00.jpg", "twice"]),
    "noise nan": (["merge", "{IMG}", "--noise", "sigma_o2=nan,alpha=1"], {}, 1, ["--noise", "sigma_o2", "nan"]),
    "noise empty": (["merge", "{IMG}", "--noise", ""], {}, 1, ["--noise", "empty"]),
    "bounds zero": (["merge", "{IMG}", "--weights", "bounded", "--bounds", "inv_alpha=0,sigma_o2=0"], {}, 1,
                    ["--bounds", "inv_alpha"]),
    "profile NaN noise": (["merge", "{IMG}", "--profile", "{D}/p.json"],
                          {"p.json": _profile(noise={"ISO100": {"R": {"sigma_o2": math.nan, "alpha": 1}}})}, 1,
                          ["p.json", "NaN"]),
    "profile string noise": (["merge", "{IMG}", "--profile", "{D}/p.json"],
                             {"p.json": _profile(noise={"ISO100": "loud"})}, 1, ["p.json", "ISO100"]),
    "profile nested deep": (["merge", "{IMG}", "--profile", "{D}/p.json"], {"p.json": DEEP}, 1, ["p.json", "nested"]),
    "profile ragged CRF": (["merge", "{IMG}", "--crf", "{D}/p.json"], {"p.json": _profile(crf=CRF_TABLE)}, 1,
                           ["p.json", "crf/inverse"]),
    "csv huge z": (["merge", "{IMG}", "--crf", "{D}/c.csv"], {"c.csv": "z,linear\n0,0\n1e300,1\n"}, 1,
                   ["c.csv:3", "z"]),
    "csv nan": (["merge", "{IMG}", "--crf", "{D}/c.csv"], {"c.csv": "z,linear\n0,0\n255,nan\n"}, 1,
                ["c.csv:3", "nan"]),
    "lambda nan": (["estimate-crf", "{IMG}", "--lambda", "nan"], {}, 2, ["--lambda", "finite"]),
    "config not UTF-8": (["merge", "{IMG}", "--config", "{D}/c.toml"], {"c.toml": b"\xff\xfe = 1\n"}, 2,
                         ["--config", "c.toml", "UTF-8"]),
}


def _write(path, content):
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    return str(path)


#: cases also run through the installed command (a subprocess: ~1.5 s each, mostly imports)
SUBPROCESS = ("times overflow", "times file duplicate", "noise empty", "profile nested deep", "config not UTF-8")


def _invoke(how, run, argv):
    """(exit code, stderr) of ``hdrmerge-cli argv``: the installed command in a subprocess,
    or the same click group in this process (an uncaught exception becomes a traceback)."""
    if how == "subprocess":
        proc = run(*argv, check=False)
        return proc.returncode, proc.stderr
    from hdrmerge_cli.cli import cli

    result = CliRunner().invoke(cli, [str(a) for a in argv], prog_name="hdrmerge-cli")
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        return 99, "Traceback: " + "".join(traceback.format_exception(*result.exc_info))
    return result.exit_code, result.stderr


@pytest.mark.parametrize("name, how", [(n, "in-process") for n in CLI_CASES] + [(n, "subprocess") for n in SUBPROCESS])
def test_cli_refuses_hostile_values_in_one_line(run, tmp_path, jpeg_bracket, name, how):
    args, files, code, words = CLI_CASES[name]
    for fname, content in files.items():
        _write(tmp_path / fname, content)
    frames = [str(p) for p in frames_of(*jpeg_bracket)]
    out = tmp_path / {"merge": "out.exr", "estimate-crf": "out.json"}.get(args[0], "out")
    argv = [a for arg in args for a in (frames if arg == "{IMG}" else [arg.replace("{D}", str(tmp_path))])]
    returncode, stderr = _invoke(how, run, argv + ["-o", out])
    assert returncode == code, stderr
    assert "Traceback" not in stderr
    errors = [ln for ln in stderr.splitlines() if ln.startswith(("Error:", "hdrmerge-cli: error:"))]
    assert len(errors) == 1, stderr
    if code == 1:
        assert [ln for ln in stderr.strip().splitlines() if "warning" not in ln] == errors, stderr
    for word in words:
        assert word in errors[0], stderr
    assert not out.exists() and not list(tmp_path.glob("out*"))


# ---------------------------------------------------------------- parser functions, in process
@pytest.mark.parametrize("text, words", [
    ("1e400", ["1e400", "between"]), ("1e999999999", ["between"]), ("nan", ["nan"]), ("inf", ["inf"]),
    ("1/0", ["1/0"]), ("0x10", ["0x10"]), ("1_000", ["1_000"]), ("1e-400", ["between"]), ("", ["no exposure"]),
    ("2e6", ["between"]),
])
def test_bad_times(text, words):
    with pytest.raises(HdrMergeError) as exc:
        parse_times(text)
    assert all(w in str(exc.value) for w in words)


@pytest.mark.parametrize("content, words", [
    ("a.jpg 1\nb.jpg 2\na.jpg 3\n", ["t.txt:3", "a.jpg", "twice", "line 1"]),
    ("a.jpg 1e400\n", ["t.txt:1", "1e400"]),
    (b"a.jpg \xff1\n", ["t.txt", "UTF-8"]),
    ("a.jpg 1 2\n", ["t.txt:1", "name seconds"]),
])
def test_bad_times_files(tmp_path, content, words):
    path = _write(tmp_path / "t.txt", content)
    with pytest.raises(HdrMergeError) as exc:
        read_times_file(path)
    assert all(w in str(exc.value) for w in words)


@pytest.mark.parametrize("text, words", [
    ("sigma_o2=nan,alpha=1", ["--noise", "sigma_o2", "nan"]), ("sigma_o2=1,alpha=1,beta=nan", ["beta"]),
    ("sigma_o2=1,alpha=inf", ["alpha"]), ("sigma_o2=1,alpha=1e400", ["alpha"]), ("", ["empty"]),
    ("sigma_o2=1,alpha=0", ["alpha"]), ("sigma_o2=-1,alpha=1", ["sigma_o2"]), ("sigma_o2=1", ["alpha"]),
    ("sigma_o2=1,alpha=1,alpha=2", ["twice"]), ("R:sigma_o2=1,alpha=1 r:sigma_o2=1,alpha=1", ["R", "twice"]),
    ("a:b:sigma_o2=1,alpha=1", ["channel"]),
])
def test_bad_noise(text, words):
    with pytest.raises(HdrMergeError) as exc:
        parse_noise(text)
    assert all(w in str(exc.value) for w in words)


@pytest.mark.parametrize("text, words", [
    ("inv_alpha=0,sigma_o2=0", ["inv_alpha"]), ("sigma_o2=nan", ["sigma_o2"]), ("inv_alpha=inf", ["inv_alpha"]),
    ("beta=-1", ["beta"]), ("delta=1", ["delta"]), ("delta=0.1", ["exactly one"]), ("", ["--bounds"]),
    ("inv_alpha=1,inv_alpha=2", ["twice"]),
])
def test_bad_bounds(text, words):
    with pytest.raises(HdrMergeError) as exc:
        parse_bounds(text)
    assert all(w in str(exc.value) for w in words)


@pytest.mark.parametrize("content, words", [
    ("z,linear\n0,0\n1e300,1\n", ["c.csv:3", "0..65535"]), ("z,linear\n0,0\n255,inf\n", ["c.csv:3", "inf"]),
    ("z,linear\n0,0\n128,0.5,0.5\n255,1\n", ["c.csv:3", "columns"]), ("z,linear\n0,0\n", ["at least two"]),
    ("0,0\n10,1\n5,1\n", ["c.csv:3", "increase"]), ("z,linear\n0,0\n2.5,1\n", ["integer"]),
    ("0,0\n-1,1\n", ["c.csv:2", "-1"]), ("0,0.5\n10,0.2\n", ["monotone"]), (b"0,0\n\xff,1\n", ["UTF-8"]),
    ("z,linear\nz,linear\n0,0\n1,1\n", ["c.csv:2"]),
])
def test_bad_crf_csv(tmp_path, content, words):
    path = _write(tmp_path / "c.csv", content)
    with pytest.raises(HdrMergeError) as exc:
        read_crf_csv(path)
    assert all(w in str(exc.value) for w in words), exc.value


@pytest.mark.parametrize("content, words", [
    (_profile(noise={"ISO100": {"R": {"sigma_o2": math.inf, "alpha": 1}}}), ["Infinity"]),
    (_profile(noise=NOISE_OK).replace("4", "1e400"), ["1e400", "out of range"]),
    (_profile(noise=NOISE_OK).replace("4", "1" * 5000), ["too long"]),
    (_profile(crf=CRF_TABLE), ["crf/inverse", "[2, 3]"]),
    (_profile(crf={"model": "table", "inverse": [[0, 1]] * 5}), ["crf/inverse"]),
    (_profile(crf={"model": "table", "inverse": [[0.5, 0.2]]}), ["monotone"]),
    (DEEP, ["nested"]), ("[" * 65 + "]" * 65, ["nested"]),
    ('{"schema": 1, "schema": 1}', ["twice"]),
    (b"\xff\xfe{}", ["UTF-8"]), ("{", ["not JSON"]), ("5", ["not a valid profile"]),
])
def test_bad_profiles(tmp_path, content, words):
    path = _write(tmp_path / "p.json", content)
    with pytest.raises(HdrMergeError) as exc:
        load_profile(path)
    assert "p.json" in str(exc.value) and all(w in str(exc.value) for w in words), exc.value


@pytest.mark.parametrize("noise, words", [
    ({"ISO100": "loud"}, ["ISO100"]), ({"ISO100": {"R": "loud"}}, ["'ISO100'", "'R'"]),
    ({"ISO100": {"R": {"sigma_o2": "4", "alpha": 1}}}, ["sigma_o2", "number"]),
    ({"ISO100": {"R": {"sigma_o2": True, "alpha": 1}}}, ["sigma_o2"]),
    ({"ISO100": {"R": {"sigma_o2": 4}}}, ["alpha", "missing"]), ({"ISO100": {}}, ["ISO100"]),
    ({"ISO100": {"R": {"sigma_o2": 4, "alpha": 1e300}}}, ["alpha"]),
])
def test_bad_profile_noise(tmp_path, noise, words):
    path = _write(tmp_path / "p.json", _profile(noise=noise))
    with pytest.raises(HdrMergeError) as exc:
        noise_from_profile(load_profile(path), 100, path)
    assert "p.json" in str(exc.value) and all(w in str(exc.value) for w in words), exc.value


def test_good_values_still_parse(tmp_path):
    assert parse_times("1/100, 1/25,0.5,2s") == [0.01, 0.04, 0.5, 2.0]
    assert parse_noise("R:sigma_o2=4,alpha=1 G:sigma_o2=3,alpha=1,beta=0")["G"].sigma_o2 == 3
    assert parse_bounds("inv_alpha=0.005,sigma_o2=0.02,beta=0") == (0.005, 0.02, 0.0)
    path = _write(tmp_path / "p.json", "\ufeff" + _profile(noise=NOISE_OK))
    assert noise_from_profile(load_profile(path), 100, path)["R"].alpha == 1
    assert read_crf_csv(_write(tmp_path / "c.csv", "# measured\nz, R, G, B\n0,0,0,0\n255,1,1,1\n")).table.shape == (3, 256)


@pytest.mark.parametrize("text", ["nan", "inf", "-inf", "1e400"])
def test_finite_float_option_type(text):
    for kind in (FiniteFloatRange(), FiniteFloatRange(min=0), FiniteFloatRange(0.5, 10)):
        with pytest.raises(click.BadParameter):
            kind.convert(text, None, None)
    assert FiniteFloatRange(min=0).convert("2.5", None, None) == 2.5


# ---------------------------------------------------------------- property-based: garbage in
NUMBERISH = st.one_of(
    st.floats().map(repr), st.integers(-10**30, 10**30).map(str),
    st.sampled_from(["nan", "inf", "-inf", "1e400", "1e999999999", "1/0", "0x10", "1_0", "", " ", "1/3", "1e-400",
                     "1e308/1e-308", "0", "-0", "2\"", "5s", "١"]),
    st.from_regex(r"[0-9eE+\-./\"s ]{0,24}", fullmatch=True),
)
GARBAGE = st.one_of(st.text(max_size=60), NUMBERISH)
HYP = settings(max_examples=200, deadline=None)


def _checked(fn, *args):
    """fn(*args), or None if it raised HdrMergeError (any other exception fails the test)."""
    try:
        return fn(*args)
    except HdrMergeError as exc:
        assert "\n" not in str(exc)
        return None


@HYP
@given(st.one_of(GARBAGE, st.lists(NUMBERISH, max_size=6).map(",".join)))
def test_times_parser_never_crashes(text):
    times = _checked(parse_times, text)
    assert times is None or (times and all(MIN_SECONDS <= t <= MAX_SECONDS for t in times))


@HYP
@given(GARBAGE)
def test_number_parser_never_crashes(text):
    value = _checked(parse_number, text)
    assert value is None or math.isfinite(value)


KEYS = st.sampled_from(["sigma_o2", "alpha", "beta", "delta", "inv_alpha", "x", ""])
VALUES = st.one_of(NUMBERISH, st.floats(0, 2e3).map(repr), st.floats(0, 1).map(repr))
ASSIGNMENTS = st.lists(st.tuples(KEYS, VALUES).map("=".join), min_size=1, max_size=4).map(",".join)


def _in_range(params):
    return all(lo <= getattr(params, k) <= hi for k, (lo, hi) in NOISE_RANGES.items())


@HYP
@given(st.one_of(GARBAGE, st.lists(st.tuples(st.sampled_from(["", "R:", "g2:", "*:", "1:", "R:G:", ":"]), ASSIGNMENTS)
                                   .map("".join), max_size=3).map(" ".join)))
def test_noise_parser_never_crashes(text):
    noise = _checked(parse_noise, text)
    assert noise is None or (noise and all(_in_range(p) for p in noise.values()))


BOUNDS_TEXT = st.dictionaries(st.sampled_from(["inv_alpha", "sigma_o2", "beta", "delta"]), VALUES, min_size=1).map(
    lambda d: ",".join(f"{k}={v}" for k, v in d.items()))


@HYP
@given(st.one_of(GARBAGE, ASSIGNMENTS, BOUNDS_TEXT))
def test_bounds_parser_never_crashes(text):
    bounds = _checked(parse_bounds, text)
    if bounds is not None:
        inv_alpha, sigma_o2, beta = bounds
        assert all(math.isfinite(b) for b in bounds) and inv_alpha > 0 and sigma_o2 > 0 and beta >= 0


@pytest.fixture(scope="module")
def scratch(tmp_path_factory):
    return tmp_path_factory.mktemp("hostile")


CSV_TEXT = st.lists(st.lists(NUMBERISH, min_size=1, max_size=5).map(",".join), max_size=6).map("\n".join)


@st.composite
def csv_tables(draw):
    """Mostly sensible tables (sorted codes and values), with a few cells made hostile."""
    n, width = draw(st.integers(0, 6)), draw(st.integers(1, 4))
    codes = sorted(draw(st.lists(st.integers(-1, 70000), min_size=n, max_size=n)))
    values = sorted(draw(st.lists(st.floats(0, 1e6), min_size=n * width, max_size=n * width)))
    rows = [[str(z)] + [repr(v) for v in values[i * width:(i + 1) * width]] for i, z in enumerate(codes)]
    for _ in range(draw(st.integers(0, 2)) if rows else 0):
        row = draw(st.sampled_from(rows))
        row[draw(st.integers(0, len(row) - 1))] = draw(NUMBERISH)
    return "z,linear\n" + "\n".join(",".join(row) for row in rows)


@HYP
@given(st.one_of(st.binary(max_size=200), CSV_TEXT.map(str.encode), csv_tables().map(str.encode)))
def test_crf_csv_parser_never_crashes(scratch, content):
    crf = _checked(read_crf_csv, _write(scratch / "c.csv", content))
    if crf is not None:
        tab = crf.table
        assert tab.shape[1] >= 2 and np.all(np.isfinite(tab)) and np.all(np.diff(tab, axis=1) >= 0)


@HYP
@given(st.one_of(st.binary(max_size=200), st.lists(st.tuples(st.text(max_size=10), NUMBERISH).map(" ".join),
                                                   max_size=5).map(lambda ls: "\n".join(ls).encode(errors="replace"))))
def test_times_file_parser_never_crashes(scratch, content):
    times = _checked(read_times_file, _write(scratch / "t.txt", content))
    assert times is None or all(MIN_SECONDS <= t <= MAX_SECONDS for t in times.values())


JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.floats() | st.integers() | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=20,
)
NOISE_ENTRY = st.dictionaries(st.sampled_from(["sigma_o2", "alpha", "beta", "x"]), JSON_VALUES | st.floats(), max_size=4)
PROFILES = st.builds(
    lambda crf, noise: json.dumps(PROFILE | {"crf": crf, "noise": noise}).encode(),
    st.one_of(JSON_VALUES, st.sampled_from([{"model": "srgb"}, {"model": "gamma", "gamma": 2.2}, CRF_TABLE]),
              st.builds(lambda rows: {"model": "table", "inverse": rows},
                        st.lists(st.lists(st.floats() | st.integers(), max_size=5), max_size=5))),
    st.one_of(JSON_VALUES, st.dictionaries(st.sampled_from(["ISO100", "ISO_unknown", "x"]),
                                           JSON_VALUES | st.dictionaries(st.sampled_from(["R", "G"]), NOISE_ENTRY))),
)


@HYP
@given(st.one_of(st.binary(max_size=200), PROFILES, PROFILES.map(lambda b: b[: len(b) // 2])))
def test_profile_loader_never_crashes(scratch, content):
    path = _write(scratch / "p.json", content)
    profile = _checked(load_profile, path)
    if profile is not None:
        assert crf_from_json(profile["crf"], path) is not None
        if isinstance(profile.get("noise"), dict) and profile["noise"]:
            noise = _checked(noise_from_profile, profile, 100, path)
            assert noise is None or all(_in_range(p) for p in noise.values())
