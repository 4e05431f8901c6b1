"""``vtr batch``: manifests, a 2-worker local Dask cluster over tiny synthetic routes, failures recorded,
resume after an interruption, a worker killed mid-run retried with results equal to an undisturbed run."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import yaml

from vtr.app.batch import BLOCKED, FAILED, FINISHED, RESUMED, BatchOptions, load_manifest, run_batch
from vtr.app.runfiles.run_json import run_status
from vtr.cli.summaries import batch_table
from vtr.errors import ConfigError
from vtr.sim.batch_routes import KillWorkerOnce, write_batch_routes

OUTPUTS = ("localization.csv", "landmarks.csv", "trajectory_tum.txt", "state.csv")


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    """One tiny route (8 m teach, repeats 0 and 1 m to the side) plus a broken repeat."""
    root = tmp_path_factory.mktemp("batch")
    manifest = write_batch_routes(root, 1, [0.0, 1.0], 8.0)
    broken = root / "route_0" / "broken"
    (broken / "image_0").mkdir(parents=True)
    (broken / "image_1").mkdir()
    doc = yaml.safe_load(manifest.read_text())
    doc["routes"][0]["repeats"].append("route_0/broken")
    manifest.write_text(yaml.safe_dump(doc))
    return manifest


@pytest.fixture(scope="module")
def undisturbed(data, tmp_path_factory):
    out = tmp_path_factory.mktemp("out")
    statuses = []
    result = run_batch(
        load_manifest(data),
        out,
        BatchOptions(workers=2, fit=True),
        progress=lambda o, done, total: statuses.append((o.name, o.status, done, total)),
    )
    return out, result, statuses


def test_two_workers_run_every_run_and_record_the_failure(undisturbed):
    out, result, statuses = undisturbed
    by_name = {o.name: o for o in result.outcomes}
    assert [o.name for o in result.outcomes] == ["teach", "rep_0m", "rep_1m", "broken"]
    assert by_name["teach"].status == FINISHED and by_name["teach"].frames == 9
    for name in ("rep_0m", "rep_1m"):
        o = by_name[name]
        assert o.status == FINISHED and o.frames == 7 and o.localized_pct > 50 and o.median_inliers > 20
        for f in (*OUTPUTS, "run.json", "config.yaml", "report.png"):
            assert (out / "route_0" / name / f).is_file(), f
        assert run_status(out / "route_0" / name) == "finished"
    assert (out / "route_0" / "teach" / "route.vtrmap").is_file()
    assert (out / "route_0" / "teach" / "frames.csv").is_file()
    broken = by_name["broken"]
    assert broken.status == FAILED and "no images" in broken.error
    assert run_status(out / "route_0" / "broken") == "failed"
    assert len(statuses) == 4 and statuses[-1][2:] == (4, 4)
    assert result.failed == [broken]
    table = "\n".join(batch_table(result))
    assert "rep_1m" in table and "no images" in table and "1 failed" in table
    assert (out / "summary.csv").read_text().count("\n") == 5


def test_fit_over_every_repeat(undisturbed):
    out, result, _ = undisturbed
    rows = sum(len((out / "route_0" / r / "landmarks.csv").read_text().splitlines()) - 1 for r in ("rep_0m", "rep_1m"))
    assert result.fit["files"] == 2 and result.fit["observations"] == rows > 1000
    assert json.loads((out / "fit" / "model.json").read_text())["fit"]["n"] == rows
    assert (out / "fit" / "fit.png").stat().st_size > 1000


def test_rerun_after_an_interruption_does_only_what_was_left(data, undisturbed, tmp_path):
    out, _, _ = undisturbed
    copy = tmp_path / "out"
    shutil.copytree(out, copy)
    # an interrupted run: its folder is there, half written, without run.json
    (copy / "route_0" / "rep_1m" / "run.json").unlink()
    (copy / "route_0" / "rep_1m" / "landmarks.csv").write_text("t_ns\n")
    before = (copy / "route_0" / "rep_0m" / "run.json").stat().st_mtime_ns
    result = run_batch(load_manifest(data), copy, BatchOptions(workers=1))
    status = {o.name: o.status for o in result.outcomes}
    assert status == {"teach": RESUMED, "rep_0m": RESUMED, "rep_1m": FINISHED, "broken": FAILED}
    assert (copy / "route_0" / "rep_0m" / "run.json").stat().st_mtime_ns == before
    for f in OUTPUTS:
        assert (copy / "route_0" / "rep_1m" / f).read_bytes() == (out / "route_0" / "rep_1m" / f).read_bytes(), f


def test_a_worker_killed_mid_run_is_retried_and_results_equal(data, undisturbed, tmp_path):
    out, _, _ = undisturbed
    marker = tmp_path / "killed.txt"
    result = run_batch(
        load_manifest(data), tmp_path / "out", BatchOptions(workers=2, on_start=KillWorkerOnce(marker, "rep_1m"))
    )
    at_kill = marker.read_text().split()
    assert "localization.csv" in at_kill and "run.json" not in at_kill  # killed mid-run
    status = {o.name: o.status for o in result.outcomes}
    assert status == {"teach": FINISHED, "rep_0m": FINISHED, "rep_1m": FINISHED, "broken": FAILED}
    for name in ("rep_0m", "rep_1m"):
        for f in OUTPUTS:
            got = (tmp_path / "out" / "route_0" / name / f).read_bytes()
            assert got == (out / "route_0" / name / f).read_bytes(), f"{name}/{f}"


def test_repeats_are_blocked_when_their_teach_fails(tmp_path):
    (tmp_path / "bad" / "image_0").mkdir(parents=True)
    (tmp_path / "bad" / "image_1").mkdir()
    (tmp_path / "m.yaml").write_text(yaml.safe_dump({"routes": [{"name": "r", "teach": "bad", "repeats": ["bad"]}]}))
    result = run_batch(load_manifest(tmp_path / "m.yaml"), tmp_path / "out", BatchOptions(workers=1))
    assert [o.status for o in result.outcomes] == [FAILED, BLOCKED]


def test_manifest_forms_and_errors(tmp_path):
    m = tmp_path / "m.yaml"
    m.write_text(
        yaml.safe_dump(
            {
                "frames": "0::2",
                "routes": [
                    {
                        "name": "a",
                        "teach": "/data/a/teach",
                        "repeats": ["rel/rep1", {"source": "/x/rep1", "name": "r1b", "frames": "1::2"}],
                    }
                ],
            }
        )
    )
    spec = load_manifest(m)
    teach, rep1, rep2 = spec.runs()
    assert teach.is_teach and teach.source == Path("/data/a/teach") and teach.frames == "0::2"
    assert rep1.name == "rep1" and rep1.source == tmp_path / "rel" / "rep1"
    assert rep2.name == "r1b" and rep2.frames == "1::2"
    bad = [
        ({"routes": []}, "non-empty list 'routes'"),
        ({"routes": [{"name": "a", "teach": "t", "repeats": ["x/rep", "y/rep"]}]}, "used twice"),
        ({"routes": [{"name": "a", "repeats": []}]}, "no 'teach'"),
        ({"routes": [{"name": "a/b", "teach": "t"}]}, "folder name"),
        ({"routes": [{"name": "a", "teach": "t", "repats": []}]}, "unknown key 'repats'"),
        ({"routes": [{"name": "a", "teach": "t"}, {"name": "a", "teach": "t"}]}, "route name used twice"),
    ]
    for doc, msg in bad:
        m.write_text(yaml.safe_dump(doc))
        with pytest.raises(ConfigError, match=msg) as err:
            load_manifest(m)
        assert str(m) in str(err.value)


def test_a_running_scheduler_is_used_unchanged(data, undisturbed, tmp_path):
    from distributed import LocalCluster

    out, _, _ = undisturbed
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
        result = run_batch(
            load_manifest(data), tmp_path / "out", BatchOptions(scheduler=cluster.scheduler_address, threads=1)
        )
    assert result.workers == cluster.scheduler_address
    assert [o.status for o in result.outcomes] == [FINISHED, FINISHED, FINISHED, FAILED]
    got, want = tmp_path / "out" / "route_0" / "rep_1m", out / "route_0" / "rep_1m"
    for f in OUTPUTS:
        assert (got / f).read_bytes() == (want / f).read_bytes(), f


@pytest.mark.parametrize("change", ["recalibrated", "swapped"])
def test_a_changed_source_of_the_same_size_reruns(data, tmp_path, change):
    """Resume compares what a run read by content: a recalibration of the same size, or two images swapped, rerun the
    runs that read them (keyed by path, file count and bytes alone, both were 'resumed' with the old results)."""
    copy_data = tmp_path / "data"
    shutil.copytree(data.parent, copy_data, symlinks=True)
    manifest = copy_data / data.name
    first = run_batch(load_manifest(manifest), tmp_path / "fresh", BatchOptions(workers=1))
    assert {o.status for o in first.outcomes} <= {FINISHED, FAILED}
    again = run_batch(load_manifest(manifest), tmp_path / "fresh", BatchOptions(workers=1))
    assert {o.name: o.status for o in again.outcomes}["rep_0m"] == RESUMED
    rep = copy_data / "route_0" / "rep_0m"
    if change == "recalibrated":
        calib = rep / "calib.txt"
        text = calib.read_text()
        flipped = text.replace("0.", "1.", 1)
        assert len(flipped) == len(text) and flipped != text
        calib.write_text(flipped)
    else:
        a, b = sorted((rep / "image_0").iterdir())[2:4]
        tmp = a.with_suffix(".tmp")
        a.rename(tmp), b.rename(a), tmp.rename(b)
    result = run_batch(load_manifest(manifest), tmp_path / "fresh", BatchOptions(workers=1))
    status = {o.name: o for o in result.outcomes}
    assert status["teach"].status == RESUMED and status["rep_1m"].status == RESUMED
    assert status["rep_0m"].status != RESUMED and "source changed" in (status["rep_0m"].changed or ""), status["rep_0m"]


def test_the_batch_cluster_serves_no_logs_over_http():
    """Without the dashboard, the scheduler's HTTP port (loopback) answers /health only: Dask's default routes would
    serve logs, worker addresses and memory to anyone on the machine."""
    import urllib.error
    import urllib.request

    from vtr.app.batch.cluster import _DaskClient

    with _DaskClient(BatchOptions(workers=1), 1) as client:
        port = client.cluster.scheduler.http_server.port
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=10) as r:
            assert r.status == 200
        for route in ("/info/main/workers.html", "/json/counts.json", "/metrics", "/info/main/logs.html"):
            with pytest.raises(urllib.error.HTTPError) as err:
                urllib.request.urlopen(f"http://127.0.0.1:{port}{route}", timeout=10)
            assert err.value.code == 404, route
