"""Vehicle state: the WNOA trajectory smoother (``smoothing``) and the controller state, reference path
and path error in the gravity-aligned trunk frame (``controller``)."""
