"""rpodguard's Python API: the trained safety chain on your own images.

    from rpodguard import load_chain
    chain = load_chain()                   # the bundled weights (default profile, rpodguard/weights/default/)
    chain = load_chain("models/")          # or your own run: pose model + detector + SHAP background
    out = chain.predict(images)            # images: paths, or uint8/float arrays (N,H,W,3) or (H,W,3)

`out` (a `Prediction`) holds per image the position (m, camera frame), the quaternion (qw, qx, qy,
qz), the 6-D rotation, the detector's attack probability and its flag, or that no target is in view
(too few lit pixels: no pose). `rpod predict IMAGES...` is the same from the command line.
"""
from rpodguard.api import Chain, Prediction, load_chain

__all__ = ["Chain", "Prediction", "load_chain"]
