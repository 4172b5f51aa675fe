"""Figures and reports (matplotlib lives here and nowhere else)."""
