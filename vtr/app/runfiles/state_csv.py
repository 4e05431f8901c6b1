"""``state.csv`` (``vtr repeat``): the controller state at a fixed rate, one row per time (SI units, yaw in rad).

Columns (:data:`SCHEMA`): ``t_ns``; ``px py pz``, ``vx vy vz``, ``ax ay az`` (vehicle origin in the gravity-aligned
trunk frame o: m, m/s, m/s²); ``yaw`` (rad); ``trunk_id``; ``lateral_m``, ``vertical_m`` (errors to the taught path,
empty of meaning — NaN — where the repeat is not localized), ``along_track_m`` (arc length from the start of the
taught path); ``localized`` (0/1: the chain's verdict, ``status == localized``); ``direction`` (+1 the route travelled
in taught order, -1 backward, 0 not yet decided: ``lateral_m`` is positive to the left of the direction of travel);
``status`` (``localized``, ``dead_reckoning``, ``off_route``, ``unknown``: :class:`vtr.state.controller.StateStatus`);
``sigma_px_m sigma_py_m sigma_pz_m``, ``sigma_vx_mps sigma_vy_mps sigma_vz_mps`` (standard deviations of position and
velocity in o, from the smoother's covariance; empty where none).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...io.csv_table import Column, CsvSchema
from ...navigation.repeat_state import StateTable
from ...state.controller import StateStatus

_XYZ = ("x", "y", "z")
SCHEMA = CsvSchema(
    "state.csv",
    (
        Column("t_ns", "int", unit="ns"),
        *(Column(f"p{a}", "float", ".6f", "m") for a in _XYZ),
        *(Column(f"v{a}", "float", ".6f", "m/s") for a in _XYZ),
        *(Column(f"a{a}", "float", ".6f", "m/s^2") for a in _XYZ),
        Column("yaw", "float", ".8f", "rad"),
        Column("trunk_id", "int"),
        Column("lateral_m", "float", ".6f", "m"),
        Column("vertical_m", "float", ".6f", "m"),
        Column("along_track_m", "float", ".6f", "m"),
        Column("localized", "bool"),
        Column("direction", "int"),
        Column("status", "str"),
        *(Column(f"sigma_p{a}_m", "float", ".6f", "m") for a in _XYZ),
        *(Column(f"sigma_v{a}_mps", "float", ".6f", "m/s") for a in _XYZ),
    ),
    line_end="\n",
)


def write_state_csv(path: Path, table: StateTable) -> None:
    """The file at ``path``: one row per time of ``table``."""
    n = len(table)
    localized = np.ones(n, bool) if table.localized is None else table.localized
    direction = np.zeros(n, np.int64) if table.direction is None else table.direction
    status = (
        np.where(localized, StateStatus.LOCALIZED.value, StateStatus.UNKNOWN.value)
        if table.status is None
        else table.status
    )
    nan3 = np.full((n, 3), np.nan)
    sig_p = nan3 if table.position_sigma is None else table.position_sigma
    sig_v = nan3 if table.velocity_sigma is None else table.velocity_sigma
    SCHEMA.write(
        path,
        (
            (
                table.t_ns[j],
                *table.position[j],
                *table.velocity[j],
                *table.acceleration[j],
                table.yaw[j],
                table.trunk_id[j],
                table.lateral[j],
                table.vertical[j],
                table.along_track[j],
                localized[j],
                direction[j],
                status[j],
                *sig_p[j],
                *sig_v[j],
            )
            for j in range(n)
        ),
    )


def read_state_csv(path: Path) -> StateTable:
    """The table of a ``state.csv`` written by :func:`write_state_csv`."""
    c = SCHEMA.read(path)

    def xyz(prefix: str) -> np.ndarray:
        return np.column_stack([c[f"{prefix}{a}"] for a in _XYZ]).reshape(-1, 3)

    return StateTable(
        t_ns=c["t_ns"],
        position=xyz("p"),
        velocity=xyz("v"),
        acceleration=xyz("a"),
        yaw=c["yaw"],
        trunk_id=c["trunk_id"],
        lateral=c["lateral_m"],
        vertical=c["vertical_m"],
        along_track=c["along_track_m"],
        localized=c["localized"],
        direction=c["direction"],
        status=c["status"],
        position_sigma=np.column_stack([c[f"sigma_p{a}_m"] for a in _XYZ]).reshape(-1, 3),
        velocity_sigma=np.column_stack([c[f"sigma_v{a}_mps"] for a in _XYZ]).reshape(-1, 3),
    )


__all__ = ["SCHEMA", "read_state_csv", "write_state_csv"]
