"""Stereo visual odometry: features, stereo matching, landmark matching, estimation (RANSAC, bundle
adjustment), keyframe odometry, and the compiled kernels under them (``python -m vtr.vo.kernels``)."""
