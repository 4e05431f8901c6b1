"""Control on the taught path: the perception field (``field``), the flat multirotor model
(``flat_model``), the perception-aware flatness-based MPC (``mpc``), closed-loop repeat
simulation (``closed_loop``) and the thesis' chapter 8 comparison of PD, flatness MPC and
discrete-time flatness control under position noise (``discrete_flatness``). Frames and yaw:
``perception_model.frames``."""
