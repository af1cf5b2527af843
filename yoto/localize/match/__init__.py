"""Training-free contact localization: an exhaustive matched filter over the object surface and the sensor roll.

A GelSight contact is a small height map. Pressed at a point of the object along its normal, the sensor would
see the object's own height map there, up to the sensor's roll about the normal and a small tilt. So:

1. Once per object model, anchors every `anchor_spacing_m` on the parent cloud, each with a smoothed normal,
   a tangent frame and the object's height map over a disc of cells around it (rays cast on the mesh).
2. Per contact, the tactile cloud becomes a height image in its own tangent frame, sampled at the same
   cells for every roll. The squared height difference after removing the best plane (offset and tilt),
   for every (roll, anchor), is a handful of matrix products: a coarse pass over every anchor, then a fine
   pass over the best `shortlist`. Cells where the sensor saw nothing but the anchor's surface would have
   pushed into the gel count against the anchor (free space).
3. The best anchors after non-maximum suppression give full sensor poses on the object; each is refined by
   a damped point-to-plane ICP of the tactile points and ranked by its truncated residual (plus free-space
   violation). Beliefs come from those residuals.

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
