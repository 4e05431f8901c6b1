"""What a command writes (vtr.app.outputs): only inside its output folder, only files it made, never through a
link it did not make, never into a folder holding its inputs; a batch nobody else can drive (TLS on loopback),
one batch per --out, resume keyed on what made a run, manifests read as written, run.json checked when read."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import yaml

from vtr.app.batch import (
    FINISHED,
    RESUMED,
    BatchLock,
    BatchOptions,
    check_scheduler,
    check_workers,
    load_manifest,
    run_batch,
)
from vtr.app.outputs import RECORD, OutputFolder
from vtr.cli.summaries import batch_table
from vtr.errors import ConfigError, DataError, OutputError
from vtr.sim.batch_routes import write_batch_routes


def vtr(*args, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vtr", *map(str, args)], capture_output=True, text=True, cwd=cwd)


def tree_bytes(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def one_error_line(r: subprocess.CompletedProcess, *words: str) -> str:
    assert r.returncode == 1, (r.stdout, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("vtr: error:"), r.stderr
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def routes(tmp_path_factory) -> Path:
    """DATA/route_0/teach, DATA/route_0/rep_0m (tiny synthetic route) and DATA/manifest.yaml (the README layout)."""
    return write_batch_routes(tmp_path_factory.mktemp("data"), 1, [0.0], 6.0)


# ------------------------------------------------------------------------------ class 1: data loss


def test_batch_out_holding_the_data_is_refused_and_the_recording_kept(routes):
    data = routes.parent
    before = tree_bytes(data)
    r = vtr("batch", routes, "--out", data, "--workers", "1")
    one_error_line(r, "--out", "contains the input")
    assert tree_bytes(data) == before
    # inside an input is refused too
    r = vtr("batch", routes, "--out", data / "route_0" / "teach" / "out", "--workers", "1")
    one_error_line(r, "is inside the input")
    assert tree_bytes(data) == before


def test_a_symlinked_route_folder_inside_out_is_not_written_through(routes, tmp_path):
    elsewhere = tmp_path / "elsewhere"
    (elsewhere / "teach").mkdir(parents=True)
    (elsewhere / "teach" / "precious.bin").write_bytes(b"x" * 1000)
    (elsewhere / "teach" / "run.json").write_text("{}")  # looks like an unfinished run folder
    out = tmp_path / "out"
    out.mkdir()
    (out / "route_0").symlink_to(elsewhere)
    with pytest.raises(OutputError, match="route_0 is a symbolic link"):
        run_batch(load_manifest(routes), out, BatchOptions(workers=1))
    assert tree_bytes(elsewhere) == {"teach/precious.bin": b"x" * 1000, "teach/run.json": b"{}"}


@pytest.mark.parametrize("name", ["localization.csv", "config.yaml", "report.png", "state.csv", "run.json"])
def test_planted_symlinks_in_a_repeat_out_are_refused(kitti_clip, tmp_path, name):
    m = tmp_path / "route.vtrmap"
    r = vtr("teach", kitti_clip, "--map", m, "--frames", "0:12:2")
    assert r.returncode == 0, r.stderr
    victim = tmp_path / "victim.txt"
    victim.write_text("do not touch")
    out = tmp_path / "rep"
    out.mkdir()
    (out / name).symlink_to(victim)
    # --force writes into a folder that holds files, and still never through a link it did not make
    r = vtr("repeat", kitti_clip, "--map", m, "--frames", "1:12:2", "--out", out, "--force")
    one_error_line(r, str(out / name), "symbolic link")
    assert victim.read_text() == "do not touch"


def test_a_planted_tmp_link_and_hard_link_never_receive_output(kitti_clip, tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("do not touch")
    out = tmp_path / "odo"
    out.mkdir()
    (out / "run.json.tmp").symlink_to(victim)  # the old fixed temporary name
    r = vtr("odometry", kitti_clip, "--out", out, "--frames", "0:6", "--force")
    assert r.returncode == 0, r.stderr
    assert victim.read_text() == "do not touch" and json.loads((out / "run.json").read_text())["status"] == "finished"
    # a rerun replaces vtr's own files (recorded) ...
    r = vtr("odometry", kitti_clip, "--out", out, "--frames", "0:6", "--force")
    assert r.returncode == 0, r.stderr
    # ... and a hard link planted in place of one of them is replaced (renamed over), never written through
    (out / "frames.csv").unlink()
    os.link(victim, out / "frames.csv")
    r = vtr("odometry", kitti_clip, "--out", out, "--frames", "0:6", "--force")
    assert r.returncode == 0, r.stderr
    assert victim.read_text() == "do not touch" and (out / "frames.csv").read_text().startswith("t_ns")
    # a hard link at an output name vtr never wrote there is refused
    os.link(victim, out / "landmarks.csv")
    r = vtr("repeat", kitti_clip, "--map", out / "none.vtrmap", "--out", out, "--force")
    assert r.returncode == 1 and victim.read_text() == "do not touch"


def test_odometry_out_inside_its_source_is_refused(kitti_clip, tmp_path):
    clip = tmp_path / "clip"
    shutil.copytree(kitti_clip, clip)
    r = vtr("odometry", clip, "--out", clip / "out")
    one_error_line(r, "is inside the input")
    assert not (clip / "out" / "run.json").exists()


def test_clear_removes_exactly_what_vtr_made(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("keep")
    f = OutputFolder.prepare(tmp_path / "o", names=["a.txt"])
    f.write_text("a.txt", "ours")
    with f.open("b.csv") as fh:
        fh.write("x\n")
    (f.path / "notes.txt").write_text("the user's")
    (f.path / "link").symlink_to(victim)
    with (f.path / RECORD).open("a") as rec:  # a record that names a link: still only unlinked
        rec.write("link\n../victim.txt\n")
    OutputFolder(f.path).clear()
    assert sorted(p.name for p in f.path.iterdir()) == ["link", "notes.txt"]
    assert victim.read_text() == "keep"
    with pytest.raises(OutputError, match="not made by vtr"):
        OutputFolder.prepare(f.path, names=["notes.txt"])


# ------------------------------------------------------------------------------ class 2: the cluster


def test_another_process_cannot_use_the_batch_cluster(tmp_path):
    from vtr.app.batch.cluster import _DaskClient

    with _DaskClient(BatchOptions(), 1) as client:
        address = client.scheduler.address
        assert address.startswith("tls://127.0.0.1:")
        assert client.submit(sum, [1, 2]).result() == 3  # the batch's own client works
        assert http_hosts(client) == {"127.0.0.1"}  # its HTTP server (health) on loopback
        marker = tmp_path / "ran"
        probe = textwrap.dedent(f"""
            import sys
            from distributed import Client
            for addr in ({address!r}, {address.replace("tls://", "tcp://")!r}):
                try:
                    c = Client(addr, timeout=5)
                except Exception as err:
                    print("refused", addr, type(err).__name__)
                    continue
                c.submit(open, {str(marker)!r}, "w").result()
                print("connected", addr)
        """)
        r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True)
    assert r.stdout.count("refused") == 2, (r.stdout, r.stderr)
    assert not marker.exists()


def http_hosts(client) -> set[str]:
    """Hosts the scheduler's HTTP server (dashboard, health) listens on."""
    server = client.cluster.scheduler.http_server
    return {sock.getsockname()[0] for sock in server._sockets.values()}


@pytest.mark.parametrize("dashboard", [False, True])
def test_dashboard_only_when_asked_and_on_loopback(dashboard):
    """In a fresh process (Dask's HTTP routes are process-wide once a dashboard was served): /status is served
    only with dashboard=True, and only on 127.0.0.1."""
    probe = textwrap.dedent(f"""
        import urllib.error, urllib.request
        from vtr.app.batch import BatchOptions
        from vtr.app.batch.cluster import _DaskClient
        links = []
        with _DaskClient(BatchOptions(dashboard={dashboard}, on_dashboard=links.append), 1) as client:
            server = client.cluster.scheduler.http_server
            hosts = {{s.getsockname()[0] for s in server._sockets.values()}}
            port = client.scheduler_info()["services"]["dashboard"]
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{{port}}/status", timeout=30) as r:
                    code = r.status
            except urllib.error.HTTPError as err:
                code = err.code
        print(sorted(hosts), code, links)
    """)
    r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True)
    hosts, code, links = r.stdout.strip().rsplit("\n", 1)[-1].split(" ", 2)
    assert hosts == "['127.0.0.1']", r.stdout + r.stderr
    assert code == ("200" if dashboard else "404"), r.stdout + r.stderr
    assert ("http://127.0.0.1:" in links) == dashboard


def test_workers_and_scheduler_are_checked():
    from vtr.parallel import available_cores

    assert check_workers(None) == available_cores()
    for bad in (0, 1000, -1):
        with pytest.raises(ConfigError, match="--workers"):
            check_workers(bad)
    assert check_scheduler("tls://10.0.0.5:8786") == "tls://10.0.0.5:8786"
    for bad in ("10.0.0.5:8786", "http://x:1", "tls://host", "tls://host:99999", "tcp://h:1/x", "tls://h :1"):
        with pytest.raises(ConfigError, match="--scheduler"):
            check_scheduler(bad)
    r = vtr("batch", "m.yaml", "--out", "o", "--workers", "1000")
    one_error_line(r, "--workers 1000")


def test_workers_times_threads_is_bounded(routes, tmp_path):
    from vtr.app.batch import check_batch
    from vtr.parallel import available_cores

    with pytest.raises(ConfigError, match="--workers 1 x --threads 1024"):
        check_batch(load_manifest(routes), tmp_path / "out", BatchOptions(workers=1, threads=1024))
    assert check_batch(load_manifest(routes), tmp_path / "out", BatchOptions(workers=1, threads=1)) == 1
    assert available_cores() >= 1 and not (tmp_path / "out").exists()


# ------------------------------------------------------------------------------ class 3: batch outputs


def test_a_second_batch_on_the_same_out_is_refused(routes, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            textwrap.dedent(f"""
        import sys
        from vtr.app.batch import BatchLock
        with BatchLock({str(out)!r}):
            print("locked", flush=True)
            sys.stdin.readline()
    """),
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "locked"
        with pytest.raises(OutputError, match="another vtr batch is writing"):
            run_batch(load_manifest(routes), out, BatchOptions(workers=1))
        assert sorted(p.name for p in out.iterdir()) == [".vtr-batch.lock"]
    finally:
        holder.communicate("\n")
    with BatchLock(out):  # released when its holder ended
        pass


def test_changed_manifest_reruns_what_changed_and_keeps_foreign_files(routes, tmp_path):
    out = tmp_path / "out"
    first = run_batch(load_manifest(routes), out, BatchOptions(workers=1))
    assert [o.status for o in first.outcomes] == [FINISHED, FINISHED]
    notes = out / "route_0" / "rep_0m" / "notes.txt"
    notes.write_text("the user's")
    again = run_batch(load_manifest(routes), out, BatchOptions(workers=1))
    assert [o.status for o in again.outcomes] == [RESUMED, RESUMED]
    doc = yaml.safe_load(routes.read_text())
    route = doc["routes"][0]
    route["teach"] = str(routes.parent / route["teach"])
    route["repeats"] = [{"source": str(routes.parent / route["repeats"][0]), "frames": "0:5"}]
    m = tmp_path / "m.yaml"
    m.write_text(yaml.safe_dump(doc))
    changed = run_batch(load_manifest(m), out, BatchOptions(workers=1))
    by = {o.name: o for o in changed.outcomes}
    assert by["teach"].status == RESUMED
    assert by["rep_0m"].status == FINISHED and "frames" in by["rep_0m"].changed and by["rep_0m"].frames == 5
    assert "rerun: " in "\n".join(batch_table(changed))
    assert notes.read_text() == "the user's"  # not made by vtr: never removed


def test_manifest_read_as_written(tmp_path):
    m = tmp_path / "m.yaml"
    m.write_text("frames: 1:10\nroutes:\n  - name: a\n    teach: t\n    repeats: [{source: r, frames: 190:20:30}]\n")
    teach, rep = load_manifest(m).runs()
    assert teach.frames == "1:10" and rep.frames == "190:20:30"  # YAML 1.1 read them as 70 and 685230
    m.write_text("\ufeffroutes: [{name: a, teach: t}]\n")  # a UTF-8 BOM is not part of the YAML
    assert load_manifest(m).runs()[0].name == "teach"
    bad = [
        ("frames: 70\nroutes: [{name: a, teach: t}]\n", "frames: 70 is not a frame range"),
        ('routes: [{name: "a\\nb", teach: t}]\n', "not a usable folder name"),
        ('routes: [{name: "a\\n", teach: t}]\n', "not a usable folder name"),
        ("routes: [{name: summary.csv, teach: t}]\n", "batch's own output"),
        ("routes: [{name: fit, teach: t}]\n", "batch's own output"),
        ("routes: [{name: A, teach: t}, {name: a, teach: t}]\n", "used twice"),
        ("routes: [{name: a, teach: t, repeats: [teach]}]\n", "teach folder"),
    ]
    for text, msg in bad:
        m.write_text(text)
        with pytest.raises(ConfigError, match=msg):
            load_manifest(m)


def test_an_edited_run_json_is_one_line(routes, tmp_path):
    out = tmp_path / "out"
    run_batch(load_manifest(routes), out, BatchOptions(workers=1))
    run_json = out / "route_0" / "rep_0m" / "run.json"
    doc = json.loads(run_json.read_text())
    for edit, field in (
        (lambda d: d.update(summary=[1, 2]), "'summary'"),
        (lambda d: d["summary"].update(frames="many"), "summary.frames"),
        (lambda d: d.update(status="done"), "status"),
    ):
        d = json.loads(json.dumps(doc))
        edit(d)
        run_json.write_text(json.dumps(d))
        with pytest.raises(DataError, match=field):
            run_batch(load_manifest(routes), out, BatchOptions(workers=1))
    run_json.write_text('{"status": "finished", "summary": {"frames": [')
    r = vtr("batch", routes, "--out", out, "--workers", "1")
    one_error_line(r, str(run_json))


def test_a_failed_rerun_of_a_finished_run_keeps_its_outputs(routes, tmp_path):
    """The source of a finished teach changes (image_1/ lost in a partial sync): the rerun is built beside the
    finished outputs and fails; the taught map (the only copy) and every other output stay byte for byte, the
    outcome says they were kept, the repeats are blocked and keep theirs. Once the source is whole again the
    rerun finishes and its outputs replace the old ones (only vtr's; the user's notes stay)."""
    from vtr.app.batch import BLOCKED, FAILED

    data = tmp_path / "data"
    shutil.copytree(routes.parent, data)
    manifest = data / routes.name
    out = tmp_path / "out"
    first = run_batch(load_manifest(manifest), out, BatchOptions(workers=1))
    assert [o.status for o in first.outcomes] == [FINISHED, FINISHED]
    notes = out / "route_0" / "teach" / "notes.txt"
    notes.write_text("the user's")
    finished = tree_bytes(out / "route_0")
    assert "teach/route.vtrmap" in finished

    shutil.move(data / "route_0" / "teach" / "image_1", tmp_path / "image_1")  # a partial sync
    failed = run_batch(load_manifest(manifest), out, BatchOptions(workers=1))
    teach, rep = failed.outcomes
    assert teach.status == FAILED and "finished outputs of the earlier run are kept" in teach.error
    assert rep.status == BLOCKED
    assert tree_bytes(out / "route_0" / "teach") == {
        k[len("teach/") :]: v for k, v in finished.items() if k.startswith("teach/")
    }
    assert tree_bytes(out / "route_0" / "rep_0m") == {
        k[len("rep_0m/") :]: v for k, v in finished.items() if k.startswith("rep_0m/")
    }

    shutil.move(tmp_path / "image_1", data / "route_0" / "teach" / "image_1")
    (data / "route_0" / "teach" / "README.txt").write_text("a new file in the source: it changed")
    again = run_batch(load_manifest(manifest), out, BatchOptions(workers=1))
    assert [o.status for o in again.outcomes] == [FINISHED, FINISHED], again.outcomes
    assert all(o.changed for o in again.outcomes)
    assert notes.read_text() == "the user's"
    assert not list((out / "route_0").glob(".vtr-rerun-*"))  # the rerun folders moved in and went
    made = set((out / "route_0" / "teach" / RECORD).read_text().split())
    assert {"route.vtrmap", "run.json", "batch_key.json"} <= made and not any(".vtr-tmp-" in n for n in made)
    third = run_batch(load_manifest(manifest), out, BatchOptions(workers=1))
    assert [o.status for o in third.outcomes] == [RESUMED, RESUMED]
