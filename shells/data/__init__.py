"""The data side: cameras, data sets, camera paths, COLMAP."""
