"""The layout of a batch's output folder ``OUT`` and the statuses of its runs: names every part of the batch shares.

``OUT/<route>/teach/`` holds the taught map ``route.vtrmap``; each repeat writes ``OUT/<route>/<repeat name>/`` with its
own copy of the map; ``OUT`` itself holds ``summary.csv``, ``fit/`` (``--fit``) and the batch lock. See the README's
"Batches" section and ``docs/outputs.md``.
"""

from __future__ import annotations

from ..outputs import RECORD

MAP_NAME = "route.vtrmap"  # the taught map inside OUT/<route>/teach/ (each repeat holds a copy)
TEACH_FOLDER = "teach"
SUMMARY_CSV = "summary.csv"
FIT_FOLDER = "fit"
LOCK_NAME = ".vtr-batch.lock"  # one batch per OUT (flock)
KEY_NAME = "batch_key.json"  # what made a run (resume compares it)
RESERVED_NAMES = {SUMMARY_CSV, FIT_FOLDER, LOCK_NAME, RECORD}  # OUT's own files: no route may be named so

#: A rerun of a finished run is built in ``OUT/<route>/<RERUN_PREFIX><run>`` (a run name starts with a letter or
#: digit, so never one of these) and moved into the run's folder only when it finished.
RERUN_PREFIX = ".vtr-rerun-"


# statuses of a run in a batch
FINISHED = "finished"  # ran now, to the end
RESUMED = "resumed"  # finished by an earlier invocation; skipped
FAILED = "failed"  # stopped on an error (run.json holds it)
BLOCKED = "blocked"  # a repeat whose route's teach did not finish
DONE = (FINISHED, RESUMED)
