"""Training-free contact localization: an exhaustive matched filter over the object surface and the sensor roll.

A GelSight contact is a small height map. Pressed at a point of the object along its normal, the sensor would
see the object's own height map there, up to the sensor's roll about the normal and a small tilt. So:

1. Once per object model, anchors every `anchor_spacing_m` on the parent cloud, each with a smoothed normal,
   a tangent frame and the object's height map over a disc of cells around it, and on rings around it
   (rays cast on the mesh).
2. Per contact, the tactile cloud becomes a height image in its own tangent frame. Coarse stage
   (`rings.py`): its rings' means and angular harmonic magnitudes do not depend on the sensor's roll, and
   their distance to every anchor's, a lower bound of the fine cost, is a few matrix-vector products; the
   best `shortlist` anchors go on. Fine stage: the image sampled at the cells for every roll; the squared
   height difference after removing the best plane (offset and tilt), for every (roll, anchor), is a
   handful of matrix products. Cells where the sensor saw nothing but the anchor's surface would have pushed
   into the gel count against the anchor (free space).
3. The best anchors after non-maximum suppression give full sensor poses on the object; each is refined by
   a damped point-to-plane ICP of a few tactile points, the best few again on more points, and ranked by
   its truncated residual (plus free-space violation). Beliefs come from those residuals.

No training, nothing learnt: it works on any object model the moment it is built. A contact on a featureless
region (a flat face, a cylinder) matches many places equally well; the candidates then carry that ambiguity to
the pose stage, whose joint two-contact selection resolves what geometry allows.
"""

from yoto.localize.match.anchors import AnchorMaps, MapGrid, anchor_maps, clear_cache
from yoto.localize.match.config import AnchorConfig, MatchConfig
from yoto.localize.match.localizer import MatchLocalizer
from yoto.localize.match.scores import plane_costs

__all__ = [
    "AnchorConfig",
    "AnchorMaps",
    "MapGrid",
    "MatchConfig",
    "MatchLocalizer",
    "anchor_maps",
    "clear_cache",
    "plane_costs",
]
