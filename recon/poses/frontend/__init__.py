"""The streaming front end (after DROID-SLAM's ``droid.py`` and ``motion_filter.py``):
``streaming`` wires the pieces; ``tracker`` adds keyframes and runs the local BA,
``motion_filter`` decides what is a keyframe, ``backend`` runs the global BA, ``filler``
gives the non-keyframes their poses, ``track_state`` holds the tracking state and
``pieces`` cuts the trajectory where a check breaks it and merges the pieces.
"""
