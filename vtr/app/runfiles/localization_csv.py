"""``localization.csv`` (``vtr repeat``): one row per localization attempt, streamed (flushed per row).

The columns (:data:`SCHEMA`): ``t_ns`` (leaf time, ns), ``leaf_id``, ``trunk_id``, ``twig_id``, ``branch_id`` (map
ids; twig and branch before the attempt, -1 before the first success), ``success`` (0/1), ``matches``,
``inliers``, ``x y z qx qy qz qw`` (``T_leaf_trunk`` as TUM: metres and a unit quaternion), ``var_rx var_ry var_rz
var_x var_y var_z`` (the diagonal of its covariance: rad² and m²), ``consecutive_failures``,
``distance_since_success_m``, ``status`` (``LocalizationStatus``), ``direction`` (+1 as taught, -1 backward) and
``experiences`` (the earlier repeats, map run ids joined by ``;``, whose landmarks gave a success inliers besides the
teach's; empty when none: docs/map.md, "Experiences").
"""

from __future__ import annotations

from pathlib import Path
from typing import IO

import numpy as np

from ...geometry import T_to_tum, tum_to_T
from ...io.csv_table import Column, CsvRowWriter, CsvSchema
from ...navigation.localization import Localization, LocalizationStatus

POSE_COLUMNS = ("x", "y", "z", "qx", "qy", "qz", "qw")
VARIANCE_COLUMNS = ("var_rx", "var_ry", "var_rz", "var_x", "var_y", "var_z")
SCHEMA = CsvSchema(
    "localization.csv",
    (
        Column("t_ns", "int", unit="ns"),
        *(Column(name, "int") for name in ("leaf_id", "trunk_id", "twig_id", "branch_id")),
        Column("success", "bool"),
        Column("matches", "int"),
        Column("inliers", "int"),
        *(Column(name, "float", ".9f", "m" if name in "xyz" else "") for name in POSE_COLUMNS),
        *(Column(name, "float", ".6e", "rad^2" if name.startswith("var_r") else "m^2") for name in VARIANCE_COLUMNS),
        Column("consecutive_failures", "int"),
        Column("distance_since_success_m", "float", ".3f", "m"),
        Column("status", "str"),
        Column("direction", "int"),
        Column("experiences", "str"),
    ),
)
EXPERIENCE_SEPARATOR = ";"


class LocalizationWriter:
    """Appends one row per localization attempt to an open ``localization.csv`` (the header first)."""

    def __init__(self, file: IO[str]):
        self._rows: CsvRowWriter = SCHEMA.writer(file)

    def write(self, loc: Localization) -> None:
        self._rows.write(
            (
                loc.t_ns,
                loc.leaf_id,
                loc.trunk_id,
                loc.twig_id,
                loc.branch_id,
                loc.success,
                loc.matches,
                loc.inliers,
                *T_to_tum(loc.T_leaf_trunk),
                *np.diag(loc.covariance),
                loc.consecutive_failures,
                loc.distance_since_success_m,
                loc.status.value,
                loc.direction,
                EXPERIENCE_SEPARATOR.join(str(e) for e in loc.experiences),
            )
        )


def read_localization_csv(path: Path) -> list[Localization]:
    """The attempts of a ``localization.csv`` as ``Localization`` records (the covariance is its diagonal; the
    landmark records are in ``landmarks.csv``)."""
    c = SCHEMA.read(path)
    poses = tum_to_T(np.column_stack([c[k] for k in POSE_COLUMNS])) if len(c["t_ns"]) else np.zeros((0, 4, 4))
    variances = np.column_stack([c[k] for k in VARIANCE_COLUMNS]) if len(c["t_ns"]) else np.zeros((0, 6))
    return [
        Localization(
            t_ns=int(c["t_ns"][i]),
            leaf_id=int(c["leaf_id"][i]),
            trunk_id=int(c["trunk_id"][i]),
            twig_id=int(c["twig_id"][i]),
            branch_id=int(c["branch_id"][i]),
            success=bool(c["success"][i]),
            matches=int(c["matches"][i]),
            inliers=int(c["inliers"][i]),
            T_leaf_trunk=poses[i],
            covariance=np.diag(variances[i]),
            consecutive_failures=int(c["consecutive_failures"][i]),
            distance_since_success_m=float(c["distance_since_success_m"][i]),
            status=LocalizationStatus(c["status"][i]),
            direction=int(c["direction"][i]),
            experiences=tuple(int(e) for e in str(c["experiences"][i]).split(EXPERIENCE_SEPARATOR) if e),
        )
        for i in range(len(c["t_ns"]))
    ]


__all__ = ["SCHEMA", "LocalizationWriter", "read_localization_csv"]
