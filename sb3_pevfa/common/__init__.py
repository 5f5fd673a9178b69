"""Helpers that are not PeVFA-specific."""
