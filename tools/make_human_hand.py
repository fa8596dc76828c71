"""Regenerate models/hands/human.yaml: the default hand with the finger bases on the human metacarpal
arc (handmodel.anthropometry; provenance of the shipped file).

Usage: .venv/bin/python tools/make_human_hand.py models/hands/human.yaml [--overwrite]
"""
from __future__ import annotations

import sys

from handmodel.anthropometry import write_human_hand

if __name__ == "__main__":
    print(write_human_hand(sys.argv[1], overwrite="--overwrite" in sys.argv[2:]))
