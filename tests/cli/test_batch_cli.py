"""`vtr batch` and `--threads` as a user runs them: one-line errors on a bad manifest, a tiny batch end to end."""

from __future__ import annotations

import subprocess
import sys

import yaml


def vtr(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vtr", *map(str, args)], capture_output=True, text=True)


def test_bad_manifests_are_one_line_errors(tmp_path):
    m = tmp_path / "m.yaml"
    for doc, msg in [({"routes": [{"name": "a", "teach": "t", "repeat": []}]}, "unknown key 'repeat'"),
                     ({"routes": [{"name": "a", "teach": "missing"}]}, "no such file or folder")]:
        m.write_text(yaml.safe_dump(doc))
        r = vtr("batch", m, "--out", tmp_path / "out", "--workers", "1")
        assert r.returncode == 1
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("vtr: error:") and msg in lines[0] and str(m) in lines[0]
    r = vtr("batch", tmp_path / "none.yaml", "--out", tmp_path / "out")
    assert r.returncode == 1 and "no such manifest" in r.stderr


def test_batch_runs_and_resumes(kitti_clip, tmp_path):
    m = tmp_path / "m.yaml"
    m.write_text(yaml.safe_dump({"routes": [{"name": "clip", "teach": {"source": str(kitti_clip), "frames": "0:12:2"},
                                             "repeats": [{"source": str(kitti_clip), "frames": "1:12:2",
                                                          "name": "odd"}]}]}))
    r = vtr("batch", m, "--out", tmp_path / "out", "--workers", "1", "--threads", "2")
    assert r.returncode == 0, r.stderr
    assert "2 finished" in r.stdout and "odd" in r.stdout
    assert (tmp_path / "out" / "clip" / "odd" / "localization.csv").is_file()
    r = vtr("batch", m, "--out", tmp_path / "out", "--workers", "1")
    assert r.returncode == 0, r.stderr
    assert "2 resumed" in r.stdout


def test_threads_option_is_checked(kitti_clip, tmp_path):
    r = vtr("odometry", kitti_clip, "--out", tmp_path / "o", "--threads", "-1")
    assert r.returncode == 1 and "--threads" in r.stderr and len(r.stderr.splitlines()) == 1   # a usage error: one line
