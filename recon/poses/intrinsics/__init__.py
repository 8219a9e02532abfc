"""The camera from the video itself when no intrinsics are given: the lens from straight
edges (``plumb_line``), the focal length from vanishing points (``vanishing``), from a
camera that only turns (``rotation_focal``) and from the BA's cost (``calib``), and the
choice among them (``focal_choice``).
"""
