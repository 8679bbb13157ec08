"""merge --batch: grouping, local processes, a Dask LocalCluster, failures and skips."""
import dataclasses
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from conftest import SHARED, frames_of, needs_shared
from hdrmerge_cli.io.frames import Frame
from hdrmerge_cli.pipeline.batch import DEFAULT_GAP, capture_seconds, split_brackets


def group_brackets(frames, gap=DEFAULT_GAP, thumbnail=None):
    """The frames of each bracket of :func:`split_brackets`."""
    return [b.frames for b in split_brackets(frames, gap, thumbnail)]

ROOT = Path(__file__).resolve().parents[1]


def _frame(name, t, stamp=None, width=4):
    return Frame(path=f"/x/{name}", kind="raw", width=width, height=4, exposure_time=t, iso=100.0, aperture=None,
                 make="Cam", model="One", timestamp=stamp, bits=12, n_codes=65536, black=np.zeros(4),
                 white=np.full(4, 4095.0), channels=4, cfa_pattern="RGGB")


def test_capture_seconds_reads_iso_and_exif_stamps():
    assert capture_seconds("2024-05-01T10:00:03") - capture_seconds("2024:05:01 10:00:00") == 3.0
    assert capture_seconds(None) is None and capture_seconds("yesterday") is None


def test_groups_split_at_time_gaps_repeated_exposures_and_layout_changes():
    s = "2024-05-01T10:00:{:02d}"
    frames = [
        _frame("a1", 1 / 100, s.format(0)), _frame("a2", 1 / 25, s.format(1)), _frame("a3", 1 / 6, s.format(2)),
        _frame("b1", 1 / 100, s.format(30)), _frame("b2", 1 / 25, s.format(31)),  # 28 s later
        _frame("c1", 1 / 100, s.format(32)), _frame("c2", 1 / 400, s.format(33)),  # 1/100 again: a new sequence
        _frame("d1", 1 / 50, s.format(34), width=8),  # another image size
    ]
    groups = group_brackets(list(reversed(frames)), gap=3.0)
    assert [[f.path[3:] for f in g] for g in groups] == [["a1", "a2", "a3"], ["b1", "b2"], ["c1", "c2"], ["d1"]]


def test_without_timestamps_the_exposure_sequence_decides():
    frames = [_frame(n, t) for n, t in [("f1", 0.01), ("f2", 0.04), ("f3", 0.01), ("f4", 0.04), ("f5", 0.16)]]
    assert [len(g) for g in group_brackets(frames)] == [2, 3]


def test_the_gap_counts_from_the_end_of_the_previous_exposure():
    """A 30 s frame starting 9 s after an 8 s frame began follows 1 s after it ended."""
    s = "2024-05-01T10:00:{:02d}"
    frames = [_frame("f1", 1.0, s.format(0)), _frame("f2", 8.0, s.format(1)), _frame("f3", 30.0, s.format(10))]
    assert [len(g) for g in group_brackets(frames, gap=3.0)] == [3]


def test_a_descending_sequence_that_turns_back_has_restarted():
    times = [0.16, 0.04, 0.01, 0.0025]  # then again half a stop longer: no time repeats
    frames = [_frame(f"f{k}", t) for k, t in enumerate(times + [t * 1.5 for t in times])]
    assert [len(g) for g in group_brackets(frames)] == [4, 4]


def _tagged(name, t, iso, bias, stamp, auto=True):
    """An 8-bit image frame of a compact camera's auto-bracket mode (EXIF ExposureMode 2)."""
    return Frame(path=f"/x/{name}", kind="image", width=4, height=4, exposure_time=t, iso=iso, aperture=2.8,
                 make="Cam", model="Compact", timestamp=stamp, bits=8, n_codes=256, black=np.zeros(3),
                 white=np.full(3, 255.0), channels=3, auto_bracket=auto, exposure_bias=bias)


def test_the_cameras_bracketing_tags_decide_and_exposures_not_times_restart():
    """A compact camera's folder: a single shot, an aborted 2-frame auto bracket, two whole
    5-frame auto brackets (compensation 0, -0.7, +0.7, -1.3, +1.3; the camera changes ISO
    inside a bracket, so an exposure time repeats; frames up to 8 s apart) and a single shot.
    The tags give the brackets whole; the singles and the aborted one apart."""
    s = "2024-05-01T10:{:02d}:{:02d}"
    biases = (0.0, -0.7, 0.7, -1.3, 1.3)
    times = (1 / 30, 1 / 30, 1 / 30, 1 / 60, 1 / 15)
    isos = (6400, 4000, 10000, 4000, 6400)

    def bracket(tag, minute, n=5, start=0):
        return [_tagged(f"{tag}{k}", times[k], isos[k], biases[k], s.format(minute, start + 8 * k)) for k in range(n)]

    frames = ([_tagged("single1", 1 / 30, 6400, 0.0, s.format(0, 0), auto=False)] + bracket("aborted", 1, 2)
              + bracket("one", 1, start=20) + bracket("two", 5) + [_tagged("single2", 1 / 30, 6400, 0.0, s.format(9, 0),
                                                                           auto=False)])
    groups = group_brackets(frames, gap=3.0, thumbnail=lambda f: pytest.fail("no scene test is needed"))
    assert [[f.path[3:] for f in g] for g in groups] == [
        ["single1"], ["aborted0", "aborted1"], [f"one{k}" for k in range(5)], [f"two{k}" for k in range(5)],
        ["single2"]]


def test_a_changed_iso_is_a_new_exposure_not_a_restart():
    """Untagged frames: 1/30 s at ISO 6400 then 1/30 s at ISO 1600 are two exposures 2 stops
    apart, so the sequence goes on; the same time and ISO again restarts it."""
    f = [_frame("a", 1 / 30), _frame("b", 1 / 30), _frame("c", 1 / 30), _frame("d", 1 / 30)]
    for frame, iso in zip(f, (6400, 1600, 400, 6400)):
        frame.iso = float(iso)
    assert [len(g) for g in group_brackets(f)] == [3, 1]


def test_files_the_tool_wrote_and_files_without_a_time_are_left_out(run, tmp_path, dng_bracket):
    """A merge's preview written into the bracket's folder, and a PNG without EXIF: left out
    with a warning naming each; the bracket merges."""
    import OpenImageIO as oiio

    folder, meta = dng_bracket
    shoot = tmp_path / "shoot"
    shoot.mkdir()
    for p in frames_of(folder, meta)[:3]:
        shutil.copy(p, shoot / Path(p).name)
    run("merge", *sorted(shoot.glob("*.dng")), "-o", tmp_path / "one.exr", "--preview", shoot / "preview.jpg")
    buf = oiio.ImageBuf(oiio.ImageSpec(8, 8, 3, oiio.UINT8))
    buf.write(str(shoot / "notes.png"))
    proc = run("merge", "--batch", shoot, "-o", tmp_path / "out", "--json")
    assert json.loads(proc.stdout)["merged"] == 1
    assert "preview.jpg: written by hdrmerge-cli" in proc.stderr and "left out of the batch" in proc.stderr
    assert "notes.png: no exposure time" in proc.stderr


def _scene(seed, height=160, width=240):
    """A smooth random irradiance field about 14 stops deep, one per seed."""
    from scipy.ndimage import gaussian_filter

    field = gaussian_filter(np.random.default_rng(seed).standard_normal((height, width)), 4)
    return 2.0 ** (2.5 * (field - field.mean()) / field.std())


def _write_jpeg(path, irradiance, t, stamp, size=None):
    """An sRGB JPEG of ``irradiance * t`` with EXIF ExposureTime, DateTimeOriginal and a
    camera (grey, or the given RGB codes resized to ``size``)."""
    import OpenImageIO as oiio

    if irradiance.ndim == 2:
        v = np.clip(irradiance * t, 0, 1)
        v = np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055)
        pixels = np.repeat((v * 255 + 0.5).astype(np.uint8)[..., None], 3, axis=2)
    else:
        import cv2

        pixels = cv2.resize(irradiance, size, interpolation=cv2.INTER_AREA)
    spec = oiio.ImageSpec(pixels.shape[1], pixels.shape[0], 3, oiio.UINT8)
    for key, value in (("ExposureTime", float(t)), ("Exif:DateTimeOriginal", stamp), ("Make", "Cam"),
                       ("Model", "One"), ("Compression", "jpeg:90")):
        spec.attribute(key, value)
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), spec)
    out.write_image(pixels)
    out.close()


def test_structure_correlation_ignores_response_exposure_and_a_one_pixel_shift():
    from hdrmerge_cli.core.similarity import same_scene, structure_correlation

    scene = _scene(1, 96, 144)[::3, ::3]  # a 32 x 48 thumbnail
    dark = np.clip(scene / 16, 0, 1) ** (1 / 2.2)
    bright = np.clip(np.roll(scene, 1, axis=1), 0, 1) ** 0.3  # 4 stops up, another response, shifted
    r, n = structure_correlation(dark, bright, 8 / 255, 247 / 255)
    assert same_scene(r, n) and r > 0.9
    other = np.clip(_scene(2, 96, 144)[::3, ::3] / 16, 0, 1) ** (1 / 2.2)
    r, n = structure_correlation(dark, other, 8 / 255, 247 / 255)
    assert not same_scene(r, n) and abs(r) < 0.3 and n > 500
    assert structure_correlation(np.zeros((8, 8)), np.zeros((8, 8)), 0.1, 0.9)[1] == 0  # nothing well exposed


def test_frames_far_apart_join_on_the_same_scene_and_split_on_another(run, tmp_path):
    """Three frames of one scene shot 10 s apart stay one bracket; three of another scene 6 s
    later (their times going on up: only the content tells) are a second; a last frame of a
    third scene is a bracket of one, warned about with why it was cut off."""
    shoot = tmp_path / "shoot"
    shoot.mkdir()
    stamp = "2024:05:01 10:{:02d}:{:02d}"
    shots = [("a", 1, [1 / 100, 1 / 25, 1 / 6], 0), ("b", 2, [0.4, 1.0, 2.5], 26), ("c", 3, [6.0], 54)]
    for prefix, seed, times, start in shots:
        for k, t in enumerate(times):
            at = start + 10 * k
            _write_jpeg(shoot / f"{prefix}{k}.jpg", _scene(seed), t, stamp.format(at // 60, at % 60))
    proc = run("merge", "--batch", shoot, "-o", tmp_path / "out", "--dry-run", "--json")
    brackets = json.loads(proc.stdout)["brackets"]
    assert [[Path(p).name for p in e["frames"]] for e in brackets] == [
        ["a0.jpg", "a1.jpg", "a2.jpg"], ["b0.jpg", "b1.jpg", "b2.jpg"], ["c0.jpg"]]
    assert [j["frame"] for j in brackets[0]["joined"]] == ["a1.jpg", "a2.jpg"]
    assert "a different scene" in brackets[1]["reason"] and "after a2.jpg's exposure ended" in brackets[1]["reason"]
    warning = [line for line in proc.stderr.splitlines() if "c0.jpg" in line]
    assert len(warning) == 1 and "one frame" in warning[0] and "a different scene" in warning[0]
    listing = run("merge", "--batch", shoot, "-o", tmp_path / "out", "--dry-run").stdout
    assert "new bracket: 6 s after a2.jpg's exposure ended (more than --gap 3 s), and a different scene" in listing
    assert "kept together across long gaps, the same scene: 10 s before a1.jpg" in listing


def _frames_of_folder(folder):
    return [p for p in sorted(folder.iterdir()) if p.suffix.lower() in (".jpg", ".jpeg")]


def _shared_brackets():
    """The shared real brackets whose frames carry their exposure times (EXIF JPEGs; the
    film scan's PNGs take theirs from a file, which a folder of many brackets cannot)."""
    return sorted(p for p in (SHARED / "brackets").iterdir() if p.is_dir() and _frames_of_folder(p))


@needs_shared
def test_the_shared_brackets_in_one_folder_come_back_whole(run, tmp_path):
    """Every real bracket with EXIF times (tripod and hand-held; some shot 4-45 s apart) of
    the shared data, linked into one folder, is exactly one bracket."""
    shoot = tmp_path / "all"
    shoot.mkdir()
    for folder in _shared_brackets():
        for p in _frames_of_folder(folder):
            (shoot / f"{folder.name}__{p.name}").symlink_to(p)
    brackets = json.loads(run("merge", "--batch", shoot, "-o", tmp_path / "out", "--dry-run", "--json").stdout)
    got = sorted(sorted(Path(p).resolve() for p in e["frames"]) for e in brackets["brackets"])
    want = sorted(sorted(p.resolve() for p in _frames_of_folder(folder)) for folder in _shared_brackets())
    assert len(want) >= 10 and got == want


def _dry_run(run, folder, tmp_path) -> list[list[str]]:
    out = json.loads(run("merge", "--batch", folder, "-o", tmp_path / "out", "--dry-run", "--json").stdout)
    return [[Path(p).name for p in e["frames"]] for e in out["brackets"]]


@needs_shared
def test_three_brackets_shot_by_hand_come_back_whole(run, tmp_path):
    """Two LX100 brackets shot by hand (3-30 s between frames, one out of file-name order,
    4 minutes apart) and a Canon one: 3 brackets of 8, 9 and 3.  The scene test across each
    pause reads thumbnails large enough that neighbours 1 EV apart share enough
    well-exposed gradients."""
    groups = _dry_run(run, SHARED / "folders" / "handshot_three_brackets", tmp_path)
    assert sorted(len(g) for g in groups) == [3, 8, 9], groups
    assert all(len({name.split("_")[0] for name in g}) == 1 for g in groups), groups


@needs_shared
def test_an_aborted_auto_bracket_is_not_joined_to_the_retake(run, tmp_path):
    """An RX100 VI folder: single shots, an aborted 2-frame auto bracket, then two whole
    5-frame ones.  The retake's first frame lies inside the exposures the aborted one spans
    (a retake, not a sequence extending the range): both 5-frame brackets come back whole
    and nothing is joined to them."""
    groups = _dry_run(run, SHARED / "folders" / "rx100m6_autobracket", tmp_path)
    assert [f"DSC0{n}.JPG" for n in range(8196, 8201)] in groups, groups
    assert [f"DSC0{n}.JPG" for n in range(8201, 8206)] in groups, groups
    assert ["DSC08194.JPG", "DSC08195.JPG"] in groups, groups


@needs_shared
def test_two_real_scenes_of_one_camera_seconds_apart_are_two_brackets(run, tmp_path):
    """Two real kitchens written at one size as one camera's frames, the second bracket
    starting 5 s after the first ended with the exposure sequence going on down: split on
    the content."""
    import cv2

    brackets = SHARED / "brackets"
    first = [(p, t) for p, t in (("4.jpg", 1 / 6), ("5.jpg", 1 / 13), ("1.jpg", 1 / 15), ("2.jpg", 1 / 25),
                                 ("3.jpg", 1 / 40))]
    second = [("6.jpg", 1 / 60), ("7.jpg", 1 / 8), ("8.jpg", 1.0)]
    shoot = tmp_path / "shoot"
    shoot.mkdir()
    at = 0
    for k, (name, t) in enumerate(first):
        rgb = cv2.imread(str(brackets / "em1ii_kitchen_jpg" / name))[..., ::-1]
        _write_jpeg(shoot / f"img_{k:02d}.jpg", rgb, t, f"2024:05:01 10:00:{at:02d}", size=(480, 320))
        at += 2
    at += 5
    for k, (name, t) in enumerate(second, start=len(first)):
        rgb = cv2.imread(str(brackets / "eos70d_kitchen_jpg" / name))[..., ::-1]
        _write_jpeg(shoot / f"img_{k:02d}.jpg", rgb, t, f"2024:05:01 10:00:{at:02d}", size=(480, 320))
        at += 2
    s = json.loads(run("merge", "--batch", shoot, "-o", tmp_path / "out", "--dry-run", "--json").stdout)
    assert [len(e["frames"]) for e in s["brackets"]] == [5, 3]
    assert "a different scene" in s["brackets"][1]["reason"]


@pytest.fixture()
def shoot(tmp_path, dng_bracket):
    """A folder holding two brackets (the session bracket's frames 0-2 twice, renamed: no
    timestamps, so the repeated exposure sequence splits them) and one unreadable file."""
    folder, meta = dng_bracket
    paths = frames_of(folder, meta)
    shoot = tmp_path / "shoot"
    shoot.mkdir()
    for prefix, picks in (("a", paths[0:3]), ("b", paths[0:3])):
        for k, p in enumerate(picks):
            shutil.copy(p, shoot / f"{prefix}_{k}.dng")
    (shoot / "c_broken.dng").write_bytes(b"not raw")
    return shoot


def test_batch_merges_good_brackets_reports_the_bad_one_and_skips_done_ones(run, tmp_path, shoot):
    out = tmp_path / "merged"
    listing = run("merge", "--batch", shoot, "-o", out, "--dry-run").stdout
    assert listing.count("planned") == 2 and "c_broken.dng" in listing and not out.exists()

    proc = run("merge", "--batch", shoot, "-o", out, "-j", "2", "--json", check=False)
    assert proc.returncode == 1
    summary = json.loads(proc.stdout)
    assert (summary["merged"], summary["failed"], summary["skipped"]) == (2, 1, 0)
    assert sorted(p.name for p in out.glob("*.exr")) == ["a_0.exr", "b_0.exr"]
    assert "c_broken.dng" in proc.stderr and "1 of 3 brackets failed" in proc.stderr.splitlines()[-1]
    assert "Traceback" not in proc.stderr

    again = json.loads(run("merge", "--batch", shoot, "-o", out, "--skip-existing", "--json", check=False).stdout)
    assert (again["merged"], again["skipped"]) == (0, 2)


def test_batch_on_a_dask_local_cluster_with_a_profile(run, tmp_path, shoot):
    """One task per bracket on a LocalCluster (one-thread workers); the --profile is sent
    to the workers once (scatter, broadcast)."""
    distributed = pytest.importorskip("distributed")
    (shoot / "c_broken.dng").unlink()
    profile = tmp_path / "noise.json"
    first = sorted(shoot.glob("a_*.dng"))
    run("calibrate-noise", *first, "-o", profile)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        proc = run("merge", "--batch", shoot, "-o", tmp_path / "out", "--scheduler", cluster.scheduler_address,
                   "--profile", profile, "--weights", "probabilistic", "--json")
    summary = json.loads(proc.stdout)
    assert summary["merged"] == 2 and summary["failed"] == 0
    used = json.loads((tmp_path / "out" / "a_0.profile.json").read_text())["noise"]["used"]
    saved = json.loads(profile.read_text())["noise"]
    iso = next(iter(saved))
    assert used["R"]["sigma_o2"] == pytest.approx(saved[iso]["R"]["sigma_o2"])


def test_unreachable_scheduler_is_a_one_line_error(run, tmp_path, shoot):
    pytest.importorskip("distributed")
    proc = run("merge", "--batch", shoot, "-o", tmp_path / "o", "--scheduler", "tcp://127.0.0.1:1", check=False)
    assert proc.returncode == 1 and "scheduler" in proc.stderr and "Traceback" not in proc.stderr


@pytest.mark.parametrize("args, message", [
    (["-j", "2"], "apply to --batch only"),
    (["--gap", "5"], "apply to --batch only"),
    (["--preview-size", "100"], "--preview only"),
    (["--batch", "."], "not both"),
])
def test_batch_usage_errors(run, tmp_path, dng_bracket, args, message):
    folder, meta = dng_bracket
    proc = run("merge", *frames_of(folder, meta)[:2], "-o", tmp_path / "x.exr", *args, check=False)
    assert proc.returncode == 2 and message in proc.stderr


def test_batch_sample_config(run, tmp_path, shoot):
    (shoot / "c_broken.dng").unlink()
    cfg = ROOT / "sample_configs" / "batch.toml"
    s = json.loads(run("merge", "--config", cfg, "--batch", shoot, "-o", tmp_path / "m", "--json").stdout)
    assert s["merged"] == 2
    s = json.loads(run("merge", "--config", cfg, "--batch", shoot, "-o", tmp_path / "m", "--json").stdout)
    assert s["skipped"] == 2  # skip-existing = true in the config


def test_interleaved_raw_and_jpeg_frames_group_per_layout():
    """A RAW + JPEG folder sorted by name interleaves x.dng, x.jpg, ...: each layout keeps
    its own open bracket."""
    raw = [_frame(f"f{k}.dng", t) for k, t in enumerate((0.01, 0.04, 0.16))]
    jpg = [dataclasses.replace(_frame(f"f{k}.jpg", t), kind="image", channels=3, cfa_pattern=None)
           for k, t in enumerate((0.01, 0.04, 0.16))]
    groups = group_brackets([f for pair in zip(raw, jpg) for f in pair])
    assert sorted([f.path[3:] for f in g] for g in groups) == [["f0.dng", "f1.dng", "f2.dng"],
                                                              ["f0.jpg", "f1.jpg", "f2.jpg"]]


def test_brackets_never_share_an_output_name(run, tmp_path, dng_bracket, jpeg_bracket):
    shoot = tmp_path / "mixed"
    shoot.mkdir()
    for (folder, meta), ext in ((dng_bracket, "dng"), (jpeg_bracket, "jpg")):
        for k, p in enumerate(frames_of(folder, meta)[:3]):
            shutil.copy(p, shoot / f"x_{k}.{ext}")
    s = json.loads(run("merge", "--batch", shoot, "-o", tmp_path / "o", "--dry-run", "--json").stdout)
    outputs = [Path(e["output"]).name for e in s["brackets"]]
    assert sorted(outputs) == ["x_0.exr", "x_0_jpg.exr"] and all(Path(e["output"]).is_absolute() for e in s["brackets"])


def test_an_empty_folder_is_a_one_line_error_and_writes_nothing(run, tmp_path):
    (tmp_path / "empty").mkdir()
    proc = run("merge", "--batch", tmp_path / "empty", "-o", tmp_path / "out", check=False)
    assert proc.returncode == 1 and "no frames" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


@pytest.fixture(scope="module")
def big_shoot(tmp_path_factory, run):
    """Four brackets of 1600 x 1200 frames (no timestamps: split by the sequence), slow
    enough to merge that a signal arrives while they are being written."""
    big = tmp_path_factory.mktemp("bigshoot")
    run("simulate", "-o", big / "sim", "-q", "--size", "1600x1200", "--frames", "3", "--seed", "2")
    shoot = big / "shoot"
    shoot.mkdir()
    for prefix in "abcd":
        for k, p in enumerate(sorted((big / "sim").glob("frame_*.dng"))):
            shutil.copy(p, shoot / f"{prefix}_{k}.dng")
    return shoot


def _stop_while_writing(shoot, out, signum):
    """Start ``merge --batch shoot -o out -j 2``, send ``signum`` once a temporary is being
    written; returns (process, its stderr, the worker pids, the outputs begun by then)."""
    import subprocess
    import time

    from conftest import _command

    proc = subprocess.Popen(_command() + ["merge", "--batch", str(shoot), "-o", str(out), "-j", "2", "-q"],
                            stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not (out.is_dir() and any(".part" in n for n in os.listdir(out))):
        assert proc.poll() is None and time.monotonic() < deadline, "the batch ended before writing"
        time.sleep(0.005)
    children = Path(f"/proc/{proc.pid}/task/{proc.pid}/children").read_text().split()
    started = {n.split(".")[1] for n in os.listdir(out) if ".part" in n} | {n.split(".")[0] for n in os.listdir(out)}
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=90)
    return proc, err, children, started


def test_sigterm_stops_the_batch_workers_and_nothing_is_written_after(tmp_path, big_shoot):
    """SIGTERM to `merge --batch -j 2`: exit 143, the worker processes are gone, no
    temporary is left, no bracket that had not started is merged (the pool queues one
    ahead: a worker that went on to it wrote it after the signal) and no output appears
    after the command has ended; the output folder is left only if an output is in it."""
    import signal
    import time

    out = tmp_path / "merged"
    proc, err, children, started = _stop_while_writing(big_shoot, out, signal.SIGTERM)
    if proc.returncode == 0:
        pytest.skip("the batch finished before the signal arrived")
    assert proc.returncode == 128 + signal.SIGTERM and "Traceback" not in err, err
    listing = sorted(os.listdir(out)) if out.exists() else []
    time.sleep(3)
    assert (sorted(os.listdir(out)) if out.exists() else []) == listing and not any(".part" in n for n in listing)
    assert {n.split(".")[0] for n in listing} <= started, (listing, started)
    assert not out.exists() or listing
    assert not [c for c in children if Path(f"/proc/{c}").exists()
                and "zombie" not in Path(f"/proc/{c}/status").read_text()]


def test_ctrl_c_before_any_output_leaves_no_output_folder(tmp_path, big_shoot):
    """Ctrl-C while the first brackets are being written: nothing was committed, so the
    output folder (and the parent made for it) is gone; one committed already keeps it."""
    import signal

    out = tmp_path / "new" / "merged"
    proc, err, _, _ = _stop_while_writing(big_shoot, out, signal.SIGINT)
    if proc.returncode == 0:
        pytest.skip("the batch finished before the signal arrived")
    assert proc.returncode != 0
    if out.exists():
        assert [n for n in os.listdir(out) if n.endswith(".exr")], os.listdir(out)
    else:
        assert not (tmp_path / "new").exists()


def test_a_batch_whose_every_bracket_fails_leaves_no_output_folder(run, tmp_path):
    import OpenImageIO as oiio

    shoot = tmp_path / "shoot"
    shoot.mkdir()
    base = np.random.default_rng(0).uniform(20, 200, (24, 32, 3))
    for k, (level, t) in enumerate(((1.0, 0.01), (0.3, 0.1))):  # the longer exposure darker: the merge fails
        spec = oiio.ImageSpec(32, 24, 3, oiio.UINT8)
        spec.attribute("ExposureTime", t)
        buf = oiio.ImageBuf(spec)
        buf.set_pixels(oiio.ROI(), (base * level).astype(np.uint8))
        buf.write(str(shoot / f"x{k}.png"))
    out = tmp_path / "a" / "b"
    proc = run("merge", "--batch", shoot, "-o", out, check=False)
    assert proc.returncode == 1 and "1 of 1 brackets failed" in proc.stderr
    assert not (tmp_path / "a").exists()


def test_a_retried_cluster_task_counts_its_own_earlier_outputs_as_done(tmp_path, dng_bracket):
    """A task that runs again after its worker died (its outputs already written by this
    batch) is merged, not failed with 'already exists'; older files are not taken for it."""
    import os
    import time

    from hdrmerge_cli.pipeline.batch import merge_one
    from hdrmerge_cli.pipeline.options import MergeOptions

    folder, meta = dng_bracket
    paths = [str(p) for p in frames_of(folder, meta)[:3]]
    opts = MergeOptions.from_fields(output=tmp_path / "a.exr")
    assert merge_one(paths, opts)["status"] == "merged"
    started = time.time() - 60
    again = merge_one(paths, opts, None, started)
    assert again["status"] == "merged" and again["summary"]["retried"]
    for p in (tmp_path / "a.exr", tmp_path / "a.profile.json"):  # written before this batch began
        os.utime(p, (started - 10, started - 10))
    late = merge_one(paths, opts, None, started)
    assert late["status"] == "failed" and "already exists" in late["error"]


def test_no_output_folder_before_the_scheduler_answers(run, tmp_path, shoot):
    pytest.importorskip("distributed")
    out = tmp_path / "o"
    proc = run("merge", "--batch", shoot, "-o", out, "--scheduler", "tcp://127.0.0.1:1", check=False)
    lines = proc.stderr.strip().splitlines()  # the broken file of the shoot, then the scheduler
    assert proc.returncode == 1 and "scheduler" in lines[-1] and len(lines) == 2 and not out.exists()
