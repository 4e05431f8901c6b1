"""The library side of each ``vtr`` command (never prints): run orchestration (``pipeline``), ``convert``,
``evaluation`` against ground truth, plots (``report``) and the run files (``runfiles``: each file's schema,
writer and reader, ``run.json`` among them)."""
