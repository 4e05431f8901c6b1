"""Control on the taught path: the perception field (``field``), the flat multirotor model
(``flat_model``), the perception-aware flatness-based MPC (``mpc``) and closed-loop repeat
simulation (``closed_loop``). Frames and yaw: ``perception_model.frames``."""
