"""The library side of each ``vtr`` command (never prints): run orchestration (``pipeline``), ``convert``,
``evaluation`` against ground truth, plots (``report``) and ``run.json`` (``runlog``)."""
