"""Synthetic hand image engine."""
