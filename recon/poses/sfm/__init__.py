"""Structure from motion with COLMAP (pycolmap) on keyframes: the second estimator beside the
front end. ``mapper`` runs it and registers the frames between keyframes, ``keyframes``
chooses the images and pairs, ``model`` reads COLMAP's model, ``map_join`` joins separate
models through their shared views.
"""
