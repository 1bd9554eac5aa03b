"""Worked examples of plugging an environment into lmac (see meet.py)."""
