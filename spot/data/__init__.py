"""Datasets (D4RL layout), file formats, preference labels and local recipes."""
