"""Camera geometry shared by the pose estimators, the readers and the stages: pinhole
intrinsics (``camera``), lens distortion (``lens``), rolling shutter (``rolling_shutter``),
rigid transforms and trajectory alignment (``rigid``), SE(3)/Sim(3) Lie algebra (``lie``) and
batched projection (``projective``)."""
