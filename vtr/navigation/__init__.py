"""Teach and repeat on top of odometry and the map: the localization chain and localizer
(``localization``), ``Teach`` (``teach``), ``Repeat`` (``repeat``), and the repeat state estimator feeding
the smoother (``repeat_state``)."""
