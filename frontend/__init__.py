"""Perception: images -> bearing observations (numpy/OpenCV only). Arrives with issue 4."""
