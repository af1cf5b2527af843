"""GelSight sensor model: image geometry, calibration from ball presses, image <-> height map <-> point cloud."""
