"""Volumetric compensation (TF5280, manual 004)."""
