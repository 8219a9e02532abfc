"""Checks on an estimated trajectory that can mark it, cut it or stop a run: the tracking
quality gate (``quality``), the scale watch (``scale_watch``), the prior's agreement in scale
(``prior_agreement``), motion checks (``motion_checks``), shortened steps on plain surfaces
(``normal_flow``) and the joining of stretches across a break (``join``).
Imports the BA, matching and ``recon.poses.result`` only.
"""
