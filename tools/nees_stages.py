"""Where the position covariance a controller reads goes wrong: the NEES of each stage of the online repeat against
ground truth, on the six cases of ``tools/bench_online.py``'s calibration replay.

usage: python tools/nees_stages.py [--out OUT] [--cases ...]

Stages (position NEES, 3 dof; 2.37 is the median of an exact covariance, 11.34 its 99 % bound):

- ``odometry``: the relative pose between consecutive repeat vertices as the smoother is fed it (odometry's edge
  covariance plus the drift term) against the true relative pose; ``odometry_edge``: with the edge covariance alone;
- ``localization``: ``T_leaf_trunk`` of each success against the true pose relative to the true trunk, with the
  covariance the localizer reports; ``localization_adjustment`` with the adjustment's part alone; and two other
  models of the map's part: ``localization_trunk_edge`` (the trunk's own temporal edge only) and
  ``localization_chain`` (each neighbour that gave inliers adds the covariance of the taught edges between it and
  the trunk, ``T_s_trunk``, instead of its own edge);
- ``knots``: the state at each vertex's time right after it was fed (the smoother's newest knot);
- ``ticks``: the state at every control tick 0-90 ms after each frame (bench_online's replay).

Writes OUT/nees_stages.json.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_online as bo  # noqa: E402  (tools/bench_online.py: the cases and the truth)

from vtr.control.online import OnlineRepeat  # noqa: E402
from vtr.geometry import inv_T, log_se3  # noqa: E402
from vtr.io import open_source  # noqa: E402
from vtr.map import Map  # noqa: E402
from vtr.navigation.localization import LocalizationEstimate, TaughtSubmap  # noqa: E402
from vtr.state.trajectory import adjoint  # noqa: E402

CASES = ("aerial backward", "kitti06", "aerial forward", "kitti06 reversed", "ramp", "ramp reversed")


def _stats(a: list[float]) -> dict:
    x = np.array(a, float)
    if not len(x):
        return {"n": 0, "median": None, "inside_99": None}
    return {"n": len(x), "median": float(np.median(x)), "inside_99": float(np.mean(x <= bo.NEES_BOUND))}


def _nees3(e: np.ndarray, P: np.ndarray) -> float:
    return float(e @ np.linalg.solve(P, e))


def stages(map_path: Path, images: list, truth: bo.Truth, args) -> dict:
    with Map.open(map_path) as m:
        teach_t = {int(v): int(t) for v, t in zip(m.taught_path().ids, m.taught_path().t_ns, strict=True)}
    ticks = max(1, int(round(args.control_hz / args.camera_hz)))
    period_ns = int(round(1e9 / args.control_hz))
    names = ("odometry", "odometry_edge", "localization", "localization_adjustment", "localization_trunk_edge")
    out: dict[str, list[float]] = {k: [] for k in (*names, "localization_chain")}
    out.update({"knots": [], "knots_smoother_only": [], "ticks": [], "ticks_0": [], "ticks_after": []})
    previous = None  # (T_world_kf, t_ns) of the previous vertex
    with OnlineRepeat(map_path) as live:
        est = live.estimator
        attempts: list[tuple[TaughtSubmap, LocalizationEstimate]] = []
        localize = live.repeat.localizer.localize

        def recording(leaf, submap, *a, **k):  # what each localization attempt was matched against
            e = localize(leaf, submap, *a, **k)
            attempts.append((submap, e))
            return e

        live.repeat.localizer.localize = recording  # type: ignore[method-assign]
        edge = live.repeat.submaps.taught_edge_covariance
        for im in images:
            attempts.clear()
            step = live.feed(im)
            kf, loc = step.odometry.new_keyframe, step.localization
            if kf is not None:
                T_true = truth.repeat_at(int(kf.t_ns))
                if previous is not None:
                    T_pc = inv_T(previous[0]) @ kf.T_world_kf
                    G = inv_T(truth.repeat_at(previous[1])) @ T_true
                    cov = kf.edge_covariance + est._drift_covariance(previous[0], kf.T_world_kf)
                    xi = log_se3(inv_T(G) @ T_pc)  # right perturbation of T_prev_cur
                    out["odometry"].append(_nees3(xi[3:], cov[3:, 3:]))
                    out["odometry_edge"].append(_nees3(xi[3:], kf.edge_covariance[3:, 3:]))
                previous = (np.asarray(kf.T_world_kf, float), int(kf.t_ns))
                if loc is not None and loc.success:
                    T_tr = truth.teach_at(teach_t[int(loc.trunk_id)])
                    G_lt = inv_T(T_true) @ T_tr
                    xi = log_se3(np.asarray(loc.T_leaf_trunk) @ inv_T(G_lt))  # left perturbation
                    P = np.asarray(loc.covariance, float)
                    out["localization"].append(_nees3(xi[3:], P[3:, 3:]))
                    F = np.zeros((6, 6)) if loc.frame_covariance is None else np.asarray(loc.frame_covariance)
                    out["localization_adjustment"].append(_nees3(xi[3:], (P - F)[3:, 3:]))
                    sub, e = next(
                        (a, e)
                        for a, e in reversed(attempts)
                        if e.ok and np.allclose(e.T_leaf_trunk, loc.T_leaf_trunk)  # type: ignore[arg-type]
                    )
                    trunk_edge, chain = _map_parts(sub, e, edge)
                    out["localization_trunk_edge"].append(_nees3(xi[3:], (P - F + trunk_edge)[3:, 3:]))
                    out["localization_chain"].append(_nees3(xi[3:], (P - F + chain)[3:, 3:]))
            if not live.localized:
                continue
            view = live.view
            if kf is not None and view.trajectory.last_time_ns == int(kf.t_ns):
                t = int(kf.t_ns)
                s = view.controller_state_at(t, with_covariance=True)
                out["knots"].append(bo._nees(view, s, t, truth, teach_t))
                k = int(view.trunk_index_at(np.array([t]))[0])
                F = view.frame_output_covariance(t, s.T_o_a)[:3, :3]
                e = s.position - _p_true(view, k, t, truth, teach_t)
                out["knots_smoother_only"].append(_nees3(e, s.position_covariance - F))
            for j in range(ticks):
                t = int(im.t_ns) + j * period_ns
                s = view.controller_state_at(t, with_covariance=True)
                n = bo._nees(view, s, t, truth, teach_t)
                out["ticks"].append(n)
                (out["ticks_0"] if j == 0 else out["ticks_after"]).append(n)
    return {k: _stats(v) for k, v in out.items()}


def _map_parts(sub: TaughtSubmap, e: LocalizationEstimate, edge) -> tuple[np.ndarray, np.ndarray]:
    """Two other models of the map's part of a localization's covariance (6x6, leaf frame): the trunk's own
    temporal edge moved to the leaf, and the sum over the neighbours that gave inliers of the covariance of the
    taught edges between each and the trunk (``T_s_trunk``, composed along the path) moved to the leaf."""
    assert e.T_leaf_trunk is not None
    T_lt = e.T_leaf_trunk
    ids = [int(v) for v in sub.vertex_ids]
    slot_of = {v: i for i, v in enumerate(ids)}
    trunk = ids[sub.trunk_slot]

    def into(v: int) -> np.ndarray:  # the edge that placed v after v - 1, in v's frame
        P = edge(v)
        return np.zeros((6, 6)) if P is None else np.asarray(P, float)

    def moved(P: np.ndarray, T_x_trunk: np.ndarray) -> np.ndarray:
        A = adjoint(T_lt @ inv_T(T_x_trunk))
        return A @ P @ A.T

    A = adjoint(T_lt)
    P_trunk = into(trunk)
    trunk_edge = A @ P_trunk @ A.T
    chain = np.zeros((6, 6))
    for s in np.unique(sub.slot[e.matched[e.inlier]]):
        v = ids[int(s)]
        if v == trunk:
            continue
        lo, hi = min(v, trunk), max(v, trunk)
        for w in range(lo + 1, hi + 1):  # every edge between the two, each moved from its own vertex
            chain += moved(into(w), sub.T_vertex_trunk[slot_of[w]])
    return trunk_edge, chain


def _p_true(view, k: int, t: int, truth: bo.Truth, teach_t: dict[int, int]) -> np.ndarray:
    trunk_id = int(view.route.path.ids[k])
    T_rel = inv_T(truth.teach_at(teach_t[trunk_id])) @ truth.repeat_at(t)
    T_sv = view.route.T_sensor_vehicle
    return (view.route.trunk(k)[0] @ inv_T(T_sv) @ T_rel @ T_sv)[:3, 3]


def case(name: str, args) -> tuple[Path, list, bo.Truth]:
    out = args.out
    if name.startswith("aerial"):
        map_path, source, indices, truth = (
            bo.aerial_case(out, args) if name == "aerial backward" else bo.aerial_forward_case(out, args)
        )
    elif name.startswith("kitti06"):
        map_path, source, indices, truth = bo.kitti_case(out)
    else:
        map_path, source, indices, truth = bo.kitti_case(out, "kitti00_ramp_clip")
    with open_source(source) as src:
        images = [src[i] for i in indices]
    if name.endswith("reversed"):
        images, truth = bo.reversed_repeat(images, truth)
    return map_path, images, truth


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("out/bench_online"), help="bench_online's folder (maps reused)")
    ap.add_argument("--camera-hz", type=float, default=10.0)
    ap.add_argument("--control-hz", type=float, default=100.0)
    ap.add_argument("--speed", type=float, default=6.0, help="aerial flight speed (m/s)")
    ap.add_argument("--cases", default=",".join(CASES), help=f"comma-separated of: {', '.join(CASES)}")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows = {}
    for name in [c.strip() for c in args.cases.split(",") if c.strip()]:
        if name not in CASES:
            raise SystemExit(f"--cases: unknown case {name!r} (known: {', '.join(CASES)})")
        rows[name] = stages(*case(name, args), args)
        cells = ", ".join(f"{k} {v['median']:.2f}/{100 * v['inside_99']:.0f}%" for k, v in rows[name].items() if v["n"])
        print(f"{name}: {cells}", flush=True)
    (args.out / "nees_stages.json").write_text(json.dumps(rows, indent=2) + "\n")


if __name__ == "__main__":
    main()
