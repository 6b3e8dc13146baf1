"""GTSAM factors and the math they need (pure numpy + gtsam; no file I/O, no plotting)."""
