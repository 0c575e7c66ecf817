"""Scene sources: built-in generators (highway-env, SUMO) and readers of recorded data (WOMD)."""
