"""The synthetic hand image engine (handsynth)."""
