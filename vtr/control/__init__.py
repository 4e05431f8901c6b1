"""Control on the taught path: the perception field (``field``), the flat multirotor model
(``flat_model``), the perception-aware flatness-based MPC (``mpc``), closed-loop repeat simulation
(``closed_loop``), one route followed online by a camera thread and a control thread (``online``) and the thesis'
chapter 8 comparison of PD, flatness MPC and discrete-time flatness control under position noise
(``discrete_flatness``; its plant ``pitch_model``, outputs ``output_sources`` and sweep ``flatness_sweep``).
Frames and yaw: ``perception_model.frames``. Every part takes the direction of travel (+1 taught order, -1 the route
flown back, ``vtr.navigation.trunk``); errors of ``perception_model`` raised through the field are
``field.PerceptionFieldError`` (a ``vtr.errors.VtrError``). See docs/perception_aware_mpc/README.md and
docs/online.md."""
