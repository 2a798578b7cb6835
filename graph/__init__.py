"""Estimation core: bearing-only factor graph, landmark policies (numpy/GTSAM only)."""
