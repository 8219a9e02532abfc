"""Correspondences between frames: dense optical flow (``flow``: DIS with forward-backward
and photometric agreement) and sparse features (``features``: detection, matching, PnP).
Imports nothing else of recon.poses.
"""
