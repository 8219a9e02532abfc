"""Poses the user gave: the check that they agree with the frames (``pose_check``) and the
optional polish that refines them against the images (``polish``).
"""
