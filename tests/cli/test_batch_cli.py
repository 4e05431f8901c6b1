"""`vtr batch` and `--threads` as a user runs them: one-line errors on a bad manifest, a tiny batch end to end."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import pytest
import yaml


def vtr(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vtr", *map(str, args)], capture_output=True, text=True)


def test_bad_manifests_are_one_line_errors(tmp_path):
    m = tmp_path / "m.yaml"
    for doc, msg in [
        ({"routes": [{"name": "a", "teach": "t", "repeat": []}]}, "unknown key 'repeat'"),
        ({"routes": [{"name": "a", "teach": "missing"}]}, "no such file or folder"),
    ]:
        m.write_text(yaml.safe_dump(doc))
        r = vtr("batch", m, "--out", tmp_path / "out", "--workers", "1")
        assert r.returncode == 1
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("vtr: error:") and msg in lines[0] and str(m) in lines[0]
    r = vtr("batch", tmp_path / "none.yaml", "--out", tmp_path / "out")
    assert r.returncode == 1 and "no such manifest" in r.stderr


def test_batch_runs_and_resumes(kitti_clip, tmp_path):
    m = tmp_path / "m.yaml"
    m.write_text(
        yaml.safe_dump(
            {
                "routes": [
                    {
                        "name": "clip",
                        "teach": {"source": str(kitti_clip), "frames": "0:12:2"},
                        "repeats": [{"source": str(kitti_clip), "frames": "1:12:2", "name": "odd"}],
                    }
                ]
            }
        )
    )
    r = vtr("batch", m, "--out", tmp_path / "out", "--workers", "1", "--threads", "2")
    assert r.returncode == 0, r.stderr
    assert "2 finished" in r.stdout and "odd" in r.stdout
    assert (tmp_path / "out" / "clip" / "odd" / "localization.csv").is_file()
    r = vtr("batch", m, "--out", tmp_path / "out", "--workers", "1")
    assert r.returncode == 0, r.stderr
    assert "2 resumed" in r.stdout
    # --fit over a finished repeat whose landmarks.csv was replaced by a link (the /etc/shadow case): the link
    # is named, its target never read or shown, and a fit asked for and not done is exit code 1
    secret = tmp_path / "shadow"
    secret.write_text("root:$6$secret-hash:19000:0:99999:7:::\n")
    lm = tmp_path / "out" / "clip" / "odd" / "landmarks.csv"
    lm.unlink()
    lm.symlink_to(secret)
    r = vtr("batch", m, "--out", tmp_path / "out", "--workers", "1", "--fit")
    assert r.returncode == 1, (r.stdout, r.stderr)
    assert "2 resumed" in r.stdout
    assert "fit: not done" in r.stderr and "landmarks.csv: is a symbolic link" in r.stderr
    assert "secret-hash" not in r.stdout + r.stderr
    assert not (tmp_path / "out" / "fit" / "model.json").exists()


def test_threads_option_is_checked(kitti_clip, tmp_path):
    r = vtr("odometry", kitti_clip, "--out", tmp_path / "o", "--threads", "-1")
    assert r.returncode == 1 and "--threads" in r.stderr and len(r.stderr.splitlines()) == 1  # a usage error: one line


def test_ctrl_c_of_a_batch_leaves_no_worker_tracebacks(tmp_path):
    """Ctrl-C in a terminal reaches the whole process group (the batch and its Dask workers): the batch ends
    with exit 130 and its one line, the workers print nothing (were: a KeyboardInterrupt traceback each), and
    the same command then finishes the rest."""
    import os
    import signal
    import time

    from vtr.sim.batch_routes import write_batch_routes

    manifest = write_batch_routes(tmp_path / "data", 1, [0.0, 1.0], 8.0)
    out = tmp_path / "out"
    p = subprocess.Popen(
        [sys.executable, "-m", "vtr", "batch", str(manifest), "--out", str(out), "--workers", "2"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    started = out / "route_0" / "teach" / "route.vtrmap"
    deadline = time.monotonic() + 600  # a bound on waiting, not an assertion on time
    while not started.exists() and p.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    assert started.exists() and p.poll() is None
    os.killpg(p.pid, signal.SIGINT)
    _, err = p.communicate()
    assert p.returncode == 130, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    assert err.rstrip().splitlines()[-1].startswith("interrupted: finished runs are kept")
    r = vtr("batch", manifest, "--out", out, "--workers", "2")
    assert r.returncode == 0, r.stderr
    assert "0 failed" in r.stdout and (out / "route_0" / "rep_1m" / "run.json").is_file()


@pytest.mark.skipif(not hasattr(signal, "SIGXFSZ"), reason="needs POSIX file size limits")
@pytest.mark.parametrize("limit_bytes", [500_000, 1_000_000])
def test_a_full_disk_under_a_batch_is_one_line_per_run_naming_the_file(kitti_clip, tmp_path, limit_bytes):
    """The batch's files cannot grow past ``limit_bytes`` (a full disk, as the workers see it): the run that hit
    it fails naming its file, a repeat of a failed teach is blocked, nothing is retried and no worker prints a
    traceback (round 4: tracebacks in the log, the task retried twice, no path named)."""
    import resource

    def full_disk() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG instead
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))

    m = tmp_path / "m.yaml"
    m.write_text(
        yaml.safe_dump(
            {
                "routes": [
                    {
                        "name": "clip",
                        "teach": {"source": str(kitti_clip), "frames": "0:12:2"},
                        "repeats": [{"source": str(kitti_clip), "frames": "1:12:2", "name": "odd"}],
                    }
                ]
            }
        )
    )
    r = subprocess.run(
        [sys.executable, "-m", "vtr", "batch", str(m), "--out", str(tmp_path / "out"), "--workers", "1"],
        capture_output=True,
        text=True,
        preexec_fn=full_disk,
        timeout=600,
    )
    assert r.returncode == 1, (r.stdout, r.stderr)
    assert "Traceback" not in r.stdout + r.stderr
    failed = [line for line in r.stdout.splitlines() if " failed " in line and line.startswith("clip")]
    assert len(failed) == 1 and "route.vtrmap" in failed[0] and "MapError" in failed[0], r.stdout
    assert "0 finished" in r.stdout or "1 finished" in r.stdout
    assert "retr" not in (r.stdout + r.stderr).lower()


def test_a_route_with_experiences_flies_its_repeats_in_order_on_one_growing_map(kitti_clip, tmp_path):
    """`experiences: true`: the second repeat starts from the map the first grew (teach + both repeats in its map,
    in the order listed), resumes as a whole, and a change to the first repeat reruns the second too."""
    from vtr.map import Map

    def manifest(first_frames: str) -> Path:
        m = tmp_path / "m.yaml"
        m.write_text(
            yaml.safe_dump(
                {
                    "routes": [
                        {
                            "name": "clip",
                            "experiences": True,
                            "teach": {"source": str(kitti_clip), "frames": "0:16:2"},
                            "repeats": [
                                {"source": str(kitti_clip), "frames": first_frames, "name": "week1"},
                                {"source": str(kitti_clip), "frames": "1:16:2", "name": "week2"},
                            ],
                        }
                    ]
                }
            )
        )
        return m

    out = tmp_path / "out"
    r = vtr("batch", manifest("1:16:2"), "--out", out, "--workers", "2")
    assert r.returncode == 0, r.stderr
    assert "3 finished" in r.stdout
    with Map.open(out / "clip" / "week2" / "route.vtrmap") as m:
        runs = m.runs()
        assert [x.kind for x in runs] == ["teach", "repeat", "repeat"]
        assert [x.state for x in runs] == ["finished"] * 3
        assert runs[1].source == runs[2].source == str(kitti_clip)
    with Map.open(out / "clip" / "week1" / "route.vtrmap") as m:
        assert [x.kind for x in m.runs()] == ["teach", "repeat"]
    r = vtr("batch", manifest("1:16:2"), "--out", out, "--workers", "2")
    assert r.returncode == 0 and "3 resumed" in r.stdout, r.stdout
    r = vtr("batch", manifest("1:14:2"), "--out", out, "--workers", "2")
    assert r.returncode == 0, r.stderr
    assert "2 finished, 1 resumed" in r.stdout, r.stdout  # week1 changed: week2, flown after it, reruns


def test_experiences_must_be_true_or_false(tmp_path):
    m = tmp_path / "m.yaml"
    m.write_text("routes:\n  - {name: r, teach: /x, experiences: yes-please}\n")
    r = vtr("batch", m, "--out", tmp_path / "out")
    assert r.returncode == 1 and "experiences: expected true or false" in r.stderr, r.stderr
