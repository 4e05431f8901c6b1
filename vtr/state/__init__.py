"""Vehicle state: the WNOA trajectory smoother (``smoothing``; its GP algebra, numpy only, in ``wnoa``) and
the controller state, reference path and path error in the gravity-aligned trunk frame (``controller``)."""
