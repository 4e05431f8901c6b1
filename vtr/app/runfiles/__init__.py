"""The files a run writes into its ``--out`` folder: each has one module here that owns its schema, its writer and
its reader; every whole file is written through :meth:`vtr.app.outputs.OutputFolder.write` (a temporary file
renamed: the one atomic write), streamed files through :meth:`~vtr.app.outputs.OutputFolder.open`.

==========================  =====================================================  ==========================
file                        what                                                   owner
==========================  =====================================================  ==========================
``frames.csv``              one row per frame: odometry result, matches, inliers   :mod:`.frames_csv`
``localization.csv``        one row per localization attempt (streamed)            :mod:`.localization_csv`
``state.csv``               controller state at a fixed rate                       :mod:`.state_csv`
``run.json``/``config.yaml``  provenance and summary, written last                 :mod:`.run_json`
``trajectory_tum.txt``      camera poses (TUM; also read as ground truth)          :mod:`vtr.io.trajectory`
``landmarks.csv``           landmark match records (``perception-model fit``)      ``perception_model.landmarks_file``
``summary.csv``             ``vtr batch``: one row per run                         :mod:`.summary_csv`
``envelope.csv``            the localization envelope, one row per vertex          :mod:`.envelope_csv`
==========================  =====================================================  ==========================

The names below are what each command writes (checked before any work starts: :mod:`vtr.app.outputs`).
"""

RUN_FILES = ("config.yaml", "run.json")
ODOMETRY_OUTPUTS = ("trajectory_tum.txt", "frames.csv", "trajectory.png", *RUN_FILES)
TEACH_OUTPUTS = ("trajectory_tum.txt", "frames.csv", *RUN_FILES)
REPEAT_OUTPUTS = ("localization.csv", "landmarks.csv", "state.csv", "trajectory_tum.txt", "report.png", *RUN_FILES)

__all__ = ["ODOMETRY_OUTPUTS", "REPEAT_OUTPUTS", "RUN_FILES", "TEACH_OUTPUTS"]
