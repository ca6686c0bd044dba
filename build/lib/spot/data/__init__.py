"""Datasets (D4RL layout), file formats and preference labels (the local recipes that build them live in
spot.recipes)."""
