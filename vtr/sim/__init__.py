"""Synthetic stereo worlds with exact ground truth (``synthetic``)."""
