"""Figures drawn from a model and its scenes (matplotlib, imported only when drawing)."""
