"""Rendered batch routes are reused only when they were rendered with the same parameters."""

from __future__ import annotations

from vtr.sim.batch_routes import write_batch_routes


def _frames(folder) -> int:
    return len((folder / "times_ns.txt").read_text().split())


def test_routes_are_reused_only_with_the_same_parameters(tmp_path):
    write_batch_routes(tmp_path, 1, [1.0], 6.0)
    teach = tmp_path / "route_0" / "teach"
    short, stamp = _frames(teach), (teach / "times_ns.txt").stat().st_mtime_ns
    write_batch_routes(tmp_path, 1, [1.0], 6.0)  # the same: kept as it is
    assert (teach / "times_ns.txt").stat().st_mtime_ns == stamp
    write_batch_routes(tmp_path, 1, [1.0], 9.0)  # a longer route: rendered anew
    assert _frames(teach) > short
    assert _frames(tmp_path / "route_0" / "rep_1m") > 0
