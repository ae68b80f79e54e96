"""Loaders of recorded datasets (mrclam.py: UTIAS MR.CLAM)."""
