"""rpodguard's Python API: the trained safety chain on your own images.

    from rpodguard import load_chain
    chain = load_chain()                   # the bundled weights (default profile, rpodguard/weights/default/)
    chain = load_chain("models/")          # or your own run's shipped chain: robust pose model + its detector
    out = chain.predict(images)            # images: paths, or uint8/float arrays (N,H,W,3) or (H,W,3)

`out` (a `Prediction`) holds per image the position (m, camera frame), the quaternion (qw, qx, qy,
qz), the 6-D rotation, the detector's attack probability and its flag, or that no target is in view
(too few lit pixels: no pose). `rpod predict IMAGES...` is the same from the command line.

    track = chain.track(images, commands, attitudes)   # a sequence, with the chaser's motion per frame

`track` (a `Track`) holds per frame the defended chain's trusted estimate (world frame, m), its
protection level (m) and whether the guidance may fly on it (`rpod predict IMAGES... --motion CSV`).
"""

from rpodguard.api import Chain, Prediction, load_chain
from rpodguard.sequence import Track

__all__ = ["Chain", "Prediction", "Track", "load_chain"]
