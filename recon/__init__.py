"""recon: video -> camera poses -> depth prior -> MEDeA adjustment -> TSDF mesh.

Conventions (used everywhere in this package and in ``medea_core``):

* poses are camera-to-world 4x4 matrices (``X_world = T @ X_cam``);
* camera axes follow OpenCV: x right, y down, z forward;
* depth is z-depth in metres (not ray length); 0 marks an invalid pixel;
* intrinsics are ``fx, fy, cx, cy`` in pixels of the stored image.
"""

__version__ = "0.1.0"
