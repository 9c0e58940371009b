"""Preprocessing: periods and harmonics, the declared instrument undone, drift and motion."""
