"""Inputs that used to end in a traceback or a hang end in one line, at once: nesting deeper than the file kind
has, a key given twice, named pipes and devices as input files, a tls:// scheduler without certificates, a time
outside int64, and a 2 M-position constraint path evaluated chunk by chunk. Real pipes, devices and processes."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from perception_model.errors import ModelFileError
from perception_model.landmarks_file import write_landmarks
from perception_model.model import PerceptionModel
from perception_model.synthetic import ground_scene, simulate_observations
from vtr.app.batch import load_manifest
from vtr.config import Config
from vtr.errors import ConfigError, EstimationError

DEEP = "[" * 5000 + "]" * 5000


def run(*args, timeout: float = 60) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith("DASK_")}
    return subprocess.run(
        [sys.executable, "-m", *map(str, args)], capture_output=True, text=True, timeout=timeout, env=env
    )


def one_line(r: subprocess.CompletedProcess, prog: str, *words: str) -> str:
    assert r.returncode == 1, (r.stdout, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{prog}: error:"), r.stderr
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]


# ------------------------------------------------------------------ nesting and duplicate keys


@pytest.mark.parametrize(
    "name, text", [("deep.yaml", f"odometry: {DEEP}\n"), ("deep.toml", f"a = {DEEP}\n")], ids=["yaml", "toml"]
)
def test_a_config_nested_5000_deep_is_one_line(tmp_path, name, text):
    (tmp_path / name).write_text(text)
    with pytest.raises(ConfigError, match="nested too deeply"):
        Config.load(tmp_path / name)


def test_a_manifest_and_a_model_nested_5000_deep_are_one_line(tmp_path):
    (tmp_path / "m.yaml").write_text(f"routes: {DEEP}\n")
    with pytest.raises(ConfigError, match="m.yaml: nested too deeply"):
        load_manifest(tmp_path / "m.yaml")
    (tmp_path / "model.json").write_text(DEEP)
    with pytest.raises(ModelFileError, match="model.json: nested too deeply"):
        PerceptionModel.load(tmp_path / "model.json")
    r = run("vtr", "batch", tmp_path / "m.yaml", "--out", tmp_path / "o")
    one_line(r, "vtr", "nested too deeply")


@pytest.mark.parametrize(
    "name, text, words",
    [
        (
            "c.yaml",
            "odometry:\n  min_inliers: 10\nstereo: {}\nodometry:\n  min_inliers: 12\n",
            ["key 'odometry' given twice", "lines 1 and 4"],
        ),
        (
            "c.yaml",
            "odometry:\n  min_inliers: 10\n  min_inliers: 12\n",
            ["key 'min_inliers' given twice", "lines 2 and 3"],
        ),
        ("c.toml", "[odometry]\nmin_inliers = 10\n\n[odometry]\n", ["table '[odometry]' given twice", "lines 1 and 4"]),
        (
            "c.toml",
            "[odometry]\nmin_inliers = 10\nmin_inliers = 12\n",
            ["'odometry.min_inliers' given twice", "lines 2 and 3"],
        ),
    ],
)
def test_a_key_given_twice_in_a_config_names_it_and_both_lines(tmp_path, name, text, words):
    (tmp_path / name).write_text(text)
    with pytest.raises(ConfigError) as err:
        Config.load(tmp_path / name)
    for w in words:
        assert w in str(err.value)


def test_a_key_given_twice_in_a_manifest_names_it_and_both_lines(tmp_path):
    (tmp_path / "t").mkdir()
    m = tmp_path / "m.yaml"
    m.write_text("routes:\n  - name: a\n    teach: t\n    name: b\n")
    with pytest.raises(ConfigError, match=r"key 'name' given twice \(lines 2 and 4\)"):
        load_manifest(m)
    m.write_text("frames: '0:4'\nroutes:\n  - name: a\n    teach: t\nframes: '0:8'\n")
    with pytest.raises(ConfigError, match=r"key 'frames' given twice \(lines 1 and 5\)"):
        load_manifest(m)
    m.write_text("base: &b {frames: '0:4'}\nroutes:\n  - {name: a, teach: t}\n")  # anchors still work
    with pytest.raises(ConfigError, match="unknown key"):
        load_manifest(m)


# ------------------------------------------------------------------ pipes and devices


@pytest.fixture
def landmarks(tmp_path) -> Path:
    p = tmp_path / "in.csv"
    write_landmarks(p, simulate_observations(PerceptionModel.thesis(), 3_000, np.random.default_rng(0), name="r"))
    return p


def test_named_pipes_and_devices_are_refused_at_once(tmp_path, landmarks):
    pipe = tmp_path / "pipe.csv"
    os.mkfifo(pipe)
    # (in a child with a timeout: before, these blocked forever or read /dev/zero until memory ran out)
    pm = "vtr.cli.perception_model"
    one_line(run(pm, "fit", pipe, "--out", tmp_path / "f"), "perception-model", "named pipe")
    one_line(run(pm, "fit", "/dev/zero", "--out", tmp_path / "f"), "perception-model", "a device")
    PerceptionModel.thesis().save(tmp_path / "model.json")
    one_line(run(pm, "evaluate", "/dev/zero", landmarks), "perception-model", "a device")
    one_line(run(pm, "evaluate", tmp_path / "model.json", "/dev/zero"), "perception-model", "a device")
    one_line(
        run(pm, "constraint", tmp_path / "model.json", "--landmarks", pipe, "--positions", pipe),
        "perception-model",
        "named pipe",
    )
    mp = tmp_path / "m.vtrmap"
    os.mkfifo(mp)
    for args in (("map", "check", mp), ("map", "info", mp), ("map", "info", "/dev/zero")):
        one_line(run("vtr", *args), "vtr", "not a regular file")


def test_a_model_file_is_read_bounded(tmp_path):
    import perception_model.inputs as inputs

    big = tmp_path / "big.json"
    with big.open("wb") as f:
        f.truncate(inputs.MAX_MODEL_FILE_BYTES + 1)  # sparse: no disk used
    with pytest.raises(ModelFileError, match="larger than"):
        PerceptionModel.load(big)


# ------------------------------------------------------------------ batch, smoother


def test_a_tls_scheduler_without_certificates_is_one_line(tmp_path):
    (tmp_path / "t").mkdir()
    (tmp_path / "m.yaml").write_text("routes:\n  - name: a\n    teach: t\n")
    r = run("vtr", "batch", tmp_path / "m.yaml", "--out", tmp_path / "o", "--scheduler", "tls://127.0.0.1:8786")
    one_line(r, "vtr", "--scheduler tls://127.0.0.1:8786", "distributed.comm.tls")


@pytest.mark.parametrize("t_ns", [2**63, -(2**63) - 1, 10**30])
def test_a_time_outside_int64_is_refused_at_the_smoothers_entry(t_ns):
    from vtr.state.smoothing import TrajectorySmoother

    s = TrajectorySmoother(Config().smoothing)
    with pytest.raises(EstimationError, match="outside the int64 nanosecond range"):
        s.add_pose(t_ns, np.eye(4), np.eye(6) * 1e-4)
    with pytest.raises(EstimationError, match="outside the int64"):
        s.add_knot(t_ns, T_world_sensor=np.eye(4), covariance=np.eye(6) * 1e-4)
    s.add_pose(0, np.eye(4), np.eye(6) * 1e-4)  # refused before anything was inserted
    s.add_pose(10**8, np.eye(4), np.eye(6) * 1e-4)
    assert s.state_at(5 * 10**7).t_ns == 5 * 10**7


# ------------------------------------------------------------------ constraint over a long path


def test_a_long_constraint_path_is_evaluated_in_chunks_with_the_same_rows(tmp_path, monkeypatch):
    """2 M positions allocated 6.2 GiB at once; now at most MAX_CHUNK_ELEMENTS position-landmark pairs are evaluated
    at a time (here shrunk so that a short path spans many chunks) and the CSV is the same as in one piece."""
    from click.testing import CliRunner

    import perception_model.cli as cli
    import perception_model.cli.constraint_commands as constraint_commands
    from perception_model.constraint import PerceptionConstraint

    rng = np.random.default_rng(3)
    np.savetxt(tmp_path / "lm.csv", ground_scene(300, rng).landmarks, delimiter=",", header="x,y,z", comments="")
    n = 1_000
    pos = np.column_stack([np.zeros(n), np.linspace(0, 6, n), np.zeros(n), np.linspace(-0.5, 0.5, n)])
    np.savetxt(tmp_path / "pos.csv", pos, delimiter=",", header="x,y,z,yaw", comments="")
    PerceptionModel.thesis().save(tmp_path / "model.json")

    def csv_of(out: Path) -> bytes:
        r = CliRunner().invoke(
            cli.main,
            [
                "constraint",
                str(tmp_path / "model.json"),
                "--landmarks",
                str(tmp_path / "lm.csv"),
                "--positions",
                str(tmp_path / "pos.csv"),
                "--no-exact",
                "--out",
                str(out),
            ],
        )
        assert r.exit_code == 0, r.output
        return (out / "constraint.csv").read_bytes()

    whole = csv_of(tmp_path / "a")
    sizes: list[int] = []
    evaluate = PerceptionConstraint.evaluate

    def spy(self, positions, *args, **kwargs):
        sizes.append(len(positions))
        return evaluate(self, positions, *args, **kwargs)

    monkeypatch.setattr(PerceptionConstraint, "evaluate", spy)
    monkeypatch.setattr(constraint_commands, "MAX_CHUNK_ELEMENTS", 300 * 64)
    assert csv_of(tmp_path / "b") == whole
    assert max(sizes) == 64 and sum(sizes) == n


def test_a_config_or_manifest_that_is_a_pipe_is_named_as_one(tmp_path):
    """Found beyond the issue's list: a named pipe as --config or manifest was reported as "no such file"."""
    for name in ("c.yaml", "m.yaml"):
        os.mkfifo(tmp_path / name)
    with pytest.raises(ConfigError, match="c.yaml: is a named pipe"):
        Config.load(tmp_path / "c.yaml")
    from vtr.errors import DataError

    with pytest.raises(DataError, match="m.yaml: is a named pipe"):
        load_manifest(tmp_path / "m.yaml")
