"""The dense bundle adjustment (DROID-SLAM's "dense BA" on a keyframe graph).

Owns the solver (``bundle``: residuals, robust weights, Gauss-Newton steps), its normal
equations and their Schur complement over depth (``normal_equations``, ``schur``), the
pose-only solve for frames outside the graph (``motion_only``) and the keyframe graph the
solver works on (``graph``). Imports only recon.geometry.
"""
