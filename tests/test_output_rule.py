"""One write rule for every file the distribution writes (perception_model.outputs owns it; vtr's forms use it):
never through a symbolic link, never over one of the command's own inputs, with or without --force; run-folder
files are read back only when vtr made them. Real symbolic links, real hard links, real processes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import perception_model.outputs as pm_outputs
import vtr.app.outputs as app_outputs
from perception_model.landmarks_file import write_landmarks
from perception_model.model import PerceptionModel
from perception_model.synthetic import simulate_observations
from vtr.app.outputs import RECORD, OutputFolder
from vtr.errors import OutputError
from vtr.io.outputs import check_new_output

SECRET = "root:$6$secret-hash:19000:0:99999:7:::\n"


def pm(*args) -> subprocess.CompletedProcess:
    """The perception-model console script installed with vtr, in a real process."""
    return subprocess.run(
        [sys.executable, "-m", "vtr.cli.perception_model", *map(str, args)], capture_output=True, text=True
    )


def vtr(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vtr", *map(str, args)], capture_output=True, text=True)


def one_error_line(r: subprocess.CompletedProcess, prog: str, *words: str) -> str:
    assert r.returncode == 1, (r.stdout, r.stderr)
    lines = [ln for ln in r.stderr.strip().splitlines() if ": warning:" not in ln]
    assert len(lines) == 1 and lines[0].startswith(f"{prog}: error:"), r.stderr
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("rule")
    rng = np.random.default_rng(5)
    write_landmarks(d / "in.csv", simulate_observations(PerceptionModel.thesis(), 6_000, rng, name="run1"))
    PerceptionModel.thesis().save(d / "model.json")
    return d


@pytest.fixture
def victim(tmp_path) -> Path:
    """A file of the user's that a planted link points to."""
    p = tmp_path / "shadow"
    p.write_text(SECRET)
    return p


# ------------------------------------------------------------------ perception-model outputs


def test_fit_plot_through_a_link_is_refused_with_force(data, tmp_path, victim):
    (tmp_path / "P.png").symlink_to(victim)
    r = pm("fit", data / "in.csv", "--out", tmp_path / "O", "--plot", tmp_path / "P.png", "--force")
    one_error_line(r, "perception-model", "P.png", "symbolic link")
    assert victim.read_text() == SECRET
    assert not (tmp_path / "O" / "model.json").exists()  # refused before any work


def test_fit_model_json_link_in_out_is_refused_with_force(data, tmp_path, victim):
    (tmp_path / "O").mkdir()
    (tmp_path / "O" / "model.json").symlink_to(victim)
    r = pm("fit", data / "in.csv", "--out", tmp_path / "O", "--force")
    one_error_line(r, "perception-model", "model.json", "symbolic link")
    assert victim.read_text() == SECRET and (tmp_path / "O" / "model.json").is_symlink()


def test_evaluate_json_link_in_out_is_refused_with_force(data, tmp_path, victim):
    (tmp_path / "O").mkdir()
    (tmp_path / "O" / "evaluation.json").symlink_to(victim)
    r = pm("evaluate", data / "model.json", data / "in.csv", "--out", tmp_path / "O", "--force")
    one_error_line(r, "perception-model", "evaluation.json", "symbolic link")
    assert victim.read_text() == SECRET


def test_fit_never_replaces_its_input_by_any_name(data, tmp_path):
    src = tmp_path / "in.json"  # a landmarks file, whatever its name
    src.write_bytes((data / "in.csv").read_bytes())
    before = src.read_bytes()
    r = pm("fit", src, "--out", src, "--force")
    one_error_line(r, "perception-model", "is the input")
    os.link(src, tmp_path / "hard.json")
    (tmp_path / "soft.json").symlink_to(src)
    r = pm("fit", src, "--out", tmp_path / "hard.json", "--force")
    one_error_line(r, "perception-model", "is the input")
    r = pm("fit", src, "--out", tmp_path / "O", "--plot", tmp_path / "soft.json", "--force")
    one_error_line(r, "perception-model")
    assert src.read_bytes() == before


def test_fit_plot_with_no_image_suffix_is_refused_before_the_model_is_written(data, tmp_path):
    r = pm("fit", data / "in.csv", "--out", tmp_path / "O", "--plot", tmp_path / "fig.csv")
    one_error_line(r, "perception-model", "--plot", "fig.csv", ".png")
    assert not (tmp_path / "O").exists() or not any((tmp_path / "O").iterdir())


def test_fit_force_replaces_a_plain_file_whole(data, tmp_path):
    out = tmp_path / "O"
    out.mkdir()
    (out / "model.json").write_text("old")
    os.link(out / "model.json", tmp_path / "other_name")  # another name for the old file
    r = pm("fit", data / "in.csv", "--out", out, "--force")
    assert r.returncode == 0, r.stderr
    assert json.loads((out / "model.json").read_text())["c1"] > 0
    assert (tmp_path / "other_name").read_text() == "old"  # renamed over, not written into
    assert not [p for p in out.iterdir() if p.name.startswith(pm_outputs.TMP_TAG)]


# ------------------------------------------------------------------ vtr exports


def test_export_trajectory_through_a_link_or_over_its_input_is_refused(tmp_path, victim):
    tum = tmp_path / "t.txt"
    tum.write_text("0.0 0 0 0 0 0 0 1\n0.1 1 0 0 0 0 0 1\n")
    (tmp_path / "out.kitti").symlink_to(victim)
    r = vtr("export-trajectory", tum, tmp_path / "out.kitti", "--to", "kitti", "--force")
    one_error_line(r, "vtr", "out.kitti", "symbolic link")
    assert victim.read_text() == SECRET
    r = vtr("export-trajectory", tum, tum, "--to", "kitti", "--force")
    one_error_line(r, "vtr", "is the input")
    assert tum.read_text().startswith("0.0 0 0")
    r = vtr("export-trajectory", tum, tmp_path / "new.kitti", "--to", "kitti")
    assert r.returncode == 0, r.stderr
    assert len((tmp_path / "new.kitti").read_text().splitlines()) == 2


# ------------------------------------------------------------------ one owner


CASES = ["absent", "file", "symlink", "dangling", "folder", "empty_folder", "fifo", "input", "hardlink_input"]


def make_case(tmp_path: Path, case: str) -> tuple[Path, Path]:
    inp = tmp_path / "input.csv"
    inp.write_text("x\n")
    p = tmp_path / "target"
    if case == "file":
        p.write_text("old")
    elif case == "symlink":
        p.symlink_to(inp)
    elif case == "dangling":
        p.symlink_to(tmp_path / "nowhere")
    elif case == "folder":
        p.mkdir()
        (p / "f").write_text("x")
    elif case == "empty_folder":
        p.mkdir()
    elif case == "fifo":
        os.mkfifo(p)
    elif case == "input":
        p = inp
    elif case == "hardlink_input":
        os.link(inp, p)
    return p, inp


@pytest.mark.parametrize("force", [False, True])
@pytest.mark.parametrize("case", CASES)
def test_vtr_and_perception_model_apply_one_rule(tmp_path, case, force):
    """vtr's OutputError form says exactly what perception_model.outputs says, for every kind of entry."""
    p, inp = make_case(tmp_path, case)
    problem = pm_outputs.existing_output(p, force, inputs=(inp,))
    if problem is None:
        check_new_output(p, force, inputs=(inp,))
    else:
        with pytest.raises(OutputError) as err:
            check_new_output(p, force, inputs=(inp,))
        assert str(err.value) == problem
    # with or without --force: never a link, a folder, a pipe or an input
    assert (problem is None) == (case == "absent" or (case == "file" and force))


def test_vtr_output_folder_uses_the_owners_primitives():
    assert app_outputs.create_exclusive is pm_outputs.create_exclusive
    assert app_outputs.entry_problem is pm_outputs.entry_problem
    assert app_outputs.TMP_TAG == pm_outputs.TMP_TAG


def test_replace_file_never_follows_a_link_and_leaves_no_temporary_on_error(tmp_path, victim):
    link = tmp_path / "out.txt"
    link.symlink_to(victim)
    pm_outputs.replace_text(link, "new")
    assert victim.read_text() == SECRET and not link.is_symlink() and link.read_text() == "new"

    def broken(tmp: Path) -> None:
        tmp.write_text("half")
        raise RuntimeError("writer failed")

    with pytest.raises(RuntimeError):
        pm_outputs.replace_file(tmp_path / "out.txt", broken)
    assert (tmp_path / "out.txt").read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt", "shadow"]


# ------------------------------------------------------------------ reading run folders back


def test_a_run_file_planted_as_a_link_is_not_read_back(tmp_path, victim):
    folder = OutputFolder.prepare(tmp_path / "run")
    folder.write_text("landmarks.csv", "alpha_deg,theta_deg,inlier\n")
    assert folder.own_file("landmarks.csv") == folder.path / "landmarks.csv"
    (folder.path / "landmarks.csv").unlink()
    (folder.path / "landmarks.csv").symlink_to(victim)  # recorded name, planted link
    fresh = OutputFolder(folder.path)
    with pytest.raises(OutputError, match="landmarks.csv: is a symbolic link"):
        fresh.own_file("landmarks.csv")
    with pytest.raises(OutputError, match="symbolic link"):
        fresh.read_own("landmarks.csv")
    (folder.path / "notes.csv").write_text("mine")  # a user's file vtr did not make
    with pytest.raises(OutputError, match=f"not in {RECORD}"):
        fresh.own_file("notes.csv")
    assert fresh.own_file("absent.csv") is None


def test_batch_fit_and_resume_refuse_planted_links(tmp_path, victim):
    """`vtr batch --fit` over a finished repeat whose landmarks.csv was replaced by a link to /etc/shadow (here a
    stand-in): the fit is not done, the error names the link, and nothing of the target is shown; a run.json
    planted as a link is an error, not a resumed run."""
    from vtr.app.batch import RunOutcome, checked_run, fit_repeats, load_manifest

    for d in ("teach", "rep"):
        (tmp_path / "data" / d).mkdir(parents=True)
    manifest = tmp_path / "data" / "manifest.yaml"
    manifest.write_text("routes:\n  - name: r\n    teach: teach\n    repeats: [rep]\n")
    spec = load_manifest(manifest)
    out = tmp_path / "out"
    run = OutputFolder.prepare(out / "r" / "rep")
    obs = simulate_observations(PerceptionModel.thesis(), 2_000, np.random.default_rng(1), name="rep")
    run.write("landmarks.csv", write_landmarks, obs)
    outcomes = [RunOutcome("r", "teach", "teach", "finished"), RunOutcome("r", "rep", "repeat", "finished")]
    assert "model" in fit_repeats(spec, out, outcomes)  # vtr's own file is read

    (run.path / "landmarks.csv").unlink()
    (run.path / "landmarks.csv").symlink_to(victim)
    result = fit_repeats(spec, out, outcomes)
    assert "landmarks.csv: is a symbolic link" in result["error"] and "secret" not in json.dumps(result)

    run.write_text("run.json", json.dumps({"status": "finished", "summary": {}}))
    assert checked_run(run.path)["status"] == "finished"
    (run.path / "run.json").unlink()
    (run.path / "run.json").symlink_to(victim)
    with pytest.raises(OutputError, match="run.json: is a symbolic link"):
        checked_run(run.path)
