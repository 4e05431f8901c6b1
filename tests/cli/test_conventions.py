"""One set of conventions across ``vtr`` and ``perception-model`` (perception_model/commandline.py).

- every output of every command: refused when it exists, the same one line and exit code 1, unless
  ``--force`` (or a documented exception); a new command must be classified here;
- usage errors: one line, exit code 1; ``--version``: ``PROG VERSION``; ``vtr versions`` lists every
  dependency;
- ``--format`` lists its values and accepts the names ``convert --to`` writes; ``--c-bar``/``--delta``
  wherever a confidence is taken; ``--json`` a flag.
"""

from __future__ import annotations

import json
import re

import click
import pytest
from click.testing import CliRunner

from vtr.cli import main as vtr_main
from vtr.cli.perception_model import main as pm_main

ONE_LINE_ERROR = re.compile(r"^(vtr|perception-model): error: .+\n$")


def run(group: click.Group, *args) -> tuple[int, str, str]:
    r = CliRunner().invoke(group, [str(a) for a in args])
    return r.exit_code, r.stdout, r.stderr


def refused(group, args, path) -> str:
    code, out, err = run(group, *args)
    err = "".join(ln for ln in err.splitlines(keepends=True) if ": warning: " not in ln)  # deprecations
    assert code == 1 and ONE_LINE_ERROR.match(err), (code, out, err)
    assert f"{path}" in err and "already exists" in err and "not overwriting" in err, err
    return err


# --------------------------------------------------------------------------- outputs


@pytest.fixture
def existing(tmp_path):
    """An output folder holding a file, an output file, and dummy inputs (the refusal comes first)."""
    folder = tmp_path / "out"
    folder.mkdir()
    (folder / "precious.txt").write_text("keep me")
    (tmp_path / "in.txt").write_text("0.0 0 0 0 0 0 0 1\n1.0 1 0 0 0 0 0 1\n")
    (tmp_path / "model.json").write_text("{}")
    (tmp_path / "lm.csv").write_text("x\n")
    (tmp_path / "old.bag").write_text("not a bag")
    return tmp_path


#: command -> (group, arguments with OUT for an existing folder / FILE for an existing file, what is refused)
OUTPUT_CASES = {
    "odometry": (vtr_main, ["odometry", "{kitti}", "--out", "{out}"], "out"),
    "teach --out": (vtr_main, ["teach", "{kitti}", "--map", "{tmp}/new.vtrmap", "--out", "{out}"], "out"),
    "teach --map": (vtr_main, ["teach", "{kitti}", "--map", "{tmp}/in.txt"], "in.txt"),
    "repeat": (vtr_main, ["repeat", "{kitti}", "--map", "{tmp}/none.vtrmap", "--out", "{out}"], "out"),
    "export-trajectory": (
        vtr_main,
        ["export-trajectory", "{tmp}/in.txt", "{tmp}/model.json", "--to", "kitti"],
        "model.json",
    ),
    "export-map": (vtr_main, ["export-map", "{tmp}/none.vtrmap", "--ply", "{tmp}/in.txt"], "in.txt"),
    "convert": (vtr_main, ["convert", "{kitti}", "{tmp}/old.bag", "--to", "rosbag1"], "old.bag"),
    "fit": (pm_main, ["fit", "{tmp}/lm.csv", "--out", "{out}"], "out"),
    "fit --out FILE.json (deprecated)": (pm_main, ["fit", "{tmp}/lm.csv", "--out", "{tmp}/model.json"], "model.json"),
    "evaluate --out": (pm_main, ["evaluate", "{tmp}/model.json", "{tmp}/lm.csv", "--out", "{out}"], "out"),
    "constraint --out": (
        pm_main,
        [
            "constraint",
            "{tmp}/model.json",
            "--map",
            "{tmp}/none.vtrmap",
            "--positions",
            "{tmp}/lm.csv",
            "--out",
            "{out}",
        ],
        "out",
    ),
    "envelope": (pm_main, ["envelope", "{tmp}/model.json", "--map", "{tmp}/none.vtrmap", "--out", "{out}"], "out"),
}
#: commands that write nothing, and the documented exceptions (perception_model/commandline.py, README)
NO_OUTPUT = {"versions", "config", "map"}
EXCEPTIONS = {"demo": "rewrites its own folder", "batch": "resumes in its --out folder"}


def fill(args, tmp, kitti):
    return [a.format(tmp=tmp, out=tmp / "out", kitti=kitti) for a in args]


@pytest.mark.parametrize("case", sorted(OUTPUT_CASES))
def test_every_command_refuses_to_overwrite_the_same_way(case, existing, kitti_clip):
    group, args, target = OUTPUT_CASES[case]
    path = existing / target
    before = {p: p.read_bytes() for p in existing.rglob("*") if p.is_file()}
    err = refused(group, fill(args, existing, kitti_clip), path)
    if case != "convert" and case != "teach --map":  # the two that never replace (documented)
        assert "pass --force" in err, err
    after = {p: p.read_bytes() for p in existing.rglob("*") if p.is_file()}
    assert after == before  # nothing written, nothing removed


def test_every_command_is_classified():
    """A new command must say how it treats existing outputs: add it to OUTPUT_CASES or the exceptions."""
    covered = {c.split()[0] for c in OUTPUT_CASES} | NO_OUTPUT | set(EXCEPTIONS)
    assert set(vtr_main.commands) | set(pm_main.commands) <= covered, sorted(
        set(vtr_main.commands) | set(pm_main.commands) - covered
    )


def test_force_writes_into_an_existing_folder(existing, kitti_clip):
    out = existing / "out"
    code, _out, err = run(vtr_main, "odometry", kitti_clip, "--out", out, "--frames", "0:3", "--force")
    assert code == 0, err
    assert (out / "trajectory_tum.txt").is_file() and (out / "precious.txt").read_text() == "keep me"


def test_fit_writes_into_a_folder_and_refuses_a_second_time(tmp_path):
    import numpy as np

    from perception_model.landmarks_file import write_landmarks
    from perception_model.model import PerceptionModel
    from perception_model.synthetic import simulate_observations

    write_landmarks(
        tmp_path / "lm.csv", simulate_observations(PerceptionModel.thesis(), 30_000, np.random.default_rng(1), name="r")
    )
    out = tmp_path / "model"
    code, stdout, err = run(pm_main, "fit", tmp_path / "lm.csv", "--out", out)
    assert code == 0, err
    assert json.loads((out / "model.json").read_text())["c1"] > 0 and (out / "fit.png").stat().st_size > 10_000
    refused(pm_main, ["fit", tmp_path / "lm.csv", "--out", out], out)
    code, _, err = run(pm_main, "fit", tmp_path / "lm.csv", "--out", out, "--force")
    assert code == 0, err
    # --json is a flag (JSON on stdout) as in `vtr map info`; --out DIR writes DIR/evaluation.json
    code, stdout, err = run(
        pm_main, "evaluate", out / "model.json", tmp_path / "lm.csv", "--json", "--out", tmp_path / "ev"
    )
    assert code == 0, err
    assert json.loads(stdout)["evaluation"]["n"] == 30_000
    assert json.loads((tmp_path / "ev" / "evaluation.json").read_text())["evaluation"]["n"] == 30_000
    # the old spelling still works, with a one-line deprecation warning
    code, _, err = run(pm_main, "evaluate", out / "model.json", tmp_path / "lm.csv", "--json", tmp_path / "e.json")
    assert code == 0 and "deprecated" in err and (tmp_path / "e.json").is_file(), err


# --------------------------------------------------------------------------- usage, versions


@pytest.mark.parametrize(
    "group, args, needle",
    [
        (vtr_main, ["repeat", "datasets/kitti06_clip", "--out", "o"], "Missing option '--map'"),
        (vtr_main, ["odometry", "x", "--out", "o", "--threads", "-1"], "--threads"),
        (vtr_main, ["no-such-command"], "No such command"),
        (pm_main, ["fit", "--out", "x"], "Missing argument"),
        (pm_main, ["envelope", "m.json", "--map", "m", "--out", "o", "--delta", "0.7"], "--delta"),
    ],
)
def test_usage_errors_are_one_line_and_exit_1(group, args, needle):
    code, out, err = run(group, *args)
    assert code == 1 and ONE_LINE_ERROR.match(err) and needle in err and "--help" in err, (code, err)


def test_versions_print_alike():
    for group, prog in ((vtr_main, "vtr"), (pm_main, "perception-model")):
        code, out, _ = run(group, "--version")
        assert code == 0 and re.fullmatch(rf"{prog} \d+\.\d+\.\d+\n", out), out


def test_vtr_versions_lists_every_runtime_dependency():
    code, out, err = run(vtr_main, "versions")
    assert code == 0, err
    for name in ("numpy", "scipy", "cv2", "gtsam", "open3d", "rosbags", "dask", "osqp", "pyarrow", "matplotlib"):
        assert re.search(rf"\b{name} \d", out), (name, out)


# --------------------------------------------------------------------------- names


def test_format_lists_its_choices_and_they_match_the_readers():
    from vtr.cli.common import SOURCE_FORMATS
    from vtr.io import FORMAT_ALIASES, FORMATS

    assert set(SOURCE_FORMATS) == set(FORMATS) | set(FORMAT_ALIASES)
    assert set(FORMAT_ALIASES) >= {"rosbag1", "rosbag2", "mcap"}  # what `convert --to` writes
    for cmd in ("odometry", "teach", "repeat", "convert"):
        _, out, _ = run(vtr_main, cmd, "--help")
        assert "[" + "|".join(SOURCE_FORMATS) + "]" in " ".join(out.split()).replace(" |", "|").replace("| ", "|"), (
            cmd,
            out,
        )


def test_format_rosbag1_reads_a_converted_bag(kitti_clip, tmp_path):
    bag = tmp_path / "clip.bag"
    code, _, err = run(vtr_main, "convert", kitti_clip, bag, "--to", "rosbag1", "--frames", "0:3")
    assert code == 0, err
    code, out, err = run(vtr_main, "odometry", bag, "--format", "rosbag1", "--out", tmp_path / "o")
    assert code == 0, err
    assert "frames 3" in out


def test_confidence_spellings_agree():
    for cmd in ("constraint", "envelope"):
        _, out, _ = run(pm_main, cmd, "--help")
        assert "--c-bar" in out and "--delta" in out, (cmd, out)
    code, _, err = run(pm_main, "envelope", "m.json", "--map", "m", "--out", "o", "--c-bar", "3", "--delta", "0.01")
    assert code == 1 and "at most one of --c-bar and --delta" in err, err


def test_fit_with_too_few_held_out_observations_for_r2_still_writes_its_model(tmp_path):
    """The held-out R^2 needs bins of >= min count; without one it is null in model.json, not a traceback."""
    import numpy as np

    from perception_model.landmarks_file import write_landmarks
    from perception_model.model import PerceptionModel
    from perception_model.synthetic import simulate_observations

    write_landmarks(
        tmp_path / "lm.csv", simulate_observations(PerceptionModel.thesis(), 6000, np.random.default_rng(1), name="r")
    )
    code, _, err = run(pm_main, "fit", tmp_path / "lm.csv", "--out", tmp_path / "m")
    assert code == 0, err
    assert json.loads((tmp_path / "m" / "model.json").read_text())["fit"]["holdout"]["r2_binned"] is None
