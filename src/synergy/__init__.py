"""Hand synergies from motion capture."""
