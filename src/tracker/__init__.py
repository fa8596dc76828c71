"""Synergistic hand tracking in depth images."""
