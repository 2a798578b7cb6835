"""Perception: images -> bearing observations (numpy/OpenCV only)."""
