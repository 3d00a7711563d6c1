"""Synthetic capture pipeline, on-disk formats, datasets and readers."""
