"""merge --batch: grouping, local processes, a Dask LocalCluster, failures and skips."""
import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from conftest import frames_of
from hdrmerge_cli.io.frames import Frame
from hdrmerge_cli.pipeline.batch import capture_seconds, group_brackets

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


def test_sigterm_stops_the_batch_workers_and_nothing_is_written_after(run, tmp_path, tmp_path_factory):
    """SIGTERM to `merge --batch -j 2`: exit 143, the worker processes are gone, no
    temporary is left, no bracket that had not started is merged (the pool queues one
    ahead: a worker that went on to it wrote it after the signal) and no output appears
    after the command has ended."""
    import os
    import signal
    import subprocess
    import time

    from conftest import _command

    big = tmp_path_factory.mktemp("bigshoot")
    run("simulate", "-o", big / "sim", "-q", "--size", "1600x1200", "--frames", "3", "--seed", "2")
    shoot = big / "shoot"
    shoot.mkdir()
    for prefix in "abcd":  # four brackets of the same frames (no timestamps: split by the sequence)
        for k, p in enumerate(sorted((big / "sim").glob("frame_*.dng"))):
            shutil.copy(p, shoot / f"{prefix}_{k}.dng")
    out = tmp_path / "merged"
    proc = subprocess.Popen(_command() + ["merge", "--batch", str(shoot), "-o", str(out), "-j", "2", "-q"],
                            stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not (out.is_dir() and any(".part" in n for n in os.listdir(out))):
        assert proc.poll() is None and time.monotonic() < deadline, "the batch ended before writing"
        time.sleep(0.005)
    children = Path(f"/proc/{proc.pid}/task/{proc.pid}/children").read_text().split()
    started = {n.split(".")[1] for n in os.listdir(out) if ".part" in n} | {n.split(".")[0] for n in os.listdir(out)}
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=90)
    if proc.returncode == 0:
        pytest.skip("the batch finished before the signal arrived")
    assert proc.returncode == 128 + signal.SIGTERM and "Traceback" not in err, err
    listing = sorted(os.listdir(out))
    time.sleep(3)
    assert sorted(os.listdir(out)) == listing and not any(".part" in n for n in listing)
    assert {n.split(".")[0] for n in listing} <= started, (listing, started)
    assert not [c for c in children if Path(f"/proc/{c}").exists()
                and "zombie" not in Path(f"/proc/{c}/status").read_text()]


def test_a_retried_cluster_task_counts_its_own_earlier_outputs_as_done(tmp_path, dng_bracket):
    """A task that runs again after its worker died (its outputs already written by this
    batch) is merged, not failed with 'already exists'; older files are not taken for it."""
    import os
    import time

    from hdrmerge_cli.pipeline.batch import merge_one
    from hdrmerge_cli.pipeline.options import MergeOptions

    folder, meta = dng_bracket
    paths = [str(p) for p in frames_of(folder, meta)[:3]]
    opts = MergeOptions(output=tmp_path / "a.exr")
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
